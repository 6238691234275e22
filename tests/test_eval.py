"""The evaluator: aggregation by hand, and the command line end to end (native, CPU)."""

from __future__ import annotations

import csv
import json
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agnostos_mjx import eval as ev
from agnostos_mjx.evaluation import protocol, records, run, scheduler, summary
from agnostos_mjx.evaluation.timings import process_table, time_split_table
from agnostos_mjx.policies.oracle import OraclePolicy


def _records(task: str, split: str, seed: int, successes: list[bool]) -> list[dict]:
    return [{"task": task, "split": split, "seed": seed, "episode": i, "success": s,
             "outcome": "success" if s else "max_steps", "key_actions": 2 if s else 25,
             "sim_steps": 100 * (i + 1)} for i, s in enumerate(successes)]


def test_aggregate_matches_hand_computed_values() -> None:
    # A (Level 1): seed 0 -> 100 %, seed 1 -> 50 %.  B (Level 2): seed 0 -> 0 %, seed 1 -> 50 %.
    recs = (_records("a", "unseen_level1", 0, [True, True])
            + _records("a", "unseen_level1", 1, [True, False])
            + _records("b", "unseen_level2", 0, [False, False])
            + _records("b", "unseen_level2", 1, [False, True]))
    s = summary.aggregate(recs, ["a", "b"])
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
    md = summary.format_markdown(s)
    assert "| a | unseen_level1 | 75.0 (25.0) |" in md and "max_steps: 1" in md
    rows = {r["name"]: r for r in summary.csv_rows(s)}
    assert list(rows) == ["a", "b", "Level-1", "Level-2", "All"]
    assert rows["a"] == {"name": "a", "kind": "task", "split": "unseen_level1", "tasks": 1,
                         "seeds": 2, "episodes": 4, "successes": 3, "success_pct_mean": 75.0,
                         "success_pct_std": 25.0, "success_pct_ci_low": 30.06,
                         "success_pct_ci_high": 95.44, "success_pct_seed0": 100.0,
                         "success_pct_seed1": 50.0, "mean_key_actions": 7.75,
                         "mean_sim_steps": 150.0, "outcome_max_steps": 1, "outcome_success": 3}
    assert rows["All"]["tasks"] == 2 and rows["All"]["episodes"] == 8
    assert rows["All"]["outcome_success"] == 4 and rows["All"]["success_pct_seed0"] == 50.0


def test_variations_follow_the_protocol() -> None:
    keys = protocol.episode_keys(np.zeros(16), np.arange(16))
    assert not protocol.episode_variations(keys, 3, "unseen_level1", "protocol").any()
    seen = protocol.episode_variations(keys, 3, "seen", "protocol")
    assert seen.min() >= 0 and seen.max() < 3 and len(set(seen.tolist())) > 1
    np.testing.assert_array_equal(seen, protocol.episode_variations(keys, 3, "seen", "all"))
    assert not protocol.episode_variations(keys, 3, "seen", "zero").any()
    assert (protocol.episode_variations(keys, 3, "seen", "2") == 2).all()
    # A key depends on (seed, episode) only, not on the batch it runs in.
    np.testing.assert_array_equal(protocol.episode_keys(np.zeros(1), np.array([5]))[0], keys[5])


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("eval") / "run"
    code = ev.main(["--policy", "oracle", "--tasks", "lamp_on", "--seeds", "0", "--episodes", "2", "--batch", "2",
                    "--backend", "native", "--quiet", "--out", str(out)])
    assert code == 0
    return out


def test_time_split_accounts_for_the_task(run_dir: Path) -> None:
    """timings.jsonl: one line per task run, its stages and the rest adding up to its wall
    time, physics and policy both measured (what the GPU profile of issue 26 reads)."""
    line, process_line = (run_dir / "timings.jsonl").read_text().splitlines()
    t, process = json.loads(line), json.loads(process_line)
    assert (t["task"], t["backend"], t["episodes"]) == ("lamp_on", "native", 2)
    stages = [t[k] for k in ("build_s", "reset_s", "policy_s", "physics_s", "other_s")]
    assert all(v >= 0 for v in stages) and t["physics_s"] > 0  # the oracle's policy may round to 0
    assert sum(stages) == pytest.approx(t["wall_s"], abs=0.01)
    records = [json.loads(r) for r in (run_dir / "episodes.jsonl").read_text().splitlines()]
    assert t["live_steps"] == sum(r["sim_steps"] for r in records) > 0
    assert t["world_steps"] == sum(r["world_steps"] for r in records) >= t["live_steps"]
    assert t["rounds"] >= max(r["key_actions"] for r in records)
    assert 0 < t["start_s"] < process["startup_s"] + process["tasks_s"]
    table = time_split_table([run_dir])
    start, end = t["start_s"], t["start_s"] + t["wall_s"]
    assert f"| lamp_on | native | 2 | {t['wall_s']:.1f} | {start:.1f}-{end:.1f} |" in table
    assert f"| all | native | 2 | {t['wall_s']:.1f} | {start:.1f}-{end:.1f} |" in table
    live = f"| {t['rounds']} | {t['world_steps'] / 1e6:.3f} | "
    assert live in table.splitlines()[2], table
    # The process's own line: its start-up before the first task, then its tasks' time.
    assert (process["process"], process["tasks"]) == (0, 1)
    assert 0 < process["startup_s"] and t["wall_s"] <= process["tasks_s"] + 0.01
    # Its start-up in parts: the process's age after its imports and after its policy's
    # load; the table gives each part's own seconds.
    ages = [process["startup"][k] for k in ("imports_s", "policy_s")]
    assert 0 < ages[0] <= ages[1] <= process["startup_s"]
    row = process_table([run_dir]).splitlines()[2]
    assert row.startswith("| 0 | 1 | ") and f"| {ages[0]:.1f} |" in row
    assert len(row.split("|")) == 9  # process, tasks, start-up, 2 parts, rest, tasks s


def test_time_split_prints_a_field_a_run_lacks_as_an_empty_cell(tmp_path: Path) -> None:
    """Any run folder makes a table: a field its timings.jsonl lacks (no span, stage or
    step counts here) is an empty cell, not a crash."""
    (tmp_path / "timings.jsonl").write_text(
        json.dumps({"task": "lamp_on", "backend": "warp", "episodes": 75, "wall_s": 20.0,
                    "physics_s": 12.0, "policy_s": 5.0, "rounds": 25}) + "\n"
        + json.dumps({"process": 0, "startup_s": 4.0}) + "\n")
    table = time_split_table([tmp_path]).splitlines()
    cells = [c.strip() for c in table[2].split("|")[1:-1]]
    assert cells[:5] == ["lamp_on", "warp", "75", "20.0", ""]
    assert cells[5:11] == ["", "", "", "5.0 (25%)", "12.0 (60%)", ""]
    assert cells[11:] == ["25", "", ""]
    assert table[3].startswith("| all | warp | 75 | 20.0 |  |")
    assert process_table([tmp_path]).splitlines()[2] == "| 0 |  | 4.0 |  |  |  |  |"


def test_end_to_end_writes_results(run_dir: Path, capsys: pytest.CaptureFixture) -> None:
    for name in ("episodes.jsonl", "results.json", "results.csv", "results.md"):
        assert (run_dir / name).is_file(), name
    lines = (run_dir / "episodes.jsonl").read_text().splitlines()
    assert len(lines) == 2
    recs = [json.loads(line) for line in lines]
    assert sorted((r["seed"], r["episode"]) for r in recs) == [(0, 0), (0, 1)]
    assert all(r["success"] and r["outcome"] == "success" for r in recs)
    assert recs[0]["instruction"] == "turn on the light" and recs[0]["variation"] == 0
    results = json.loads((run_dir / "results.json").read_text())
    assert results["summary"]["tasks"]["lamp_on"]["success_mean"] == 100.0
    assert results["summary"]["groups"]["Level-1"]["success_mean"] == 100.0
    assert results["complete"] and len(results["episodes"]) == 2
    assert results["versions"]["mujoco"] and results["backend"] == "native"
    with (run_dir / "results.csv").open(newline="") as f:
        rows = {r["name"]: r for r in csv.DictReader(f)}
    assert list(rows) == ["lamp_on", "Level-1", "All"]
    assert rows["lamp_on"]["kind"] == "task" and rows["All"]["kind"] == "group"
    assert float(rows["lamp_on"]["success_pct_mean"]) == 100.0
    assert float(rows["All"]["success_pct_seed0"]) == 100.0
    assert int(rows["lamp_on"]["outcome_success"]) == 2 and rows["All"]["split"] == ""
    assert "| lamp_on | unseen_level1 | 100.0 (0.0) |" in (run_dir / "results.md").read_text()


def test_resume_does_not_rerun(run_dir: Path, monkeypatch: pytest.MonkeyPatch,
                               capsys: pytest.CaptureFixture) -> None:
    import agnostos_mjx.runtime.env

    def boom(*args, **kwargs):
        raise AssertionError("resume re-ran recorded episodes")

    monkeypatch.setattr(agnostos_mjx.runtime.env, "Episodes", boom)
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


def test_resume_ignores_a_torn_last_line(run_dir: Path, tmp_path: Path) -> None:
    """A run killed while appending leaves half a line: resume drops it, runs that
    episode again, and the file ends with whole lines only."""
    out = tmp_path / "torn"
    out.mkdir()
    first, second = (run_dir / "episodes.jsonl").read_text().splitlines()
    (out / "episodes.jsonl").write_text(first + "\n" + second[: len(second) // 2])
    assert ev.main(["--policy", "oracle", "--tasks", "lamp_on", "--seeds", "0", "--episodes",
                    "2", "--batch", "2", "--backend", "native", "--quiet", "--out", str(out),
                    "--resume"]) == 0
    recs = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert recs[0] == json.loads(first)
    assert sorted((r["seed"], r["episode"]) for r in recs) == [(0, 0), (0, 1)]


def test_load_records_keeps_the_first_of_duplicates(tmp_path: Path) -> None:
    path = tmp_path / "episodes.jsonl"
    recs = _records("a", "seen", 0, [True, False])
    records.append_records(path, recs)
    records.append_records(path, [{**recs[0], "success": False}])
    path.write_text(path.read_text() + "not json\n")
    assert records.load_records(path) == recs
    assert records.repair_records(path) == recs and path.read_text() == records.jsonl(recs)


def test_resume_command_repeats_the_options_with_out_and_resume() -> None:
    argv = ["--tasks", "lamp_on,lamp_off", "--out", "old", "--resume", "--policy-arg",
            "model=a b", "--out=older"]
    command = records.resume_command(argv, Path("results/my run"))
    assert shlex.split(command) == ["python", "-m", "agnostos_mjx.eval", "--tasks",
                                    "lamp_on,lamp_off", "--policy-arg", "model=a b", "--out",
                                    "results/my run", "--resume"]


def _one_line_error(capsys: pytest.CaptureFixture) -> str:
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: "), captured.err
    assert "Traceback" not in captured.out + captured.err
    return err


@pytest.mark.parametrize("case, expected", [
    ("unwritable", "cannot write to /proc"),
    ("file", "is not a folder"),
    ("resume_without_out", "--resume needs --out DIR, the folder of the run to continue "
                           "(the latest run is results/oracle-1)"),
    ("unknown_compare", "unknown published method 'GPT'"),
    ("unknown_policy", "cannot load policy 'no_such_module:Policy'"),
    ("existing_run", "--resume"),
    ("unknown_policy_arg", "--policy timing takes no --policy-arg sise; its options: cameras, "
                           "size, chunk, modalities, numpy, renderer"),
    ("mistyped_policy_arg", '--policy timing: --policy-arg size="big": expected an integer'),
])
def test_cli_errors_are_one_line_and_leave_no_folder(case: str, expected: str, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture) -> None:
    import agnostos_mjx.policies

    monkeypatch.chdir(tmp_path)
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "done").mkdir()
    (tmp_path / "done" / "episodes.jsonl").write_text("")
    (tmp_path / "results" / "oracle-1").mkdir(parents=True)
    (tmp_path / "results" / "oracle-1" / "episodes.jsonl").write_text("")
    if case in ("unwritable", "file", "resume_without_out", "unknown_policy_arg",
                "mistyped_policy_arg"):  # found before loading models
        def no_loading(*args, **kwargs):
            raise AssertionError("loaded the policy before checking the command line")

        monkeypatch.setattr(agnostos_mjx.policies, "make_policy", no_loading)
    args = {"unwritable": ["--out", "/proc/forbidden"], "file": ["--out", "a_file"],
            "resume_without_out": ["--resume"], "unknown_compare": ["--compare", "GPT"],
            "unknown_policy": ["--policy", "no_such_module:Policy"],
            "existing_run": ["--out", "done"],
            "unknown_policy_arg": ["--policy", "timing", "--policy-arg", "sise=1"],
            "mistyped_policy_arg": ["--policy", "timing", "--policy-arg", "size=big"]}[case]
    policy = [] if "--policy" in args else ["--policy", "oracle"]
    before = sorted(p.name for p in tmp_path.iterdir())
    assert ev.main([*policy, "--tasks", "lamp_on", "--quiet", *args]) == 2
    assert expected in _one_line_error(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no results/ folder left


def test_remove_empty_dirs_keeps_anything_with_files(tmp_path: Path) -> None:
    from agnostos_mjx.infra.cli import remove_empty_dirs

    (tmp_path / "empty" / "llm_cache" / "ab").mkdir(parents=True)
    remove_empty_dirs(tmp_path / "empty")
    assert not (tmp_path / "empty").exists()
    (tmp_path / "kept" / "llm_cache" / "ab").mkdir(parents=True)
    (tmp_path / "kept" / "llm_cache" / "ab" / "x.json").write_text("{}")
    (tmp_path / "kept" / "other").mkdir()
    remove_empty_dirs(tmp_path / "kept")
    assert (tmp_path / "kept" / "llm_cache" / "ab" / "x.json").exists()
    assert not (tmp_path / "kept" / "other").exists()


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
    # The default folder the help names is the one a run uses.
    assert "results/<policy>-<timestamp>" in " ".join(out.split())
    assert re.fullmatch(r"results/retrieval-\d{8}-\d{6}", run.default_out("retrieval").as_posix())


def test_the_command_line_is_generated_from_eval_config() -> None:
    """Every option of EvalConfig's parts is one documented option; no options means the
    defaults, and each option reaches its part's field."""
    from dataclasses import asdict

    from agnostos_mjx.evaluation.config import OPTIONS, EvalConfig, build_parser, parse_config

    options = {a.dest: a for a in build_parser()._actions if a.dest not in ("help", "spec")}
    assert sorted(options) == sorted(OPTIONS)
    assert all(a.help and a.option_strings for a in options.values())
    assert parse_config([]) == EvalConfig()
    cfg = parse_config(["--seeds", "2,0,2", "--policy-arg", "k=[1]", "--policy-arg", "s=a b",
                        "--resume", "--llm-timeout", "9", "--process-id", "1"])
    assert cfg.protocol.seeds == [2, 0] and cfg.policy.args == {"k": [1], "s": "a b"}
    assert cfg.run.resume and cfg.xicm.llm_timeout == 9.0 and cfg.run.process_id == 1
    assert EvalConfig.from_dict(asdict(cfg)) == cfg  # as merge rebuilds it
    assert EvalConfig.from_dict(cfg.options()) == cfg  # a flat config, written before the parts
    assert EvalConfig.of(**cfg.options()) == cfg
    with pytest.raises(TypeError, match="no such option: sedes"):
        EvalConfig.of(sedes=[0])


def test_a_spec_file_and_the_options_beside_it(tmp_path: Path, capsys) -> None:
    """--spec FILE: the config written there, with the options given beside it; a file
    that cannot be read is a usage error (exit 2)."""
    from agnostos_mjx.evaluation.config import EvalConfig, parse_config, write_spec

    cfg = EvalConfig.of(tasks="lamp_on", seeds=[5], policy_args={"k": [1]}, out="o")
    write_spec(tmp_path / "spec.json", cfg)
    assert parse_config(["--spec", str(tmp_path / "spec.json")]) == cfg
    assert parse_config(["--spec", str(tmp_path / "spec.json"), "--process-id", "3"]
                        ) == cfg.with_options(process_id=3)
    with pytest.raises(SystemExit) as exc:
        parse_config(["--spec", str(tmp_path / "missing.json")])
    assert exc.value.code == 2 and "--spec" in capsys.readouterr().err


# The command line as it was before EvalConfig had parts: its flags and --help's sections.
FLAGS = (
    "--action-mode --backend --batch --compare --control-hz --coordinator --ddim-steps "
    "--dense-steps --devices --episodes --execute --fail-fast --gpu-mem-fraction --help "
    "--llm-cache --llm-concurrency --llm-model --llm-server-kind --llm-timeout --llm-url "
    "--local-processes --memory --merge --mps --num-demos --num-processes --out "
    "--overlap-tasks --planner --policy --policy-arg --policy-url --process-id --quiet "
    "--renderer --resume --seeds --selection --task-queue --tasks --variations --video "
    "--video-cameras -h").split()
HELP_SECTIONS = ["positional arguments", "options", "dense control (see README, Dense control)",
                 "several devices and hosts (see README, Scale out)", "X-ICM and retrieval"]


def test_the_flags_and_help_sections_stay() -> None:
    """Splitting the config into parts keeps the command line: same flags, same sections,
    the main options in their order; the processes' --spec is not in --help."""
    import argparse

    from agnostos_mjx.evaluation.config import build_parser

    parser = build_parser()
    assert sorted(s for a in parser._actions for s in a.option_strings
                  if a.help != argparse.SUPPRESS) == FLAGS
    assert "--spec" not in parser.format_help()
    assert [g.title for g in parser._action_groups] == HELP_SECTIONS
    main = [a.option_strings[0] for a in parser._action_groups[1]._group_actions]
    assert main[:6] == ["-h", "--policy", "--policy-arg", "--policy-url",
                        "--gpu-mem-fraction", "--tasks"]


def _process_results(out: Path, config: dict, task: str, seed: int) -> None:
    """A process's folder of a two-process run, as `merge` finds it."""
    folder = out / f"proc-{seed}"
    folder.mkdir(parents=True)
    recs = _records(task, "unseen_level1", seed, [True, False])
    (folder / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    (folder / "results.json").write_text(json.dumps({
        "config": config, "policy": {"name": "oracle"}, "backend": "native",
        "renderer": None, "versions": {}, "tasks": [task], "started": "t", "finished": "t",
        "wall_s": 1.0, "episodes": recs}))


@pytest.mark.parametrize("flat", [True, False])
def test_merge_reads_flat_and_nested_configs(flat: bool, tmp_path: Path) -> None:
    """results.json written before the config had parts (a flat "config", one key per
    option, some since removed) merges as well as a nested one; the merge writes it nested."""
    from dataclasses import asdict

    from agnostos_mjx.evaluation.config import EvalConfig

    for i in (0, 1):
        cfg = EvalConfig.of(tasks="lamp_on", seeds=[0, 1], episodes=2, num_processes=2,
                            process_id=i, out=str(tmp_path), compare="X-ICM 7B")
        config = {**cfg.options(), "removed_option": 1} if flat else asdict(cfg)
        _process_results(tmp_path, config, "lamp_on", i)
    merged = summary.merge(tmp_path)
    assert merged["complete"] and len(merged["episodes"]) == 4
    assert [p["process_id"] for p in merged["processes"]] == [0, 1]
    assert merged["config"]["run"]["num_processes"] == 1
    assert merged["config"]["protocol"]["seeds"] == [0, 1]
    assert "X-ICM 7B (published)" in merged["markdown"]


def test_markdown_compare_column_and_plot(tmp_path: Path) -> None:
    from agnostos_mjx.evaluation.paper import published
    from agnostos_mjx.evaluation.report_plot import plot_summary

    recs = (_records("lamp_on", "unseen_level1", 0, [True, False])
            + _records("beat_the_buzz", "unseen_level2", 0, [False, False]))
    aggregated = summary.aggregate(recs)
    ref = published("X-ICM 72B")
    md = summary.format_markdown(aggregated, "t", ref, "X-ICM 72B")
    assert "| success % mean (std) | X-ICM 72B (published) |" in md
    assert "| lamp_on | unseen_level1 | 50.0 (0.0) | 74.7 |" in md
    assert "| All (unseen) | 2 | 25.0 (0.0) | 30.1 |" in md
    assert plot_summary(aggregated, tmp_path / "r.png", "t", ref, "X-ICM 72B")
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(KeyError, match="unknown published method"):
        published("GPT")


def test_run_interleaved_runs_others_while_one_waits():
    import concurrent.futures

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
    values = scheduler.run_interleaved([waits(), runs()], limit=2,
                             on_done=lambda i, v: finished.append((i, v)))
    assert values == ["a", "b"]
    assert events == ["a:start", "b:run", "a:end"] and finished == [(1, "b"), (0, "a")]
    done: concurrent.futures.Future = concurrent.futures.Future()
    done.set_result(None)

    def lone():
        yield done
        return "c"

    assert scheduler.run_interleaved([lone()], limit=1) == ["c"]


def test_progress_moves_with_rounds_and_prints_at_once() -> None:
    import io

    from agnostos_mjx.infra.cli import Progress

    stream = io.StringIO()
    bar = Progress(10, stream=stream)
    bar.update(0, detail="lamp_on batch 1/2 key action 1/25")
    first = stream.getvalue()
    assert first.count("\n") == 1 and "0/10 episodes  lamp_on batch 1/2" in first
    bar.update(0, detail="lamp_on batch 1/2 key action 1/25")
    assert stream.getvalue() == first  # nothing new, no line
    bar.heartbeat()
    assert stream.getvalue() == first  # drawn just now
    bar._last -= 31.0  # a step that ran for half a minute: the heartbeat shows the time
    bar.heartbeat()
    assert stream.getvalue().count("\n") == 2
    bar.update(0, partial=2.5)
    assert bar.work == 2.5 and "ETA ?" not in bar.line() and "[######" in bar.line()
    bar.update(10, partial=3.0)
    assert bar.work == 10 and stream.getvalue().count("\n") == 3  # the end always prints


REPO = Path(__file__).resolve().parents[1]


def _spawn(*args: str) -> subprocess.Popen:
    """A child Python in this repository with SIGINT's default action (a shell that starts
    the tests in the background would otherwise pass SIGINT on as ignored)."""
    reset = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
             "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])")
    return subprocess.Popen([sys.executable, "-c", reset, *args], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(predicate, proc: subprocess.Popen, timeout: float = 180.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


@pytest.mark.slow
def test_sigint_keeps_finished_episodes_and_the_printed_command_completes_the_run(
        tmp_path: Path) -> None:
    out, episodes = tmp_path / "run", 24
    log = out / "episodes.jsonl"
    proc = _spawn("-m", "agnostos_mjx.eval", "--policy", "oracle", "--tasks", "lamp_on",
                  "--seeds", "0", "--episodes", str(episodes), "--batch", "2", "--backend",
                  "native", "--out", str(out))
    _wait_for(lambda: log.exists() and log.read_text().count("\n") >= 1, proc)
    proc.send_signal(signal.SIGINT)
    start = time.monotonic()
    _, err = proc.communicate(timeout=60)
    assert time.monotonic() - start < 5.0 and proc.returncode == 130, err
    assert "Traceback" not in err and "0/24 episodes  lamp_on batch 1/12" in err
    kept = log.read_text()
    assert 1 <= kept.count("\n") < episodes
    command = shlex.split(re.search(r"to continue: (.+)", err).group(1))
    assert command[:3] == ["python", "-m", "agnostos_mjx.eval"] and command[-1] == "--resume"
    resumed = _spawn(*command[1:])
    _, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    text = log.read_text()
    assert text.startswith(kept)  # appended to, never rewritten
    keys = [(r["seed"], r["episode"]) for r in map(json.loads, text.splitlines())]
    assert sorted(keys) == [(0, e) for e in range(episodes)]  # none lost, none repeated
    assert json.loads((out / "results.json").read_text())["complete"]


_STUCK = """
import sys, time
from agnostos_mjx.infra.cli import InterruptGuard, hard_exit
with InterruptGuard(grace_s=float(sys.argv[1])) as guard:
    guard.message = "resume with: x"
    ready = False
    while True:  # a main thread that never gives up (as one inside an XLA call)
        try:
            if not ready:
                ready = True
                print("ready", flush=True)
            time.sleep(60)
        except KeyboardInterrupt:
            print("KeyboardInterrupt", flush=True)
"""


@pytest.mark.parametrize("signals, grace_s", [(1, 1.0), (2, 60.0)])
def test_interrupt_guard_exits_when_the_main_thread_is_stuck(signals: int, grace_s: float
                                                             ) -> None:
    """One Ctrl-C: out after the grace period with the message; two: out at once."""
    proc = _spawn("-c", _STUCK, str(grace_s))
    assert proc.stdout.readline() == "ready\n"
    start = time.monotonic()
    for _ in range(signals):
        proc.send_signal(signal.SIGINT)
        time.sleep(0.2)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and err == "resume with: x\n"
    assert "KeyboardInterrupt" in out and time.monotonic() - start < grace_s + 3.0


def test_run_interleaved_cancels_waiting_work_when_interrupted() -> None:
    import concurrent.futures

    waiting: concurrent.futures.Future = concurrent.futures.Future()
    closed: list[str] = []

    def waits():
        try:
            yield waiting
        finally:
            closed.append("a")

    def interrupted():
        raise KeyboardInterrupt
        yield  # noqa: B901

    with pytest.raises(KeyboardInterrupt):
        scheduler.run_interleaved([waits(), interrupted()], limit=2)
    assert waiting.cancelled() and closed == ["a"]


CRASHING_POLICY = '''
from agnostos_mjx.policies.oracle import OraclePolicy


class Crashing(OraclePolicy):
    """The oracle on lamp_off; raises on lamp_on (as a policy out of GPU memory would)."""
    name = "crashing"

    def act(self, view):
        if view.episodes.task.name == "lamp_on":
            raise RuntimeError("RESOURCE_EXHAUSTED: out of memory (test)")
        return super().act(view)
'''


@pytest.mark.parametrize("tasks, code", [("lamp_on", 3), ("lamp_on,lamp_off,turn_tap", 0)])
def test_a_policy_that_raises_is_reported_not_just_counted(tasks: str, code: int,
                                                            tmp_path: Path, capsys) -> None:
    """Episodes whose policy raised end as policy_error; when they are most of the run the
    table measures the crash, so the exit code is 3 and stderr says why (a warning else)."""
    policy = tmp_path / "crashing.py"
    policy.write_text(CRASHING_POLICY)
    rc = ev.main(["--policy", f"{policy}:Crashing", "--tasks", tasks, "--seeds", "0",
                  "--episodes", "1", "--batch", "1", "--backend", "native", "--quiet",
                  "--out", str(tmp_path / "run")])
    assert rc == code
    err = capsys.readouterr().err
    n = len(tasks.split(","))
    if code == 3:
        assert f"error: 1 of {n} episodes ended as policy_error" in err
    else:
        assert "error:" not in err
    outcomes = [json.loads(line)["outcome"]
                for line in (tmp_path / "run" / "episodes.jsonl").read_text().splitlines()]
    assert outcomes.count("policy_error") == 1


UNBATCHED_POLICY = '''
import numpy as np

from agnostos_mjx.policies import Policy
from agnostos_mjx.sim.actions import KeyActions


class Unbatched(Policy):
    """One quaternion for all worlds: numpy would broadcast it without a word."""
    name = "unbatched"

    def act(self, view):
        b = len(view.instructions)
        return KeyActions(pos=np.zeros((b, 3)), quat=np.array([1.0, 0, 0, 0]),
                          gripper=np.ones(b), valid=np.ones(b, bool))
'''


@pytest.mark.parametrize("fail_fast", [True, False])
def test_an_answer_of_the_wrong_shape_stops_the_run_in_one_line(fail_fast: bool, tmp_path: Path,
                                                                 capsys) -> None:
    """A key-action answer of other shapes than (B, 3), (B, 4), (B,), (B,) is the policy's
    bug: the run stops at its first answer with one line naming both, exit 2."""
    policy = tmp_path / "unbatched.py"
    policy.write_text(UNBATCHED_POLICY)
    rc = ev.main(["--policy", f"{policy}:Unbatched", "--tasks", "lamp_on,lamp_off", "--seeds",
                  "0", "--episodes", "2", "--batch", "2", "--backend", "native", "--quiet",
                  "--out", str(tmp_path / "run"), *(["--fail-fast"] * fail_fast)])
    err = capsys.readouterr().err
    assert rc == 2, err[-3000:]
    assert err == ("error: policy unbatched answered pos (2, 3), quat (4,), gripper (2,), "
                   "valid (2,); expected KeyActions of pos (B, 3), quat (B, 4) wxyz, gripper "
                   "(B,), valid (B,), B = 2 worlds\n")


def test_policy_error_summary_counts_and_decides(capsys) -> None:
    """Merged runs point at the processes' logs; a minority of crashes only warns."""
    crashed, fine = {"outcome": "policy_error"}, {"outcome": "success"}
    assert summary.policy_error_summary({"episodes": [fine, fine]}) == 0
    assert summary.policy_error_summary({"episodes": [crashed, fine, fine]}) == 0
    assert "error" not in capsys.readouterr().err
    merged = {"episodes": [crashed, crashed, fine], "processes": [{}, {}]}
    assert summary.policy_error_summary(merged) == 3
    err = capsys.readouterr().err
    assert "2 of 3 episodes ended as policy_error" in err and "in the logs" in err


class OracleThatWaits(OraclePolicy):
    """The oracle with `act_steps`, as a policy that waits on an LLM has: tasks run at once."""

    def act_steps(self, view):
        return self.act(view)
        yield  # noqa: B901 - a generator that waits on nothing


def test_tasks_at_once_give_the_records_of_each_task_alone(tmp_path: Path, monkeypatch) -> None:
    """Tasks run at once in one process (their native physics on the pool's threads, the
    policy on this one) record what each task records alone."""
    import threading

    from agnostos_mjx.runtime.env import Episodes

    threads: set[str] = set()
    step = Episodes.step

    def step_and_note_the_thread(self, *args, **kwargs):
        threads.add(threading.current_thread().name.rsplit("_", 1)[0])
        return step(self, *args, **kwargs)

    monkeypatch.setattr(Episodes, "step", step_and_note_the_thread)
    args = ["--policy", f"{__name__}:OracleThatWaits", "--seeds", "0", "--episodes", "2",
            "--batch", "2", "--backend", "native", "--quiet",
            "--tasks", "lamp_on,phone_on_base,push_buttons"]
    assert ev.main([*args, "--overlap-tasks", "3", "--out", str(tmp_path / "together")]) == 0
    assert threads == {"physics"}
    threads.clear()  # one task after the other, all on this thread
    assert ev.main([*args, "--overlap-tasks", "1", "--out", str(tmp_path / "alone")]) == 0
    assert threads == {"MainThread"}

    def load(folder: Path) -> dict:
        rows = [json.loads(line) for line in (folder / "episodes.jsonl").read_text().splitlines()]
        return {(r["task"], r["seed"], r["episode"]): {k: v for k, v in r.items() if k != "wall_s"}
                for r in rows}

    together = load(tmp_path / "together")
    assert len(together) == 6 and together == load(tmp_path / "alone")
    assert all(r["success"] for r in together.values())


@pytest.mark.slow  # the device planner compiled at several sizes
def test_tasks_at_once_share_the_device_planners_calls(tmp_path: Path, monkeypatch) -> None:
    """With the device planner, tasks running at once plan their key actions in shared
    calls (runtime/plan_rows.py), gathered in an order that timing cannot change: a rerun
    makes the same calls and records the same episodes.  A process fed by a task queue
    plans each task's worlds alone."""
    from agnostos_mjx.infra import gather
    from agnostos_mjx.runtime import plan_rows
    from agnostos_mjx.runtime.plan_rows import GatheredPlanner

    monkeypatch.setattr(gather, "_GATHERING", [True])  # the queue's run turns it off
    calls: list[int] = []
    original = GatheredPlanner._plan_rows

    def counted(self, rows):
        calls.append(len(rows))
        return original(self, rows)

    monkeypatch.setattr(GatheredPlanner, "_plan_rows", counted)
    monkeypatch.setattr(plan_rows, "_PLANNERS", {})  # a planner built with the counted method
    args = ["--policy", f"{__name__}:OracleThatWaits", "--seeds", "0", "--episodes", "2",
            "--batch", "2", "--backend", "native", "--planner", "device", "--quiet",
            "--tasks", "lamp_on,phone_on_base,push_buttons", "--overlap-tasks", "2"]
    assert ev.main([*args, "--out", str(tmp_path / "a")]) == 0
    first = list(calls)  # two tasks at once, the third once one has finished
    calls.clear()
    assert ev.main([*args, "--out", str(tmp_path / "b")]) == 0
    assert calls == first and max(first) == 4  # two tasks' worlds in one call

    def load(folder: Path) -> dict:
        rows = [json.loads(line) for line in (folder / "episodes.jsonl").read_text().splitlines()]
        return {(r["task"], r["seed"], r["episode"]): {k: v for k, v in r.items() if k != "wall_s"}
                for r in rows}

    assert len(load(tmp_path / "a")) == 6 and load(tmp_path / "a") == load(tmp_path / "b")
    calls.clear()
    (tmp_path / "queue").mkdir()
    queue = ["--task-queue", str(tmp_path / "queue"), "--out", str(tmp_path / "c")]
    assert ev.main([*args, *queue]) == 0
    assert max(calls) == 2  # one task's worlds a call


def test_a_failing_task_does_not_stop_the_others(tmp_path: Path, monkeypatch,
                                                capsys: pytest.CaptureFixture) -> None:
    """A task that raises is recorded in results.json's failed_tasks, named on stderr and
    in the exit code (1); the run's other tasks finish."""
    import agnostos_mjx.runtime.env as runtime_env

    class BrokenScene(runtime_env.Episodes):
        def __init__(self, task, *args, **kwargs):
            if task.name == "lamp_off":
                raise RuntimeError("scene failed to build")
            super().__init__(task, *args, **kwargs)

    monkeypatch.setattr(runtime_env, "Episodes", BrokenScene)
    out = tmp_path / "run"
    code = ev.main(["--policy", "oracle", "--tasks", "lamp_off,lamp_on", "--seeds", "0",
                    "--episodes", "2", "--batch", "2", "--backend", "native", "--quiet",
                    "--out", str(out)])
    assert code == 1
    results = json.loads((out / "results.json").read_text())
    assert results["failed_tasks"] == {"lamp_off": "RuntimeError: scene failed to build"}
    assert [r["task"] for r in results["episodes"]] == ["lamp_on", "lamp_on"]
    assert "task lamp_off failed: RuntimeError: scene failed to build" in capsys.readouterr().err


def test_a_launchers_process_ends_without_the_interpreters_teardown(monkeypatch):
    """One of a launcher's processes exits at once once main returns (its results are
    written; the launcher waits on its exit); a run typed by a user returns its code."""
    from agnostos_mjx import eval as ev

    exits = []
    monkeypatch.setattr(ev, "main", lambda guard=None: 0)
    monkeypatch.setattr(ev, "quick_exit", exits.append)
    monkeypatch.setattr(sys, "argv", ["agnostos-eval", "--spec", "s.json", "--process-id", "1"])
    ev.cli()
    assert exits == [0]
    monkeypatch.setattr(sys, "argv", ["agnostos-eval", "--tasks", "lamp_on"])
    assert ev.cli() == 0 and exits == [0]
    assert ev.launched_process(["--spec", "f", "--process-id", "0"])
    assert not ev.launched_process(["--spec", "f"])


def test_quick_exit_runs_the_exit_handlers_first(tmp_path):
    """A launcher's process skips the interpreter's teardown, not its atexit handlers (a
    policy's own cleanup, logging's flush)."""
    import subprocess

    script = ("import atexit, pathlib\n"
              "from agnostos_mjx.infra.cli import quick_exit\n"
              f"atexit.register(pathlib.Path({str(tmp_path / 'done')!r}).write_text, 'yes')\n"
              "quick_exit(3)\n")
    assert subprocess.run([sys.executable, "-c", script], timeout=60).returncode == 3
    assert (tmp_path / "done").read_text() == "yes"
