"""The measuring tools the performance reports cite (tools/task_cost.py, thread_cpu.py,
rollout_threads.py, sample_threads.py, records_diff.py, observation_split.py) give what their
docstrings say."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def _tool(name: str):
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_task_cost_prices_each_task_of_a_run(tmp_path: Path, monkeypatch, capsys) -> None:
    """World-steps x the step's cost, plus ROUND_S per round, from every process's
    timings."""
    task_cost = _tool("task_cost")
    # lamp_on's seeds ran in processes 0 and 2 (task_queue.split_by_seed).
    for i, (task, steps, rounds) in enumerate([("lamp_on", 60_000, 25), ("lamp_off", 0, 1),
                                               ("lamp_on", 40_000, 25)]):
        (tmp_path / f"proc-{i}").mkdir()
        (tmp_path / f"proc-{i}" / "timings.jsonl").write_text(
            json.dumps({"task": task, "world_steps": steps, "rounds": rounds}) + "\n"
            + json.dumps({"process": i, "startup_s": 4.0}) + "\n")
    monkeypatch.setattr(task_cost, "step_us", lambda name, batch: 50.0)
    out = tmp_path / "cost.json"
    monkeypatch.setattr(sys, "argv", ["task_cost.py", str(tmp_path), "--json", str(out)])
    task_cost.main()
    assert json.loads(out.read_text()) == {"lamp_on": 17.0, "lamp_off": 0.5}  # rounded to 0.1 s
    assert "| lamp_on | 100000 | 50.0 | 17.0 |" in capsys.readouterr().out


def test_task_cost_writes_the_queues_costs_file(tmp_path: Path, monkeypatch) -> None:
    """--write merges a run's costs into one backend's table; --wall takes the measured wall
    less --first-s for each process's first task (least start_s)."""
    task_cost = _tool("task_cost")
    costs = tmp_path / "task_costs.json"
    costs.write_text(json.dumps({"about": "x", "native": {"lamp_on": 9}, "warp": {"a": 1}}))
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "timings.jsonl").write_text("".join(
        json.dumps({"task": t, "wall_s": w, "start_s": s}) + "\n"
        for t, w, s in [("lamp_off", 30.0, 20.0), ("lamp_on", 25.0, 3.0)]))
    monkeypatch.setattr(sys, "argv", ["task_cost.py", str(tmp_path / "run"), "--wall",
                                      "--first-s", "10", "--backend", "warp",
                                      "--write", str(costs)])
    task_cost.main()
    table = json.loads(costs.read_text())
    assert table == {"about": "x", "native": {"lamp_on": 9},
                     "warp": {"lamp_off": 30.0, "lamp_on": 15.0, "a": 1}}
    assert list(table["warp"]) == ["lamp_off", "lamp_on", "a"]  # longest first


def test_task_cost_help_explains_its_flags() -> None:
    done = subprocess.run([sys.executable, str(TOOLS / "task_cost.py"), "--help"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0
    for flag in ("--backend", "--wall", "--first-s", "--write", "--json", "task_costs.json"):
        assert flag in done.stdout


def test_thread_cpu_counts_each_threads_time(tmp_path: Path) -> None:
    busy = "import time\nt = time.process_time()\nwhile time.process_time() - t < 1.5: pass"
    out = tmp_path / "threads.json"
    done = subprocess.run([sys.executable, str(TOOLS / "thread_cpu.py"), str(out), "--",
                           sys.executable, "-c", busy], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    threads = [cpu for per_pid in json.loads(out.read_text()).values()
               for _, cpu in per_pid.values()]
    assert max(threads) >= 0.9  # the busy main thread (its last 0.5 s sample)
    assert "CPU-s" in done.stdout


def test_backend_start_probe_says_how_fast_python_runs_beside_it() -> None:
    done = subprocess.run([sys.executable, str(TOOLS / "backend_start_probe.py")],
                          capture_output=True, text=True, timeout=120, cwd=TOOLS.parent)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["backend"] == "cpu" and out["import_jax_s"] > 0 and out["backend_start_s"] > 0
    assert 0 < out["main_thread_speed_share"] <= 1.5  # a share of its speed alone


@pytest.mark.slow
def test_rollout_threads_reports_each_configuration() -> None:
    done = subprocess.run([sys.executable, str(TOOLS / "rollout_threads.py"), "lamp_on", "0.3",
                           "1x1", "2x1"], capture_output=True, text=True, timeout=300,
                          cwd=TOOLS.parent)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    assert [line.split(":")[0] for line in lines] == [
        "lamp_on 1 processes x 1 threads", "lamp_on 2 processes x 1 threads"]
    assert all(float(line.split(": ")[1].split()[0]) > 0 for line in lines)


@pytest.mark.slow
def test_task_cost_times_the_physics_step_under_the_expert() -> None:
    us = _tool("task_cost").step_us("lamp_on", 2)
    assert 1.0 < us < 1000.0  # one world's step on one thread, in microseconds


def test_sample_threads_sees_every_process_and_thread(tmp_path: Path) -> None:
    """A parent that starts a child Python, whose named thread sleeps in `napping` and which
    ends by os._exit: both processes' samples are written, the thread and its function are
    in the summary, and an image's own sitecustomize still loads."""
    own = tmp_path / "own_site"
    own.mkdir()
    (own / "sitecustomize.py").write_text("import os\nos.environ['OWN_SITE'] = 'loaded'\n")
    child = ("import os, threading, time\n"
             "def napping():\n    time.sleep(0.6)\n"
             "t = threading.Thread(target=napping, name='napper'); t.start(); t.join()\n"
             "print(os.environ.get('OWN_SITE'), flush=True)\n"
             "os._exit(0)\n")
    parent = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {child!r}])"
    out = tmp_path / "out"
    env = {"PYTHONPATH": str(own)}
    run = subprocess.run([sys.executable, str(TOOLS / "sample_threads.py"), str(out), "--min-s",
                          "0.2", "--", sys.executable, "-c", parent],
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, **env})
    assert run.returncode == 0, run.stderr
    assert len(list((out / "samples").glob("*.txt"))) == 2
    assert run.stdout.startswith("loaded\n")  # the image's sitecustomize ran too
    report = run.stdout
    assert "thread napper:" in report
    napping = [line for line in report.splitlines() if line.endswith(":napping")]
    assert napping and float(napping[0].split()[0]) >= 0.4


def test_sample_threads_summarises_py_spy_samples(tmp_path: Path) -> None:
    """py-spy's raw lines (--subprocesses --threads; a process's command may span lines)
    become one sample file per process, summarised as the sampler's own: seconds are
    counts over --rate, frames are 'dir/file.py:function'."""
    raw = tmp_path / "raw.txt"
    run = "/work/agnostos_mjx/evaluation/run.py"
    raw.write_text(
        'process 1:"python -m agnostos_mjx.eval";thread (11): MainThread;'
        f'<module> (agnostos_mjx/eval.py:5);Run.run ({run}:40) 300\n'
        'process 1:"python -m agnostos_mjx.eval";process 2:"python -c \nimport x";'
        "thread (21): warp-preload;_load_warp (agnostos_mjx/render/warp.py:51) 100\n")
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, str(TOOLS / "sample_threads.py"), str(out),
                           "--py-spy", str(raw), "--rate", "100", "--min-s", "0.5"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (out / "samples").glob("*.txt")) == ["1.txt", "2.txt"]
    assert "MainThread;agnostos_mjx/eval.py:<module>;evaluation/run.py:Run.run 3.0000" in (
        out / "samples" / "1.txt").read_text()
    assert "thread MainThread: 3.0 s" in done.stdout
    assert "3.00 s  evaluation/run.py:Run.run" in done.stdout
    assert "thread warp-preload: 1.0 s" in done.stdout
    assert "1.00 s  render/warp.py:_load_warp" in done.stdout
    missing = subprocess.run([sys.executable, str(TOOLS / "sample_threads.py"), str(out),
                              "--py-spy", str(tmp_path / "none.txt")],
                             capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2 and "no such file" in missing.stderr


def _episode(task: str, episode: int, **fields) -> dict:
    return {"task": task, "seed": 0, "episode": episode, "success": False, "wall_s": 1.0,
            "llm": {"latency_ms": 3.0, "requests": 1}, **fields}


def _write_run(folder: Path, records: list[dict], gz: bool = False) -> Path:
    import gzip

    folder.mkdir()
    text = "".join(json.dumps(r) + "\n" for r in records)
    if gz:
        (folder / "episodes.jsonl.gz").write_bytes(gzip.compress(text.encode()))
    else:
        (folder / "episodes.jsonl").write_text(text)
    return folder


def test_records_diff_counts_identical_and_differing_episodes(tmp_path: Path, capsys) -> None:
    """Timing (wall_s, *_s, latencies) never counts; a field only one side has is named, not
    counted; any other difference is, with the fields named, and the exit is 1; a report's
    gzipped records read the same."""
    diff = _tool("records_diff")
    a = _write_run(tmp_path / "a", [_episode("lamp_on", 0), _episode("lamp_on", 1)])
    b = _write_run(tmp_path / "b", [_episode("lamp_on", 0, wall_s=9.0, new_field=1),
                                    _episode("lamp_on", 1, llm={"latency_ms": 7.0,
                                                                "requests": 1})], gz=True)
    assert diff.main([str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "2 episodes in both, 2 identical, 0 differ" in out
    assert "fields on one side only: new_field" in out

    c = _write_run(tmp_path / "c", [_episode("lamp_on", 0, success=True),
                                    _episode("lamp_on", 2)])
    assert diff.main([str(a), str(c)]) == 1
    out = capsys.readouterr().out
    assert "1 episodes in both, 0 identical, 1 differ, 1 only in A, 1 only in B" in out
    assert "('lamp_on', 0, 0): ['success']" in out


@pytest.mark.slow  # Warp's kernels build for its CPU backend (minutes on a fresh machine)
def test_observation_split_times_every_call_on_warps_cpu_backend(tmp_path: Path) -> None:
    """The GPU route's profile runs where warp-lang is installed (here on Warp's CPU
    backend), so a renamed call in the route breaks this test, not a GPU session."""
    pytest.importorskip("warp")
    out = tmp_path / "split.json"
    run = subprocess.run([sys.executable, str(TOOLS / "observation_split.py"), "--batch", "2",
                          "--steps", "2", "--size", "16", "--cameras", "front", "--warp-cpu",
                          "--json", str(out)], capture_output=True, text=True, timeout=1200)
    assert run.returncode == 0, run.stderr[-2000:]
    figures = json.loads(out.read_text())
    for name in ("observation_numpy", "observation_device", "bare_renderer",
                 "images_device_get", "images_pinned_host"):
        assert figures[f"{name}_ms"] > 0, name
