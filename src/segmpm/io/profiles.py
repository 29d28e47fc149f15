"""``profiles.nc``: depth profiles on (time, y), written atomically after every output time."""

from __future__ import annotations

import contextlib
import io
import sys
from pathlib import Path

import numpy as np
import xarray as xr

from ..analysis.profiles import PROFILE_VARIABLES, SCALAR_VARIABLES
from .atomic import write_with


def netcdf_bytes(ds: xr.Dataset) -> bytes:
    """``ds`` as the bytes of a NetCDF-4 (HDF5) file, built in memory.

    The file is then written with plain Python I/O: when the HDF5 library itself meets a write
    error (a full disk, a file-size limit), h5netcdf's close after the error can crash the
    interpreter (a segmentation fault in h5py), so HDF5 never writes to disk here."""
    buf = io.BytesIO()
    with _local_locks():
        ds.to_netcdf(buf, engine="h5netcdf")
    return buf.getvalue()


def _local_locks():
    """Inside a dask.distributed worker (a sweep member) xarray would guard the write with a
    distributed lock named by the file, which fails for an in-memory file: the write of one
    member's own file needs only this process's locks."""
    if "dask" not in sys.modules:
        return contextlib.nullcontext()
    import dask

    return dask.config.set(scheduler="synchronous")


def write_netcdf(path: str | Path, ds: xr.Dataset) -> None:
    """Atomically write ``ds`` to ``path`` (NetCDF-4, h5netcdf engine)."""
    data = netcdf_bytes(ds)
    write_with(path, lambda tmp: tmp.write_bytes(data))


class ProfileWriter:
    """Collects profiles at the output times and rewrites ``profiles.nc`` each time (small file)."""

    def __init__(self, path: str | Path, edges: np.ndarray, attrs: dict[str, str]):
        self.path = Path(path)
        self.edges = np.asarray(edges, dtype=np.float64)
        self.attrs = dict(attrs)
        self.times: list[float] = []
        self.rows: list[dict[str, np.ndarray]] = []
        self.scalars: list[dict[str, float]] = []

    @property
    def y(self) -> np.ndarray:
        """Bin centres, m."""
        return 0.5 * (self.edges[1:] + self.edges[:-1])

    def add(
        self, time: float, profiles: dict[str, np.ndarray], scalars: dict[str, float] | None = None
    ) -> None:
        """Append the profiles (and scalar time series) at ``time`` and rewrite the file."""
        self.times.append(float(time))
        self.rows.append({k: np.asarray(v, dtype=np.float64) for k, v in profiles.items()})
        self.scalars.append(dict(scalars or {}))
        try:
            self.write()
        except BaseException:  # the file still holds the previous times: so does the writer
            del self.times[-1], self.rows[-1], self.scalars[-1]
            raise

    def dataset(self) -> xr.Dataset:
        """The profiles as an xarray Dataset."""
        data_vars = {}
        for name, (units, long_name) in PROFILE_VARIABLES.items():
            if self.rows and name not in self.rows[0]:
                continue
            arr = (
                np.stack([r[name] for r in self.rows]) if self.rows else np.zeros((0, len(self.y)))
            )
            data_vars[name] = (("time", "y"), arr, {"units": units, "long_name": long_name})
        ds = xr.Dataset(
            data_vars,
            coords={
                "time": ("time", np.asarray(self.times), {"units": "s", "long_name": "time"}),
                "y": (
                    "y",
                    self.y,
                    {"units": "m", "long_name": "distance normal to the base (bin centre)"},
                ),
            },
            attrs=self.attrs,
        )
        ds["y_edges"] = (("y_edge",), self.edges, {"units": "m"})
        for name, (units, long_name) in SCALAR_VARIABLES.items():
            if self.scalars and all(name in sc for sc in self.scalars):
                vals = np.array([sc[name] for sc in self.scalars], dtype=np.float64)
                ds[name] = (("time",), vals, {"units": units, "long_name": long_name})
        return ds

    def write(self) -> None:
        """Atomically (re)write the NetCDF file."""
        write_netcdf(self.path, self.dataset())

    def restore(self, until: float) -> None:
        """Reload the profiles already written up to time ``until`` (resume)."""
        if not self.path.exists():
            return
        with xr.open_dataset(self.path, engine="h5netcdf") as ds:
            ds = ds.load()
        for i, t in enumerate(ds["time"].values):
            if t <= until + 1e-12:
                self.times.append(float(t))
                self.rows.append(
                    {k: ds[k].values[i] for k in PROFILE_VARIABLES if k in ds.data_vars}
                )
                self.scalars.append(
                    {k: float(ds[k].values[i]) for k in SCALAR_VARIABLES if k in ds.data_vars}
                )
