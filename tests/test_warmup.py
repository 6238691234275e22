"""The cache warm-up command (agnostos_mjx/warmup.py)."""

from __future__ import annotations

from agnostos_mjx import warmup


def test_warm_task_runs_what_a_run_runs():
    """One task's reset, first expert key action (and on warp a frame), timed."""
    result = warmup.warm_task("lamp_on", "native", batch=2)
    assert result["task"] == "lamp_on" and result["backend"] == "native"
    assert result["nv"] > 0 and result["wall_s"] >= result["reset_s"] > 0
    assert result["key_action_s"] > 0 and result["render_s"] == 0


def test_one_per_size_and_bad_task(capsys):
    names = ["lamp_on", "lamp_off", "phone_on_base"]
    picked = warmup.one_per_size(names)
    assert picked[0] == "lamp_on" and "phone_on_base" in picked
    assert len(picked) == len({p for p in picked})
    assert warmup.main(["--tasks", "lamp_on,no_such_task", "--backend", "native"]) == 2
    assert "unknown task 'no_such_task'" in capsys.readouterr().err
