"""`segmpm bench` runs the coupled step and reports its throughput (no timing assertions)."""

from __future__ import annotations

import json

from segmpm.cli import main


def test_bench_writes_json(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert (
        main(["bench", "--sizes", "600", "--threads", "1", "--steps", "20", "--json", str(out)])
        == 0
    )
    doc = json.loads(out.read_text())
    (r,) = doc["results"]
    assert r["threads"] == 1 and r["steps"] == 20
    assert 300 < r["n_points"] < 1200  # about the requested size (whole cells of the seed depth)
    assert r["particle_steps_per_s"] > 0 and r["ns_per_particle_step"] > 0
    assert "Mpart-steps/s" in capsys.readouterr().out
