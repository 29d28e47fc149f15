#!/usr/bin/env python
"""The table of docs/validation.md §3 from the completed prediction runs.

Reads validation/results/nonlocal/CASE/MODEL/{run.json,compare.json} (written by
validation/nonlocal_predictions.py and ``segmpm compare``) for every completed run and writes
validation/results/nonlocal/table.md: per case and model, velocity RMS / u_s of the DEM and the
segregation skill at each compared time, and the surface speeds.

    python validation/nonlocal_table.py
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "nonlocal"
sys.path.insert(0, str(HERE))
from nonlocal_predictions import CASES, MODELS  # noqa: E402


def _f(x: float | None, fmt: str) -> str:
    return format(x, fmt) if x is not None and math.isfinite(x) else "n/a"


def rows() -> list[dict]:
    found = []
    for case in CASES:
        for model in MODELS:
            d = OUT / case / model
            try:
                run = json.loads((d / "run.json").read_text())
                cmp = json.loads((d / "compare.json").read_text())
            except (OSError, ValueError):
                continue
            if run.get("status") != "completed":
                continue
            found.append({"case": case, "model": model, "per_time": cmp["per_time"],
                          "wall_time_s": run.get("wall_time_s")})  # fmt: skip
    return found


def table(found: list[dict]) -> str:
    lines = []
    for case in CASES:
        mine = [r for r in found if r["case"] == case]
        if not mine:
            continue
        times = list(mine[0]["per_time"])
        lines += [f"**{case}** (DEM u_s: "
                  + ", ".join(f"{_f(mine[0]['per_time'][t]['u_surface_reference'], '.3f')}"
                              for t in times) + " m/s)", "",  # fmt: skip
                  "| model | " + " | ".join(f"t = {t} s" for t in times) + " | u_s run (m/s) |",
                  "|---|" + "---|" * (len(times) + 1)]  # fmt: skip
        for r in mine:
            cells = [f"{_f(r['per_time'][t]['u_rms_rel'], '.3f')} — "
                     f"{_f(r['per_time'][t]['segregation_skill'], '.2f')}" for t in times]  # fmt: skip
            us = ", ".join(_f(r["per_time"][t]["u_surface_run"], ".3f") for t in times)
            lines.append(f"| {r['model']} | " + " | ".join(cells) + f" | {us} |")
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    found = rows()
    text = table(found)
    (OUT / "table.md").write_text(text + "\n")
    (OUT / "table.json").write_text(json.dumps(found, indent=1) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
