"""segmpm — material point method for dense granular flow with size segregation.

Python API::

    import segmpm
    cfg = segmpm.load_config("examples/chute_seed.toml", overrides=["time.end=0.5"])
    sim = segmpm.Simulation(cfg, out_dir="out")
    result = sim.run()
"""

from __future__ import annotations

__version__ = "0.1.0"

from . import _cache  # noqa: F401, E402  (before any kernel is defined: keyed Numba cache)
from .threads import configure_layer as _configure_layer  # noqa: E402

_configure_layer()  # the omp layer with a passive wait, before any parallel kernel runs
from .config import Config, ConfigError, load_config  # noqa: E402

__all__ = ["Config", "ConfigError", "Simulation", "load_config", "__version__"]


def __getattr__(name: str):
    if name == "Simulation":
        from .simulation import Simulation

        return Simulation
    raise AttributeError(name)
