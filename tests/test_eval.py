"""The evaluator: aggregation by hand, and the command line end to end (native, CPU)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agnostos_mjx import eval as ev


def _records(task: str, split: str, seed: int, successes: list[bool]) -> list[dict]:
    return [{"task": task, "split": split, "seed": seed, "episode": i, "success": s,
             "outcome": "success" if s else "max_steps", "key_actions": 2 if s else 25,
             "sim_steps": 100 * (i + 1)} for i, s in enumerate(successes)]


def test_aggregate_matches_hand_computed_values() -> None:
    # A (Level 1): seed 0 -> 100 %, seed 1 -> 50 %.  B (Level 2): seed 0 -> 0 %, seed 1 -> 50 %.
    records = (_records("a", "unseen_level1", 0, [True, True])
               + _records("a", "unseen_level1", 1, [True, False])
               + _records("b", "unseen_level2", 0, [False, False])
               + _records("b", "unseen_level2", 1, [False, True]))
    s = ev.aggregate(records, ["a", "b"])
    a, b = s["tasks"]["a"], s["tasks"]["b"]
    assert a["success_per_seed"] == {"0": 100.0, "1": 50.0}
    assert (a["success_mean"], a["success_std"]) == pytest.approx((75.0, 25.0))  # ddof = 0
    assert (b["success_mean"], b["success_std"]) == pytest.approx((25.0, 25.0))
    assert a["outcomes"] == {"success": 3, "max_steps": 1}
    assert a["mean_key_actions"] == pytest.approx((2 + 2 + 2 + 25) / 4)
    assert a["mean_sim_steps"] == pytest.approx(150.0)
    g = s["groups"]
    assert (g["Level-1"]["success_mean"], g["Level-1"]["success_std"]) == pytest.approx((75, 25))
    assert (g["Level-2"]["success_mean"], g["Level-2"]["success_std"]) == pytest.approx((25, 25))
    # All: per seed mean(100, 0) = 50 and mean(50, 50) = 50 -> 50 +- 0 (pooled std would be 35).
    assert g["All"]["success_per_seed"] == {"0": 50.0, "1": 50.0}
    assert (g["All"]["success_mean"], g["All"]["success_std"]) == pytest.approx((50.0, 0.0))
    assert "Seen" not in g
    md = ev.format_markdown(s)
    assert "| a | unseen_level1 | 75.0 (25.0) |" in md and "max_steps: 1" in md
    assert ev.format_csv(s).splitlines()[1].startswith("a,unseen_level1,4,0 1,75.0000,25.0000")


def test_variations_follow_the_protocol() -> None:
    keys = ev.episode_keys(np.zeros(16), np.arange(16))
    assert not ev.episode_variations(keys, 3, "unseen_level1", "protocol").any()
    seen = ev.episode_variations(keys, 3, "seen", "protocol")
    assert seen.min() >= 0 and seen.max() < 3 and len(set(seen.tolist())) > 1
    np.testing.assert_array_equal(seen, ev.episode_variations(keys, 3, "seen", "all"))
    assert not ev.episode_variations(keys, 3, "seen", "zero").any()
    assert (ev.episode_variations(keys, 3, "seen", "2") == 2).all()
    # A key depends on (seed, episode) only, not on the batch it runs in.
    np.testing.assert_array_equal(ev.episode_keys(np.zeros(1), np.array([5]))[0], keys[5])


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("eval") / "run"
    code = ev.main(["--policy", "oracle", "--tasks", "lamp_on", "--seeds", "0", "--episodes", "2", "--batch", "2",
                    "--backend", "native", "--quiet", "--out", str(out)])
    assert code == 0
    return out


def test_end_to_end_writes_results(run_dir: Path, capsys: pytest.CaptureFixture) -> None:
    for name in ("episodes.jsonl", "results.json", "results.csv", "results.md"):
        assert (run_dir / name).is_file(), name
    lines = (run_dir / "episodes.jsonl").read_text().splitlines()
    assert len(lines) == 2
    recs = [json.loads(line) for line in lines]
    assert [(r["seed"], r["episode"]) for r in recs] == [(0, 0), (0, 1)]
    assert all(r["success"] and r["outcome"] == "success" for r in recs)
    assert recs[0]["instruction"] == "turn on the light" and recs[0]["variation"] == 0
    results = json.loads((run_dir / "results.json").read_text())
    assert results["summary"]["tasks"]["lamp_on"]["success_mean"] == 100.0
    assert results["summary"]["groups"]["Level-1"]["success_mean"] == 100.0
    assert results["complete"] and len(results["episodes"]) == 2
    assert results["versions"]["mujoco"] and results["backend"] == "native"
    assert (run_dir / "results.csv").read_text().splitlines()[1].startswith("lamp_on,")
    assert "| lamp_on | unseen_level1 | 100.0 (0.0) |" in (run_dir / "results.md").read_text()


def test_resume_does_not_rerun(run_dir: Path, monkeypatch: pytest.MonkeyPatch,
                               capsys: pytest.CaptureFixture) -> None:
    import agnostos_mjx.episode

    def boom(*args, **kwargs):
        raise AssertionError("resume re-ran recorded episodes")

    monkeypatch.setattr(agnostos_mjx.episode, "Episodes", boom)
    before = (run_dir / "episodes.jsonl").read_text()
    args = ["--policy", "oracle", "--tasks", "lamp_on", "--seeds", "0", "--episodes", "2",
            "--batch", "2",
            "--backend", "native", "--quiet", "--out", str(run_dir)]
    assert ev.main([*args, "--resume"]) == 0
    assert (run_dir / "episodes.jsonl").read_text() == before
    out = capsys.readouterr().out
    assert out.splitlines()[0] == "agnostos_mjx.eval: policy oracle"
    assert "| lamp_on | unseen_level1 | 100.0 (0.0) |" in out
    # Without --resume an existing run is not overwritten.
    assert ev.main(args) == 2
    assert "--resume" in capsys.readouterr().err


def test_unknown_task_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert ev.main(["--tasks", "lamp_on,no_such_task", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no_such_task" in err
    assert "lamp_on" in err and "close_microwave" in err  # lists the valid names
    assert not (tmp_path / "x").exists()


def test_help(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        ev.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for flag in ("--policy", "--tasks", "--seeds", "--episodes", "--batch", "--backend",
                 "--variations", "--out", "--resume", "--quiet"):
        assert flag in out


def test_markdown_compare_column_and_plot(tmp_path: Path) -> None:
    from agnostos_mjx.paper import published
    from agnostos_mjx.report_plot import plot_summary

    records = (_records("lamp_on", "unseen_level1", 0, [True, False])
               + _records("beat_the_buzz", "unseen_level2", 0, [False, False]))
    summary = ev.aggregate(records)
    ref = published("X-ICM 72B")
    md = ev.format_markdown(summary, "t", ref, "X-ICM 72B")
    assert "| success % mean (std) | X-ICM 72B (published) |" in md
    assert "| lamp_on | unseen_level1 | 50.0 (0.0) | 74.7 |" in md
    assert "| All (unseen) | 2 | 25.0 (0.0) | 30.1 |" in md
    assert plot_summary(summary, tmp_path / "r.png", "t", ref, "X-ICM 72B")
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(KeyError, match="unknown published method"):
        published("GPT")


def test_run_interleaved_runs_others_while_one_waits():
    import concurrent.futures

    from agnostos_mjx.eval import run_interleaved

    events: list[str] = []
    gate: concurrent.futures.Future = concurrent.futures.Future()

    def waits():
        events.append("a:start")
        yield gate  # not done until b has run
        events.append("a:end")
        return "a"

    def runs():
        events.append("b:run")
        gate.set_result(None)
        return "b"
        yield  # noqa: B901

    finished = []
    values = run_interleaved([waits(), runs()], limit=2,
                             on_done=lambda i, v: finished.append((i, v)))
    assert values == ["a", "b"]
    assert events == ["a:start", "b:run", "a:end"] and finished == [(1, "b"), (0, "a")]
    done: concurrent.futures.Future = concurrent.futures.Future()
    done.set_result(None)

    def lone():
        yield done
        return "c"

    assert run_interleaved([lone()], limit=1) == ["c"]
