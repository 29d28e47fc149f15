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


def test_bench_interleaves_thread_counts(tmp_path):
    """With two thread counts the blocks alternate round by round, and the speed-up is the
    median of the within-round ratios of the block times in the JSON."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs two threads")
    out = tmp_path / "bench.json"
    args = ["bench", "--sizes", "600", "--threads", "1", "2", "--steps", "10", "--repeats", "3",
            "--no-peer", "--json", str(out)]  # fmt: skip
    assert main(args) == 0
    one, two = json.loads(out.read_text())["results"]
    assert (one["threads"], two["threads"]) == (1, 2) and one["n_points"] == two["n_points"]
    ratios = sorted(a / b for a, b in zip(one["block_wall_s"], two["block_wall_s"], strict=True))
    assert two["speedup_vs_1_threads"] == pytest.approx(ratios[1], rel=1e-12)
    assert "speedup_vs_1_threads" not in one


def test_bench_taichi_peer_runs_the_same_n():
    """The mpm88 peer (optional ``bench`` extra) runs in its own process at the requested N, with
    the grid that keeps about four particles per cell, and times one block per request."""
    pytest.importorskip("taichi")
    from segmpm.bench import Peer

    q = Peer(2000, 1, 20)
    try:
        assert q.facts["n_points"] == 2000 and q.facts["threads"] == 1
        assert q.facts["n_grid"] == round((2000 / 4) ** 0.5 / 0.4)
        walls = [q.block(), q.block()]
    finally:
        q.close()
    assert all(w > 0 for w in walls) and q.proc.returncode == 0


def test_bench_reports_the_peer_ratio_within_rounds(tmp_path):
    """With the peer, the cost ratio is the median of ours / the peer's block time per round."""
    pytest.importorskip("taichi")
    out = tmp_path / "bench.json"
    args = ["bench", "--sizes", "600", "--threads", "1", "--steps", "10", "--repeats", "3",
            "--json", str(out)]  # fmt: skip
    assert main(args) == 0
    (r,) = json.loads(out.read_text())["results"]
    q = r["taichi_mpm88"]
    assert q["n_points"] == r["n_points"] and len(q["block_wall_s"]) == 3
    ratios = sorted(a / b for a, b in zip(r["block_wall_s"], q["block_wall_s"], strict=True))
    assert r["cost_ratio_vs_taichi"] == pytest.approx(ratios[1], rel=1e-12)
    qs = r["taichi_mpm88_sorted"]  # the like-for-like peer: segmpm's sorted initial order
    assert qs["order"] == "sorted" and q["order"] == "random" and len(qs["block_wall_s"]) == 3
    ratios = sorted(a / b for a, b in zip(r["block_wall_s"], qs["block_wall_s"], strict=True))
    assert r["cost_ratio_vs_taichi_sorted"] == pytest.approx(ratios[1], rel=1e-12)


@pytest.mark.parametrize("n", [2000, 2001, 32000])
def test_peer_initial_orders(n):
    """The peer's particles fill the same block in both orders; "sorted" is a lattice in
    row-major memory order (consecutive particles are neighbours), "random" is not."""
    import numpy as np

    from segmpm.bench_taichi import initial_positions

    for order in ("random", "sorted"):
        x = initial_positions(n, 0.4, order)
        assert x.shape == (n, 2) and np.all((x > 0.2) & (x < 0.6))
        assert len(np.unique(np.round(x, 12), axis=0)) == n
    xs = initial_positions(n, 0.4, "sorted")
    assert np.all(np.diff(xs[:, 1]) >= 0)  # row by row
    row = xs[:, 1] == xs[0, 1]
    assert np.all(np.diff(xs[row, 0]) > 0)  # along each row
    step = np.hypot(*np.diff(xs, axis=0).T)
    assert np.median(step) == pytest.approx(0.4 / np.ceil(np.sqrt(n)), rel=1e-9)
    xr_ = initial_positions(n, 0.4, "random")
    assert np.median(np.hypot(*np.diff(xr_, axis=0).T)) > 10 * np.median(step)


def test_bench_times_the_nonlocal_variant_against_the_local(tmp_path):
    """--variants local nonlocal: both models at the same size, blocks interleaved, the nonlocal
    one's cost ratio the median of the within-round ratios of the two blocks; the parser's list
    of variants is the bench's."""
    import statistics

    from segmpm.bench import VARIANTS
    from segmpm.cli import BENCH_VARIANTS

    assert BENCH_VARIANTS == list(VARIANTS)

    out = tmp_path / "bench.json"
    assert main(["bench", "--sizes", "600", "--threads", "1", "--steps", "20", "--repeats", "3",
                 "--no-peer", "--variants", "local", "nonlocal", "--json", str(out)]) == 0  # fmt: skip
    loc, nl = json.loads(out.read_text())["results"]
    assert loc["variant"] == "local" and nl["variant"] == "nonlocal"
    assert loc["n_points"] == nl["n_points"]
    ratios = [a / b for a, b in zip(nl["block_wall_s"], loc["block_wall_s"], strict=True)]
    assert nl["cost_ratio_vs_local"] == pytest.approx(statistics.median(ratios))
