"""What a user opens after a run: the VTK series (read back with meshio, independent of the
writer), the profile figure and ``segmpm plot``; and the FLIP transfer, which no other test runs,
on a closed-form flow.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import matplotlib.figure
import matplotlib.image
import meshio
import numpy as np
import pytest
import xarray as xr
from conftest import make_sim

from segmpm.analysis.closed_form import bagnold_velocity
from segmpm.cli import main
from segmpm.io.figures import PANELS
from segmpm.state import D_PRESSURE

RUN = [
    "geometry.depth=0.004", "geometry.length=0.002", "time.end=0.04",
    "output.profile_times=[0.0,0.02,0.04]", "output.fields=true", "output.figures=true",
    "output.progress=false", "segregation.model='hill_tan_reduced'",
]  # fmt: skip


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    args = ["run", "chute_seed", "--out", str(out)]  # make_sim below builds on chute_seed
    for s in RUN:
        args += ["--set", s]
    assert main(args) == 0
    sim = make_sim(RUN)
    for t in (0.02, 0.04):  # the same configuration and stops: the state of the last snapshot
        sim.advance_to(t)
    return out, sim.engine


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
    # the snapshot holds the state of the run: that of an identical run, point by point
    P = st.points
    np.testing.assert_allclose(last.points[:, 0], P.x[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(last.points[:, 1], P.x[1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(last.points[:, 2], 0.0, rtol=0, atol=0)  # 2-D: the plane z = 0
    np.testing.assert_allclose(np.ravel(last.point_data["velocity_x"]), P.v[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.ravel(last.point_data["pressure"]), P.diag[D_PRESSURE],
                               rtol=1e-12)  # fmt: skip


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


def _bagnold_surface_ratio(h: float, transfer: str) -> float:
    theta, H = 26.0, 0.006
    sim = make_sim([f"geometry.slope_deg={theta}", f"geometry.depth={H}",
                    f"geometry.length={4 * h}", f"grid.cell_size={h}",
                    "boundary.sidewall_friction=0.0", "material.stiffness_scale=1e-3",
                    "segregation.model='none'", f"grid.transfer='{transfer}'"])  # fmt: skip
    sim.advance_to(0.6)
    P = sim.engine.points
    top = P.x[1].max()
    u = P.v[0][np.abs(P.x[1] - top) < 1e-9].mean()
    return u / float(bagnold_velocity(sim.config, np.array([top]))[0])


def test_flip_transfer_converges_to_the_bagnold_closed_form():
    """grid.transfer = "flip" (MUSL, FLIP/PIC blend, no affine part) is dissipative at first
    order in h on a steady shear flow: its error on the Bagnold surface speed halves when h
    halves (ratio 2 ± 0.4) and the Richardson extrapolation 2 u(h/2) − u(h) meets the closed form
    within 1 %. (The default aflip is within 0.3 % at h = 0.5 mm, tests/test_rheology_flows.)"""
    r1 = _bagnold_surface_ratio(5e-4, "flip")
    r2 = _bagnold_surface_ratio(2.5e-4, "flip")
    assert r1 < r2 < 1.0, (r1, r2)
    assert 1.6 < (1 - r1) / (1 - r2) < 2.4, (r1, r2)
    assert abs(2 * r2 - r1 - 1) < 0.01, (r1, r2)


def test_run_prints_the_estimated_steps_and_wall_time(tmp_path, capsys):
    """The CLI prints the remaining steps at the current dt and the wall time at the measured
    rate after the first steps; a run estimated above an hour gets a warning."""
    args = ["run", "--out", str(tmp_path / "o")]
    for s in ["geometry.depth=0.004", "geometry.length=0.002", "time.end=0.02",
              "output.profile_times=[0.0,0.02]", "output.fields=false", "output.figures=false",
              "output.progress=false", "time.chunk_steps=50"]:  # fmt: skip
        args += ["--set", s]
    assert main(args) == 0
    err = capsys.readouterr().err
    line = next(x for x in err.splitlines() if "more steps" in x)
    n_est = int(line.split("about ")[1].split(" more")[0].replace(",", ""))
    steps = __import__("json").loads((tmp_path / "o" / "run.json").read_text())["steps"]
    assert 0.5 * steps < n_est + 50 < 1.5 * steps, (line, steps)  # dt varies a little
    assert "more than an hour" not in err
    sim = make_sim(["geometry.depth=0.004", "geometry.length=0.002"])
    sim.advance(1.0, 5)
    assert "more than an hour" in sim._estimate(1e4, 5, 1.0)
