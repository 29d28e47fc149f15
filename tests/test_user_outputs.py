"""What a user opens after a run: the VTK series (read back with meshio, independent of the
writer), the profile figure and ``segmpm plot``; and the FLIP transfer, which no other test runs,
on a closed-form flow.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import matplotlib.figure
import matplotlib.image
import meshio
import numpy as np
import pytest
import xarray as xr
from conftest import make_sim

from segmpm.cli import main
from segmpm.io.figures import PANELS

RUN = [
    "geometry.depth=0.004", "geometry.length=0.002", "time.end=0.04",
    "output.profile_times=[0.0,0.02,0.04]", "output.fields=true", "output.figures=true",
    "output.progress=false", "segregation.model='hill_tan_reduced'",
]  # fmt: skip


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    args = ["run", "--out", str(out)]
    for s in RUN:
        args += ["--set", s]
    assert main(args) == 0
    sim = make_sim(RUN)
    sim.advance_to(0.04)  # the same configuration: the state of the last snapshot
    return out, sim.state


def test_vtk_series_reads_back_with_the_particles(finished_run):
    out, st = finished_run
    pvd = ET.parse(out / "fields" / "particles.pvd").getroot()
    sets = pvd.findall(".//DataSet")
    assert [float(d.get("timestep")) for d in sets] == [0.0, 0.02, 0.04]
    for d in sets:
        mesh = meshio.read(out / "fields" / d.get("file"))
        assert mesh.points.shape == (st.n, 3)
        for name in ("velocity_x", "velocity_y", "phi_small", "pressure", "shear_rate",
                     "stress_ratio", "fluidity"):  # fmt: skip
            assert name in mesh.point_data, (name, sorted(mesh.point_data))
            assert np.all(np.isfinite(mesh.point_data[name]))
        phi = mesh.point_data["phi_small"]
        assert np.all((phi >= 0) & (phi <= 1))
    last = meshio.read(out / "fields" / sets[-1].get("file"))
    # the snapshot holds the state of the run: positions and speeds of an identical run
    order = np.lexsort((st.x[0], st.x[1]))
    got = np.lexsort((last.points[:, 0], last.points[:, 1]))
    np.testing.assert_allclose(last.points[got, 0], st.x[0][order], rtol=0, atol=1e-12)
    np.testing.assert_allclose(last.points[got, 1], st.x[1][order], rtol=0, atol=1e-12)
    u = np.asarray(last.point_data["velocity_x"])
    np.testing.assert_allclose(u[got], st.v[0][order], rtol=0, atol=1e-12)
    p = np.asarray(last.point_data["pressure"])
    np.testing.assert_allclose(p[got], st.diag[0][order], rtol=1e-12)


def test_profile_figure_has_a_panel_per_variable(finished_run, monkeypatch):
    out, _ = finished_run
    png = out / "figures" / "profiles.png"
    head = png.read_bytes()[:8]
    assert head == b"\x89PNG\r\n\x1a\n"
    img = matplotlib.image.imread(png)
    assert img.shape[0] > 400 and img.shape[1] > 600 and img[..., :3].std() > 0.01
    seen = []
    real = matplotlib.figure.Figure.savefig

    def spy(self, *a, **k):
        seen.append([ax.get_xlabel() for ax in self.axes if ax.has_data()])
        return real(self, *a, **k)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", spy)
    assert main(["plot", str(out)]) == 0
    with xr.open_dataset(out / "profiles.nc", engine="h5netcdf") as ds:
        expected = [label for name, label in PANELS if name in ds.data_vars]
    assert seen == [expected], seen
    assert png.stat().st_size > 10_000


def test_plot_of_a_folder_without_profiles_exits_2(tmp_path):
    assert main(["plot", str(tmp_path)]) == 2


def test_flip_transfer_on_the_bagnold_closed_form():
    """grid.transfer = "flip" (no affine part): the steady Bagnold profile of the local law
    within 1 % in surface speed and RMS, as for the default transfer (tests/test_rheology_flows)."""
    theta, H, h = 26.0, 0.006, 5e-4
    sim = make_sim([f"geometry.slope_deg={theta}", f"geometry.depth={H}",
                    f"geometry.length={4 * h}", f"grid.cell_size={h}",
                    "boundary.sidewall_friction=0.0", "material.stiffness_scale=1e-3",
                    "segregation.model='none'", "grid.transfer='flip'"])  # fmt: skip
    sim.advance_to(0.6)
    st = sim.state
    rows = np.unique(np.round(st.x[1], 9))
    u = np.array([st.v[0][np.abs(st.x[1] - r) < 1e-9].mean() for r in rows])
    a, qc, f, g, dbar = 0.46, 0.38 * 2 * 0.95 / (1 + 0.95**2), 0.6, 9.81, 2.5e-3
    inert = (math.tan(math.radians(theta)) - qc) / a
    k = 2 * inert / (3 * dbar) * math.sqrt(f * g * math.cos(math.radians(theta)))
    th = k * (H**1.5 - np.clip(H - rows, 0, None) ** 1.5)
    assert abs(u[-1] / th[-1] - 1) < 0.01, (u[-1], th[-1])
    assert np.sqrt(np.mean((u - th) ** 2)) / th[-1] < 0.01
