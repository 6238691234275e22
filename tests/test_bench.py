"""The physics benchmark runs and reports its timings."""

from __future__ import annotations

import json


def test_physics_benchmark_runs_and_times(tmp_path):
    from agnostos_mjx.bench import backends as bench

    out = tmp_path / "bench.json"
    assert bench.main(["--tasks", "lamp_on", "--backends", "native", "--batches", "2",
                       "--steps", "10", "--min-time", "0.05", "--no-episodes",
                       "--out", str(out)]) == 0
    rows = json.loads(out.read_text())
    rows = rows["rows"] if isinstance(rows, dict) else rows
    assert rows and rows[0]["steps_per_s"] > 0 and rows[0]["physics_calls"] >= 1
