"""The physics benchmark runs and reports its timings."""

from __future__ import annotations

import json

import numpy as np


def test_physics_benchmark_runs_and_times(tmp_path):
    from agnostos_mjx.bench import backends as bench

    out = tmp_path / "bench.json"
    assert bench.main(["--tasks", "lamp_on", "--backends", "native", "--batches", "2",
                       "--steps", "10", "--min-time", "0.05", "--no-episodes",
                       "--out", str(out)]) == 0
    rows = json.loads(out.read_text())
    rows = rows["rows"] if isinstance(rows, dict) else rows
    assert rows and rows[0]["steps_per_s"] > 0 and rows[0]["physics_calls"] >= 1


def test_gym_env_benchmark_steps_the_vector_env(tmp_path):
    """bench.gym_env steps lerobot-eval's VectorEnv and reports env steps/s per route."""
    import pytest

    pytest.importorskip("gymnasium")
    from agnostos_mjx.bench import gym_env as bench

    out = tmp_path / "gym.json"
    assert bench.main(["--quick", "--json", str(out)]) == 0
    (row,) = json.loads(out.read_text())
    assert row["route"] == "cpu" and row["num_envs"] == 4 and row["steps"] == 5
    assert row["env_steps_per_s"] > 0 and row["ratio_to_first"] == 1.0
    held = bench.hold_rows(np.array([[0.5, 0.25, 0.75, 0, 0, 0, 1, 0.0]]))
    assert held.tolist() == [[0.5, 0.25, 0.75, 0, 0, 0, 1, 1.0]]  # same pose, gripper open
