"""tools/closed_loop_bench.py: its command line and the evaluation it types."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("closed_loop_bench",
                                                  ROOT / "tools" / "closed_loop_bench.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_run_is_typed_as_a_user_would() -> None:
    bench = _bench()
    args = bench.parse_args(["--renderers", "auto,cpu", "--chunk", "10"])
    auto = bench.eval_command(args, "auto", Path("o"))
    assert "--renderer" not in auto  # auto: the user's command, no flag
    assert auto[auto.index("--dense-steps") + 1] == "300"
    assert "chunk=10" in auto and "cameras=front,wrist" in auto
    cpu = bench.eval_command(args, "cpu", Path("o"))
    assert cpu[cpu.index("--renderer") + 1] == "cpu"
    quick = bench.parse_args(["--quick"])
    assert (quick.tasks, quick.batch, quick.renderers) == ("lamp_on", 4, "cpu")
    with pytest.raises(SystemExit):
        bench.parse_args(["--chunk", "0"])


@pytest.mark.slow
def test_quick_run_reports_the_loop_and_the_time_around_it(tmp_path: Path) -> None:
    """--quick end to end: the loop's split, the bare renderer's rate, and the run's own
    wall beside the command's (the start-up and teardown around the run)."""
    import json

    bench = _bench()
    assert bench.main(["--quick", "--json", str(tmp_path / "b.json")]) == 0
    (row,) = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert row["route"] == "cpu" and row["frames"] == 4 * 20 * 2
    assert 0 < row["run_wall_s"] <= row["wall_s"]
    assert row["bare_frames_per_s"] > 0 and row["render_s"] > 0
    assert "run's own wall s" in bench.table([row])
