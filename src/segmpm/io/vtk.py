"""Particle snapshots for ParaView: one ``.vtu`` per output time and a ``.pvd`` series file."""

from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
from pyevtk.hl import pointsToVTK

from ..state import D_DRIVER, D_INERTIAL, D_PRESSURE, D_SHEAR_RATE, State
from .atomic import remove_quietly, write_text, write_with


class VTKSeries:
    """Writes ``fields/particles_NNNN.vtu`` and keeps ``fields/particles.pvd`` up to date."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.entries: list[tuple[float, str]] = []

    def add(self, time: float, st: State, nonlocal_: bool = False) -> Path:
        """Write a snapshot of the material points at ``time`` (``nonlocal_``: the fluidity is the
        nonlocal state g, else γ̇/μ)."""
        from ..analysis.profiles import point_fluidity

        mu, g = point_fluidity(st, nonlocal_)
        data = {
            "velocity_x": np.ascontiguousarray(st.v[0]),
            "velocity_y": np.ascontiguousarray(st.v[1]),
            "phi_small": np.ascontiguousarray(st.phi),
            "pressure": np.ascontiguousarray(st.diag[D_PRESSURE]),
            "shear_rate": np.ascontiguousarray(st.diag[D_SHEAR_RATE]),
            "inertial_number": np.ascontiguousarray(st.diag[D_INERTIAL]),
            "segregation_driver": np.ascontiguousarray(st.diag[D_DRIVER]),
            "sigma_xy": np.ascontiguousarray(st.sig[2]),
            "sigma_yy": np.ascontiguousarray(st.sig[1]),
            "J": np.ascontiguousarray(st.J),
            "stress_ratio": np.ascontiguousarray(mu),
            "fluidity": np.ascontiguousarray(g),
        }
        return self.add_points(time, st.x[0], st.x[1], np.zeros(st.n), data)

    def add_points(self, time: float, x: np.ndarray, y: np.ndarray, z: np.ndarray,
                   data: dict[str, np.ndarray]) -> Path:  # fmt: skip
        """Write a snapshot of points at (x, y, z) with the point ``data`` at ``time``."""
        name = f"particles_{len(self.entries):04d}.vtu"
        data = {k: np.ascontiguousarray(v, dtype=np.float64) for k, v in data.items()}
        target = self.folder / name

        def _write(tmp: Path) -> None:
            # pyevtk appends ".vtu" to the name it is given; that file is renamed onto ``tmp`` (and
            # removed if anything fails, so no temporary .vtu is left behind)
            base = str(tmp) + ".evtk"
            written = base + ".vtu"
            try:
                pointsToVTK(base, np.ascontiguousarray(x, dtype=np.float64),
                            np.ascontiguousarray(y, dtype=np.float64),
                            np.ascontiguousarray(z, dtype=np.float64), data=data)  # fmt: skip
                os.replace(written, tmp)
            finally:
                remove_quietly(written)

        write_with(target, _write)
        self.entries.append((float(time), name))
        try:
            self._write_pvd()
        except BaseException:
            del self.entries[-1]
            raise
        return target

    def _write_pvd(self) -> None:
        rows = "\n".join(
            f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(f)}/>'
            for t, f in self.entries
        )
        text = (
            '<?xml version="1.0"?>\n'
            '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
            "  <Collection>\n" + rows + "\n  </Collection>\n</VTKFile>\n"
        )
        write_text(self.folder / "particles.pvd", text)

    def restore(self, until: float) -> None:
        """Re-list the snapshots already written up to ``until`` (resume)."""
        import xml.etree.ElementTree as ET

        pvd = self.folder / "particles.pvd"
        if not pvd.exists():
            return
        for ds in ET.parse(pvd).getroot().iter("DataSet"):
            t = float(ds.get("timestep", "nan"))
            if t <= until + 1e-12:
                self.entries.append((t, ds.get("file", "")))
