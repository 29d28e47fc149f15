"""3-D axisymmetric column collapse against the runout law of Lube et al. (2004, JFM 508, 175;
the same a^{1/2} regime as Lajeunesse, Mangeney-Castelnau & Vilotte 2004, Phys. Fluids 16, 2371):
(r∞ − r₀)/r₀ ≈ 1.24 a for a ≲ 1.7 and ≈ 1.6 a^{1/2} above, a = H₀/r₀.

The generic engine in 3-D (docs/architecture.md): one quarter of a cylinder of radius r₀ = 10 mm
with symmetry planes x = 0 and z = 0, the Fei et al. local model of the seed preset (q_c ≈ 0.38),
a no-slip rough base, no segregation. The runout r∞ is the radius that holds 99.5 % of the
points at rest (stragglers excluded). Writes validation/results/collapse3d_runout.json and .png:

    python validation/collapse3d_runout.py [--cell 1e-3] [--ratios 0.5 1 2] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from segmpm.config import load_config  # noqa: E402
from segmpm.simulation import Simulation  # noqa: E402

R0 = 0.01
OUT = pathlib.Path(__file__).parent / "results"


def experiment(a: float) -> float:
    """(r∞ − r₀)/r₀ of Lube et al. 2004 (axisymmetric)."""
    return 1.24 * a if a < 1.7 else 1.6 * math.sqrt(a)


def runout(sim: Simulation) -> float:
    x = sim.engine.points.x
    r = np.hypot(x[0], x[2])
    return float(np.quantile(r, 0.995))


def run(a: float, cell: float, threads: int) -> dict:
    H0 = a * R0
    length = math.ceil(R0 * (1.0 + 1.5 * experiment(a)) / cell + 3) * cell
    t_end = 4.0 * math.sqrt(H0 / 9.81) + 0.1
    cfg = load_config(preset="chute_seed", overrides=[
        "scenario.kind='collapse'", "geometry.dimension=3", "geometry.slope_deg=0",
        f"geometry.length={length!r}", f"geometry.column_width={R0}",
        f"geometry.column_height={H0!r}", "geometry.headroom=0.3", f"grid.cell_size={cell}",
        "material.rheology='local'", "segregation.model='none'", "boundary.base='noslip'",
        f"time.end={t_end!r}", "output.progress=false", "output.fields=false",
        f"grid.threads={threads}",
    ])  # fmt: skip
    sim = Simulation(cfg)
    t0 = time.perf_counter()
    sim.advance_to(t_end)
    wall = time.perf_counter() - t0
    P = sim.engine.points
    speed = float(np.sqrt((P.v**2).sum(axis=0)).max())
    rinf = runout(sim)
    return {"a": a, "H0": H0, "r0": R0, "cell": cell, "points": sim.engine.n, "t_end": t_end,
            "r_inf": rinf, "runout": (rinf - R0) / R0, "experiment": experiment(a),
            "max_speed_at_end": speed, "steps": sim.steps, "wall_s": wall}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cell", type=float, default=1e-3)
    ap.add_argument("--ratios", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    rows = []
    tag = "" if args.cell == 1e-3 else f"_h{args.cell:g}"
    for a in args.ratios:
        r = run(a, args.cell, args.threads)
        r["relative_error"] = r["runout"] / r["experiment"] - 1.0
        rows.append(r)
        print(f"a = {a:g}: (r∞ − r₀)/r₀ = {r['runout']:.3f}, Lube et al. {r['experiment']:.3f} "
              f"({100 * r['relative_error']:+.0f} %), {r['points']} points, {r['wall_s']:.0f} s",
              flush=True)  # fmt: skip
        (OUT / f"collapse3d_runout{tag}.json").write_text(json.dumps(rows, indent=1))
    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    aa = np.linspace(0.2, max(args.ratios) * 1.2, 100)
    ax.plot(aa, [experiment(v) for v in aa], "k-", label="Lube et al. 2004")
    ax.plot([r["a"] for r in rows], [r["runout"] for r in rows], "o", label="segmpm 3-D")
    ax.set_xlabel("a = H₀/r₀")
    ax.set_ylabel("(r∞ − r₀)/r₀")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / f"collapse3d_runout{tag}.png", dpi=120)


if __name__ == "__main__":
    main()
