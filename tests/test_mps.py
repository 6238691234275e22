"""--mps and GPU placement of --local-processes (issues 26, 29) without a GPU.

A fake ``nvidia-smi`` on PATH lists the GPUs, a fake ``nvidia-cuda-mps-control`` records
each call (arguments, standard input, the MPS variables) in a JSON-lines file and, for
``-d``, makes the pipe folder's control file as the daemon would; fake children record
their environments.  The CUDA probe (mps.PROBE) is replaced: no CUDA here."""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from agnostos_mjx.evaluation import processes
from agnostos_mjx.evaluation.config import parse_config
from agnostos_mjx.infra import mps

REPO = Path(__file__).resolve().parents[1]
KEYS = ("CUDA_VISIBLE_DEVICES", "CUDA_MPS_PIPE_DIRECTORY", "CUDA_MPS_LOG_DIRECTORY")

CONTROL = """#!{python}
import json, os, sys, time
from pathlib import Path
record = {{"argv": sys.argv[1:], "stdin": "" if "-d" in sys.argv else sys.stdin.read(),
          "time": time.time(), **{{k: os.environ.get(k) for k in {keys!r}}}}}
with open({record!r}, "a") as f:
    f.write(json.dumps(record) + "\\n")
if sys.argv[1:] == ["-d"]:
    (Path(os.environ["CUDA_MPS_PIPE_DIRECTORY"]) / "control").touch()
if record["stdin"] == "get_server_list\\n":
    print(os.environ.get("FAKE_SERVERS", "4242"))
"""

CHILD = """
import json, os, sys, time
from pathlib import Path
argv = sys.argv[1:]
spec = Path(argv[argv.index("--spec") + 1])  # the launcher's --out/run_spec.json
out, i = spec.parent, argv[argv.index("--process-id") + 1]
record = {"argv": argv, "config": json.loads(spec.read_text()),
          **{k: os.environ.get(k) for k in KEYS}}
(out / f"env-{i}.json").write_text(json.dumps(record))
time.sleep(float(os.environ.get("FAKE_SLEEP", "0")))
sys.exit(int(os.environ.get("FAKE_EXIT", "0")))
""".replace("KEYS", repr(KEYS))


@pytest.fixture
def machine(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """A function (gpus, mps_binary=True) -> the record file: fakes on PATH, no real
    GPU devices, no system MPS daemon, a probe that passes."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    record = tmp_path / "mps_calls.jsonl"
    monkeypatch.setattr(mps, "DEV", tmp_path / "dev")  # no /dev/nvidia*
    monkeypatch.setattr(mps, "DEFAULT_PIPE", str(tmp_path / "no-system-daemon"))
    monkeypatch.setattr(mps, "PROBE", "pass")
    for var in (*KEYS, "JAX_PLATFORMS", "AGNOSTOS_GPU_MEM_FRACTION"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")

    def make(gpus: int, mps_binary: bool = True) -> Path:
        if gpus:
            smi = bin_dir / "nvidia-smi"
            lines = "".join(f"echo 'GPU {k}: NVIDIA H100 80GB HBM3 (UUID: GPU-{k:04d})'\n"
                            for k in range(gpus))
            smi.write_text("#!/bin/sh\n" + lines)
            smi.chmod(0o755)
        if mps_binary:
            control = bin_dir / mps.CONTROL
            control.write_text(CONTROL.format(python=sys.executable, keys=KEYS,
                                              record=str(record)))
            control.chmod(0o755)
        return record

    return make


def calls(record: Path) -> list[dict]:
    if not record.exists():
        return []
    return [json.loads(line) for line in record.read_text().splitlines()]


def run(tmp_path: Path, n: int, mode: str, monkeypatch: pytest.MonkeyPatch, **fake: str
        ) -> tuple[int, Path, list[dict]]:
    """processes.run with fake children; (exit code, out, the children's records)."""
    for key, value in fake.items():
        monkeypatch.setenv(f"FAKE_{key.upper()}", value)
    monkeypatch.setattr(processes, "merge_main", lambda out: 0)
    tmp_path.mkdir(exist_ok=True)
    child = tmp_path / "child.py"
    child.write_text(CHILD)
    out = tmp_path / "run"
    argv = ["--policy", "oracle", "--local-processes", str(n), "--mps", mode, "--out", str(out),
            "--quiet"]
    code = processes.run(parse_config(argv), poll_s=0.02, command=[sys.executable, str(child)])
    envs = [json.loads(p.read_text()) for p in sorted(out.glob("env-*.json"),
                                                      key=lambda p: int(p.stem[4:]))]
    return code, out, envs


def test_placement_is_round_robin_and_pure(machine, tmp_path: Path,
                                           caplog: pytest.LogCaptureFixture) -> None:
    """CUDA_VISIBLE_DEVICES=0,1,2,3 and 6 processes: GPUs 0,1,2,3,0,1; --mps off starts
    nothing and warns once, with the measured numbers."""
    record = machine(4)
    caplog.set_level(logging.INFO, "agnostos_mjx.eval")
    environ = {**os.environ, "CUDA_VISIBLE_DEVICES": "0,1,2,3"}
    envs, per_gpu = processes.gpu_setup(6, tmp_path / "run", "off", environ,
                                        mps.Daemons(environ))
    assert [e["CUDA_VISIBLE_DEVICES"] for e in envs] == ["0", "1", "2", "3", "0", "1"]
    assert per_gpu == 2 and not calls(record)
    assert not any("CUDA_MPS_PIPE_DIRECTORY" in e for e in envs)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "time-slice" in warnings[0] and "4x faster" in warnings[0]
    assert mps.placement(6, 4) == [0, 1, 2, 3, 0, 1] and mps.shared([0, 1, 2, 3, 0, 1]) == [0, 1]
    assert mps.child_env({"CUDA_VISIBLE_DEVICES": "0,1"}, "1", None)["CUDA_VISIBLE_DEVICES"] == "1"
    assert mps.child_env({"A": "b"}, None, None) == {"A": "b"}


def test_visible_gpus(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """CUDA_VISIBLE_DEVICES is read as CUDA reads it; no driver or a CPU-only JAX: none."""
    bare = {"PATH": ""}  # no nvidia-smi
    monkeypatch.setattr(mps, "DEV", tmp_path)
    assert mps.visible_gpus(bare)[0] == []  # and no /dev/nvidia0
    (tmp_path / "nvidia0").touch()
    (tmp_path / "nvidia1").touch()
    (tmp_path / "nvidiactl").touch()
    assert mps.visible_gpus(bare) == (["0", "1"], "/dev/nvidia*")
    assert mps.visible_gpus({**bare, "CUDA_VISIBLE_DEVICES": "2, GPU-ab,-1,3"})[0] == [
        "2", "GPU-ab"]
    assert mps.visible_gpus({**bare, "CUDA_VISIBLE_DEVICES": ""})[0] == []
    assert mps.visible_gpus({**bare, "CUDA_VISIBLE_DEVICES": "0",
                             "JAX_PLATFORMS": "cpu"}) == ([], "JAX_PLATFORMS=cpu")
    assert mps.visible_gpus({**bare, "CUDA_VISIBLE_DEVICES": "0",
                             "JAX_PLATFORMS": "cuda,cpu"})[0] == ["0"]


@pytest.mark.parametrize("mode", ["auto", "on"])
def test_one_daemon_per_shared_gpu_started_and_stopped(mode: str, machine, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """4 GPUs, 6 processes: daemons for GPUs 0 and 1 (2 processes each), started with that
    GPU and private folders in --out/mps/gpu<K>, stopped once the processes have ended;
    their processes get the folders and no CUDA_VISIBLE_DEVICES, the others their GPU."""
    record = machine(4)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1,2,3")
    code, out, envs = run(tmp_path, 6, mode, monkeypatch)
    assert code == 0
    made = calls(record)
    starts = [c for c in made if c["argv"] == ["-d"]]
    stops = [c for c in made if c["stdin"] == "quit\n"]
    mps_dir = out.resolve() / "mps"
    assert [(c["CUDA_VISIBLE_DEVICES"], c["CUDA_MPS_PIPE_DIRECTORY"], c["CUDA_MPS_LOG_DIRECTORY"])
            for c in starts] == [(str(k), str(mps_dir / f"gpu{k}" / "pipe"),
                                  str(mps_dir / f"gpu{k}" / "log")) for k in (0, 1)]
    assert sorted(c["CUDA_MPS_PIPE_DIRECTORY"] for c in stops) == sorted(
        c["CUDA_MPS_PIPE_DIRECTORY"] for c in starts)
    assert len(made) == 4
    ended = max(p.stat().st_mtime for p in out.glob("env-*.json"))
    assert min(c["time"] for c in stops) >= ended - 1.0
    assert [e["CUDA_VISIBLE_DEVICES"] for e in envs] == [None, None, "2", "3", None, None]
    assert [e["CUDA_MPS_PIPE_DIRECTORY"] for e in envs] == [
        str(mps_dir / f"gpu{k}" / "pipe") if k in (0, 1) else None for k in (0, 1, 2, 3, 0, 1)]
    assert envs[0]["argv"] == ["--spec", str(out / "run_spec.json"), "--process-id", "0"]
    assert envs[0]["config"]["run"]["local_processes"] == 1
    fraction = envs[0]["config"]["run"]["gpu_mem_fraction"]
    assert fraction == pytest.approx(0.3)  # 0.6 over the 2 processes of a GPU


def test_single_gpu_daemon_and_child_failure(machine, tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """One GPU (from nvidia-smi): one daemon in --out/mps/pipe|log, stopped also when the
    processes fail."""
    record = machine(1)
    code, out, envs = run(tmp_path, 3, "auto", monkeypatch, exit="1")
    assert code == 1
    made = calls(record)
    pipe, logs = str(out.resolve() / "mps" / "pipe"), str(out.resolve() / "mps" / "log")
    assert [(c["argv"], c["CUDA_VISIBLE_DEVICES"], c["CUDA_MPS_PIPE_DIRECTORY"],
             c["CUDA_MPS_LOG_DIRECTORY"]) for c in made] == [
        (["-d"], "0", pipe, logs), ([], "0", pipe, logs)]
    assert len(envs) == 3 and all(
        e["CUDA_MPS_PIPE_DIRECTORY"] == pipe and e["CUDA_MPS_LOG_DIRECTORY"] == logs
        and e["CUDA_VISIBLE_DEVICES"] is None for e in envs)


def test_off_starts_nothing_and_warns_once(machine, tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch,
                                           caplog: pytest.LogCaptureFixture) -> None:
    record = machine(1)
    code, _, envs = run(tmp_path, 4, "off", monkeypatch)
    assert code == 0 and not calls(record) and len(envs) == 4
    assert all(e["CUDA_MPS_PIPE_DIRECTORY"] is None for e in envs)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "--mps off: 4 processes share one GPU" in warnings[0]


def test_no_gpu_does_nothing_and_says_so_once(machine, tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch,
                                              caplog: pytest.LogCaptureFixture,
                                              capsys: pytest.CaptureFixture) -> None:
    record = machine(0)  # the control binary is there, no GPU
    caplog.set_level(logging.INFO, "agnostos_mjx.eval")
    code, _, envs = run(tmp_path, 2, "auto", monkeypatch)
    assert code == 0 and not calls(record) and len(envs) == 2
    said = [m for m in (r.getMessage() for r in caplog.records) if "GPU" in m or "MPS" in m]
    assert said == ["no GPU visible (no NVIDIA driver (no nvidia-smi on PATH, no "
                    "/dev/nvidia0)): --mps has no effect"]
    code, _, _ = run(tmp_path / "on", 2, "on", monkeypatch)
    assert code == 2 and "error: --mps on: no GPU visible" in capsys.readouterr().err


def test_on_without_the_binary_exits_2(machine, tmp_path: Path) -> None:
    """The command line: --mps on with a GPU but no nvidia-cuda-mps-control: exit 2, one
    line, no process started."""
    machine(1, mps_binary=False)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "agnostos_mjx.eval", "--policy", "oracle", "--tasks", "lamp_on",
         "--local-processes", "2", "--mps", "on", "--out", str(out)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "error: --mps on: nvidia-cuda-mps-control is not on PATH" in proc.stderr
    assert "Traceback" not in proc.stderr and not list(out.glob("proc-*.log"))


def test_auto_falls_back_with_one_warning(machine, tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch,
                                          caplog: pytest.LogCaptureFixture) -> None:
    """No binary, or a daemon through which CUDA fails: auto warns once and runs without
    MPS (the daemons it started stopped), with each process on its GPU."""
    machine(2, mps_binary=False)
    code, _, envs = run(tmp_path / "a", 4, "auto", monkeypatch)
    assert code == 0 and [e["CUDA_VISIBLE_DEVICES"] for e in envs] == ["0", "1", "0", "1"]
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "not on PATH" in warnings[0] and "time-slice" in warnings[0]

    caplog.clear()
    record = machine(2)
    monkeypatch.setattr(mps, "PROBE", "print('CUDA error 805'); raise SystemExit(1)")
    code, _, envs = run(tmp_path / "b", 4, "auto", monkeypatch)
    assert code == 0 and [e["CUDA_MPS_PIPE_DIRECTORY"] for e in envs] == [None] * 4
    made = calls(record)
    assert [c["argv"] for c in made].count(["-d"]) == 2 == [c["argv"] for c in made].count([])
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "CUDA error 805" in warnings[0]


@pytest.mark.parametrize("servers", ["4242", ""])
def test_the_probe_must_reach_the_daemon(servers: str, machine, tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch,
                                         caplog: pytest.LogCaptureFixture) -> None:
    """After the probe's CUDA context the daemon must list an MPS server: else the context
    came up without MPS (a client that cannot reach the daemon runs without it)."""
    record = machine(1)
    monkeypatch.setattr(mps, "PROBE", "print('context ok')")
    monkeypatch.setenv("FAKE_SERVERS", servers)
    code, out, envs = run(tmp_path, 2, "auto", monkeypatch)
    assert code == 0
    assert [c["stdin"] for c in calls(record)] == ["", "get_server_list\n", "quit\n"]
    pipe = str(out.resolve() / "mps" / "pipe")
    assert [e["CUDA_MPS_PIPE_DIRECTORY"] for e in envs] == [pipe if servers else None] * 2
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    if servers:
        assert not warnings
    else:
        assert len(warnings) == 1 and "could not reach it" in warnings[0]


def test_a_running_daemon_is_used(machine, tmp_path: Path,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """A daemon answering on $CUDA_MPS_PIPE_DIRECTORY is used, not a second one started; a
    socket file nobody listens on is not a daemon."""
    record = machine(1)
    pipe = tmp_path / "sys"
    pipe.mkdir()
    monkeypatch.setenv("CUDA_MPS_PIPE_DIRECTORY", str(pipe))
    with socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET) as server:
        server.bind(str(pipe / "control"))
        server.listen()
        assert mps.running_daemon(os.environ) == pipe
        code, _, envs = run(tmp_path, 2, "on", monkeypatch)
    assert code == 0 and not calls(record)
    assert [e["CUDA_MPS_PIPE_DIRECTORY"] for e in envs] == [str(pipe)] * 2
    assert mps.running_daemon(os.environ) is None  # closed: a stale socket file


@pytest.mark.parametrize("sig", [signal.SIGINT,
                                 pytest.param(signal.SIGTERM, marks=pytest.mark.slow)])
def test_interrupt_stops_the_daemons(sig: int, machine, tmp_path: Path) -> None:
    """Ctrl-C (or SIGTERM) of the launcher: the processes are interrupted, exit 130, and
    the daemons are asked to quit."""
    record = machine(2)
    child = tmp_path / "child.py"
    child.write_text(CHILD)
    out = tmp_path / "run"
    script = textwrap.dedent(f"""
        import signal, sys
        from pathlib import Path
        # Ctrl-C raises here even when the tests run in a background shell's job, which
        # passes SIGINT on as ignored
        signal.signal(signal.SIGINT, signal.default_int_handler)
        from agnostos_mjx.infra import mps
        from agnostos_mjx.evaluation import processes
        mps.PROBE = "pass"
        mps.DEFAULT_PIPE = {str(tmp_path / "none")!r}
        from agnostos_mjx.evaluation.config import parse_config
        cfg = parse_config(["--out", {str(out)!r}, "--local-processes", "4", "--quiet"])
        sys.exit(processes.run(cfg, poll_s=0.05, command=[sys.executable, {str(child)!r}]))
    """)
    env = {**os.environ, "PYTHONPATH": str(REPO), "FAKE_SLEEP": "60"}
    parent = subprocess.Popen([sys.executable, "-c", script], env=env, cwd=REPO,
                              stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while len(list(out.glob("env-*.json"))) < 4 and time.monotonic() < deadline:
        time.sleep(0.1)
    parent.send_signal(sig)
    _, err = parent.communicate(timeout=120)
    assert parent.returncode == 130, err
    made = calls(record)
    assert [c["argv"] for c in made].count(["-d"]) == 2
    assert sorted(c["CUDA_MPS_PIPE_DIRECTORY"] for c in made if c["stdin"] == "quit\n") == [
        str(out.resolve() / "mps" / f"gpu{k}" / "pipe") for k in (0, 1)]


def test_long_out_paths_get_a_short_pipe_folder(machine, tmp_path: Path) -> None:
    """A pipe folder whose socket path would not fit a UNIX socket address moves to /tmp
    (and is removed when the daemon has stopped); its log stays in --out."""
    record = machine(1)
    out = tmp_path / ("x" * 120)
    daemons = mps.Daemons(os.environ)
    daemons.start(out, ["0"], [0])
    (started,) = daemons.running.values()
    assert str(started.pipe).startswith("/tmp/agnostos-mps-gpu0-")
    assert started.log == out.resolve() / "mps" / "log"
    daemons.close()
    assert not started.pipe.exists()
    assert [c["CUDA_MPS_PIPE_DIRECTORY"] for c in calls(record)] == [str(started.pipe)] * 2


def test_cli_option() -> None:
    from agnostos_mjx.evaluation.config import parse_config

    assert parse_config([]).run.mps == "auto" and parse_config(["--mps", "off"]).run.mps == "off"
    with pytest.raises(SystemExit):
        parse_config(["--mps", "maybe"])


def test_default_process_count_follows_the_gpus_and_cores(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """--local-processes by default: 8 per GPU, at most 16 and half the cores; 1 without a
    GPU and for a process of a larger run."""
    from agnostos_mjx.evaluation import processes
    from agnostos_mjx.evaluation.config import EvalConfig
    from agnostos_mjx.infra import settings

    monkeypatch.setattr(mps, "DEV", tmp_path)  # no /dev/nvidia*
    bare = {"PATH": ""}
    cfg = EvalConfig()
    assert processes.default_count(cfg, bare)[0] == 1
    (tmp_path / "nvidia0").touch()
    (tmp_path / "nvidiactl").touch()
    for cores, gpus, expected in ((16, "0", 8), (32, "0,1", 16), (64, "0,1,2,3", 16),
                                  (4, "0", 2), (2, "0", 1)):
        monkeypatch.setattr(settings, "usable_cores", lambda c=cores: c)
        env = {**bare, "CUDA_VISIBLE_DEVICES": gpus}
        assert processes.default_count(cfg, env)[0] == expected, (cores, gpus)
    env = {**bare, "CUDA_VISIBLE_DEVICES": "0"}
    assert processes.default_count(EvalConfig.of(num_processes=4, process_id=1), env)[0] == 1
    assert processes.default_count(EvalConfig.of(resume=True), env)[0] == 1
    monkeypatch.setattr(settings, "usable_cores", lambda: 16)
    few = EvalConfig.of(tasks="lamp_on,close_jar", seeds=[0])  # one process per (task, seed)
    assert processes.default_count(few, env)[0] == 2
