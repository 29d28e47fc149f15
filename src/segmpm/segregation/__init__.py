"""Species transport of the binary mixture: extra Eulerian concentration grid and closures.

The compiled step is the engine's (``engine/kernels.py``, called by the time loop once per
subcycle); :func:`concentration_step` (grid.py) runs its 2-D version on plain arrays;
:mod:`closures` holds the flux closures and the parameter vector layout; :mod:`reference` is a
plain NumPy twin of the step; :mod:`diagnostics` has the NumPy measures
used between output chunks. Model and numerics: docs/segregation.md.
"""

from segmpm.segregation.closures import (
    MODEL_CODES,
    N_PARAMS,
    conc_cell_size,
    make_params,
    pack_params,
)
from segmpm.segregation.grid import ConcGrid, allocate_work, concentration_step, make_conc_grid

__all__ = [
    "MODEL_CODES",
    "N_PARAMS",
    "ConcGrid",
    "allocate_work",
    "conc_cell_size",
    "concentration_step",
    "make_conc_grid",
    "make_params",
    "pack_params",
]
