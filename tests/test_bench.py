"""`segmpm bench` runs the coupled step and reports its throughput (no timing assertions)."""

from __future__ import annotations

import json

import pytest

from segmpm.cli import main


def test_bench_writes_json(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert (
        main(
            [
                "bench",
                "--sizes",
                "600",
                "--threads",
                "1",
                "--steps",
                "20",
                "--repeats",
                "3",
                "--no-peer",
                "--json",
                str(out),
            ]
        )  # fmt: skip
        == 0
    )
    doc = json.loads(out.read_text())
    (r,) = doc["results"]
    assert r["threads"] == 1 and r["steps"] == 20 and r["repeats"] == 3
    # the reported cost is the median of the three timed blocks, the best one is their minimum
    walls = sorted(r["block_wall_s"])
    assert len(walls) == 3 and r["wall_s"] == walls[1]
    assert r["best_ns_per_particle_step"] == pytest.approx(walls[0] / (20 * r["n_points"]) * 1e9)
    assert 300 < r["n_points"] < 1200  # about the requested size (whole cells of the seed depth)
    assert r["particle_steps_per_s"] > 0 and r["ns_per_particle_step"] > 0
    assert "Mpart-steps/s" in capsys.readouterr().out


def test_bench_taichi_peer_runs_the_same_n():
    """The mpm88 peer (optional ``bench`` extra) runs in its own process at the requested N and
    reports its cost with the grid that keeps about four particles per cell."""
    pytest.importorskip("taichi")
    from segmpm.bench import peer_case

    q = peer_case(2000, 1, 20, 2)
    assert q is not None and q["n_points"] == 2000 and q["steps"] == 20 and q["repeats"] == 2
    assert q["ns_per_particle_step"] > 0 and q["n_grid"] == round((2000 / 4) ** 0.5 / 0.4)
