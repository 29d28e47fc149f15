"""Column-collapse runout against the experimental scaling (docs/validation.md §2).

Runs the `collapse` scenario (Fei et al. model, rough base, free-slip back wall, no sidewall
friction, no segregation) for aspect ratios a = H0/L0 from 0.5 to 6 and compares the normalised
runout (L∞ − L0)/L0 with the rectangular-channel experiments of Lube et al. (2005) and Lajeunesse,
Monnier & Homsy (2005): ≈ 1.2 a for a ≲ 2.8 and ≈ 1.9 a^{2/3} above. Writes
validation/results/collapse_runout.json and .png. Usage:
    python validation/collapse_runout.py [--cell 5e-4] [--ratios 0.5 1 2 3 4 6] [--base friction]
A cell size other than the default writes collapse_runout_h<cell>.{json,png} (resolution check).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from segmpm.config import load_config  # noqa: E402
from segmpm.simulation import Simulation  # noqa: E402

L0 = 0.01
H_CELL = 5e-4
OUT = pathlib.Path(__file__).parent / "results"


def experiment(a: float) -> float:
    """(L∞ − L0)/L0 of Lube et al. 2005 / Lajeunesse et al. 2005 (rectangular channels)."""
    return 1.2 * a if a < 2.8 else 1.9 * a ** (2.0 / 3.0)


def front(sim: Simulation) -> float:
    """Front of the deposit: the largest x where the layer is at least one point thick."""
    x, y = sim.engine.points.x
    order = np.sort(x)
    return float(order[-3]) if order.size > 3 else float(order[-1])


def run(a: float, H_CELL: float = H_CELL, base: str = "noslip", base_mu: float = 0.5) -> dict:
    H0 = a * L0
    length = L0 * (2.0 + 1.6 * experiment(a))
    length = math.ceil(length / H_CELL) * H_CELL
    t_end = 4.0 * math.sqrt(H0 / 9.81) + 0.1
    cfg = load_config(preset="chute_seed", overrides=[
        "scenario.kind='collapse'", "geometry.slope_deg=0", f"geometry.length={length!r}",
        f"geometry.column_width={L0}", f"geometry.column_height={H0!r}", "geometry.headroom=0.3",
        f"grid.cell_size={H_CELL}", "material.stiffness_scale=1e-3", "segregation.model='none'",
        "boundary.sidewall_friction=0", f"boundary.base='{base}'", f"boundary.base_friction={base_mu!r}", "boundary.walls='slip'",
        f"time.end={t_end!r}", "output.progress=false", "output.fields=false",
    ])  # fmt: skip
    sim = Simulation(cfg)
    t0 = time.perf_counter()
    history = []
    for k in range(1, 41):
        sim.advance_to(t_end * k / 40)
        P = sim.engine.points
        ke = 0.5 * float(np.sum(P.mass * (P.v**2).sum(0)))
        history.append((sim.time, front(sim), ke))
    runout = (front(sim) - L0) / L0
    return {
        "aspect_ratio": a,
        "runout": runout,
        "experiment": experiment(a),
        "relative_error": runout / experiment(a) - 1,
        "final_height": float(sim.engine.points.x[1].max()) / L0,
        "kinetic_energy_final_over_max": history[-1][2] / max(h[2] for h in history),
        "wall_s": time.perf_counter() - t0,
        "n_points": sim.engine.n,
    }


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cell", type=float, default=H_CELL)
    ap.add_argument("--ratios", type=float, nargs="+", default=[0.5, 1.0, 2.0, 3.0, 4.0, 6.0])
    ap.add_argument("--base", choices=["noslip", "friction", "slip"], default="noslip")
    ap.add_argument("--base-friction", type=float, default=0.5)
    args = ap.parse_args()
    stem = "collapse_runout" if args.cell == H_CELL else f"collapse_runout_h{args.cell:g}"
    if args.base != "noslip":
        stem += (
            f"_{args.base}{args.base_friction:g}" if args.base == "friction" else f"_{args.base}"
        )
    OUT.mkdir(exist_ok=True)
    results = []
    for a in args.ratios:
        r = run(a, args.cell, args.base, args.base_friction)
        results.append(r)
        print(f"a = {a:4.1f}: runout {r['runout']:6.2f} vs experiment {r['experiment']:6.2f} "
              f"({100 * r['relative_error']:+5.1f} %), KE end/max {r['kinetic_energy_final_over_max']:.1e}, "
              f"{r['wall_s']:.0f} s", flush=True)  # fmt: skip
        (OUT / f"{stem}.json").write_text(
            json.dumps(
                {
                    "L0": L0,
                    "h": args.cell,
                    "base": args.base,
                    "base_friction": args.base_friction,
                    "results": results,
                },
                indent=2,
            )  # fmt: skip
        )
    a = np.array([r["aspect_ratio"] for r in results])
    fig, ax = plt.subplots(figsize=(5, 4))
    aa = np.linspace(0.3, 7, 200)
    ax.plot(aa, [experiment(v) for v in aa], "k-", label="Lube 2005 / Lajeunesse 2005")
    ax.fill_between(aa, [0.8 * experiment(v) for v in aa], [1.2 * experiment(v) for v in aa],
                    color="0.85", label="±20 %")  # fmt: skip
    ax.plot(a, [r["runout"] for r in results], "ro", label="segmpm")
    ax.set_xlabel("aspect ratio a = H0/L0")
    ax.set_ylabel("(L∞ − L0)/L0")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / f"{stem}.png", dpi=120)
    worst = max(abs(r["relative_error"]) for r in results)
    print(f"largest relative error {100 * worst:.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
