"""Particle snapshots for ParaView: one ``.vtu`` per output time and a ``.pvd`` series file."""

from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
from pyevtk.hl import pointsToVTK

from .atomic import remove_quietly, write_text, write_with


class VTKSeries:
    """Writes ``fields/particles_NNNN.vtu`` and keeps ``fields/particles.pvd`` up to date."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.entries: list[tuple[float, str]] = []

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
