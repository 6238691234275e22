"""Scale-out (issue 16) on CPU: batches sharded over 4 fake host devices give the same
results as one device, and a two-process run merges into one process's records.

XLA_FLAGS must be set before JAX starts, so the sharded checks run in a child Python."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

PLACEMENT = """
import jax, numpy as np
from agnostos_mjx.infra import sharding
assert len(jax.devices()) == 4
tree = {"a": np.arange(5.0), "b": np.arange(10).reshape(5, 2)}
placed, n = sharding.shard(tree)
assert n == 5 and placed["a"].shape == (8,) and placed["b"].shape == (8, 2)
assert len(placed["a"].sharding.device_set) == 4
assert [s.data.shape for s in placed["b"].addressable_shards] == [(2, 2)] * 4
np.testing.assert_array_equal(placed["a"][5:], [4.0] * 3)  # the last row repeated
back = sharding.unpad(placed, n)
np.testing.assert_array_equal(back["b"], tree["b"])
sharding.configure(1)
same, _ = sharding.shard(tree)
assert same is tree  # one device: the single-device path, untouched
sharding.configure(None)
"""

FEATURES = """
from dataclasses import replace
import numpy as np
from flax import nnx
from agnostos_mjx.infra import sharding
from agnostos_mjx.dynamics.autoencoder import Autoencoder
from agnostos_mjx.dynamics.config import AE_QUICK, DIFFUSION_QUICK, TEXT_QUICK, UNET_QUICK
from agnostos_mjx.dynamics.data import synthetic
from agnostos_mjx.dynamics.diffusion import DynamicsModel
from agnostos_mjx.dynamics.features import extract
from agnostos_mjx.dynamics.layers import create
from agnostos_mjx.dynamics.pipeline import Pipeline

ae = create(lambda: Autoencoder(AE_QUICK, rngs=nnx.Rngs(0)))
model = create(lambda: DynamicsModel(TEXT_QUICK, UNET_QUICK, rngs=nnx.Rngs(1)))
pipe = Pipeline(ae, 0.5, model, TEXT_QUICK, replace(DIFFUSION_QUICK, sample_steps=2), chunk=8)
pairs = synthetic(6, seed=0)  # 6 queries: padded to 8, 2 per device
features = {}
for devices in (1, 4):
    sharding.configure(devices)
    features[devices] = extract(pipe, pairs.first, list(pairs.instructions))
# Equal to float32 rounding: XLA compiles the 2-query-per-device program differently from
# the 8-query one, and on some CPUs (this project's 2-core machines) the
# features then differ in the last bits (measured: 3e-8 in vis.in).
for part, value in features[1].items():
    np.testing.assert_allclose(features[4][part], value, rtol=0, atol=1e-6, err_msg=part)
"""

MJX = """
import jax, numpy as np
from agnostos_mjx.infra import sharding
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.physics.mjx_backend import MjxBackend
from agnostos_mjx.tasks import get_task

ep = Episodes(get_task("lamp_on"), "native")
keys = jax.vmap(lambda e: jax.random.fold_in(jax.random.PRNGKey(0), e))(np.arange(3))
state = ep.reset(keys, [0, 0, 0]).physics
nu = ep.scene.model.nu
ctrl = np.asarray(state.ctrl)[:, None, :] + 0.05 * np.random.default_rng(0).standard_normal(
    (3, 12, nu))
steps = np.array([12, 7, 0])
out = {}
for devices in (1, 4):
    sharding.configure(devices)
    backend = MjxBackend(ep.scene.model, impl="jax")
    assert (backend.mesh is None) == (devices == 1)
    out[devices] = jax.device_get(backend.run(state, ctrl, steps))
# Equal to float32 rounding, not bit for bit: XLA compiles the 1-world-per-device program
# differently from the 3-world one (measured: at most 1.6e-7 apart after 12 steps).
for a, b in zip(jax.tree.leaves(out[1]), jax.tree.leaves(out[4])):
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-5)
"""

KEY_ACTION = """
import jax, numpy as np
from agnostos_mjx.infra import sharding
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.tasks import get_task

keys = jax.vmap(lambda e: jax.random.fold_in(jax.random.PRNGKey(0), e))(np.arange(3))
out = {}
for devices in (1, 4):
    sharding.configure(devices)
    ep = Episodes(get_task("lamp_on"), "jax")  # the device key-action step, worlds sharded
    assert (ep.backend.mesh is None) == (devices == 1)
    env = ep.reset(keys, [0, 0, 0])
    expert = ep.expert_actions(env)
    env, _ = ep.step(env, jax.tree.map(lambda x: np.asarray(x)[:, 0], expert))
    out[devices] = (env.outcome, env.sim_steps, np.asarray(env.obs.data))
np.testing.assert_array_equal(out[4][0], out[1][0])
np.testing.assert_array_equal(out[4][1], out[1][1])
np.testing.assert_allclose(out[4][2], out[1][2], rtol=0, atol=1e-3)
"""


def run_on_4_devices(code: str, timeout: float) -> None:
    """Run `code` in a child Python that sees 4 CPU devices; fail with its output."""
    # With this process's XLA flags (conftest's configure_jax) as the package's commands set them.
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4"
    env = {**os.environ, "XLA_FLAGS": flags.strip(),
           "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_shard_pads_and_places_the_batch_over_devices() -> None:
    run_on_4_devices(PLACEMENT, timeout=60)


@pytest.mark.slow
def test_sharded_features_equal_one_device() -> None:
    run_on_4_devices(FEATURES, timeout=120)


@pytest.mark.slow
@pytest.mark.mjx_cpu  # MJX-jax's own physics compiled on the CPU
def test_sharded_mjx_jax_run_equals_one_device() -> None:
    """Two MJX-jax compiles on CPU (slow)."""
    run_on_4_devices(MJX, timeout=600)


@pytest.mark.slow
@pytest.mark.mjx_cpu  # MJX-jax's own physics compiled on the CPU
def test_sharded_key_action_step_equals_one_device() -> None:
    """The device key-action step (key_action.py) with its worlds split over 4 devices
    (3 worlds padded to 4) gives one device's outcomes (MJX-jax compiles: minutes)."""
    run_on_4_devices(KEY_ACTION, timeout=1800)


EVAL = ["--policy", "oracle", "--tasks", "lamp_on,lamp_off", "--seeds", "0", "--episodes", "2",
        "--batch", "2", "--backend", "native", "--quiet"]


def _default_sigint() -> None:
    """In the child before Python starts: SIGINT's default action, so that Python installs
    its Ctrl-C handler (a background shell job passes SIGINT on as ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _eval(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", "agnostos_mjx.eval", *EVAL, *args], cwd=REPO,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, preexec_fn=_default_sigint)


def _finish(proc: subprocess.Popen) -> None:
    output, _ = proc.communicate(timeout=300)
    assert proc.returncode == 0, output


def _episodes(out: Path) -> list[dict]:
    """The records without their timing, which differs between runs."""
    lines = (out / "episodes.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k != "wall_s"} for line in lines]


def _episodes_or_none(out: Path) -> list[dict]:
    return _episodes(out) if (out / "episodes.jsonl").exists() else []


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.mark.slow
@pytest.mark.parametrize("cluster", [False, True], ids=["static", "jax-distributed"])
def test_two_processes_merge_into_the_records_of_one(cluster: bool, tmp_path: Path) -> None:
    from agnostos_mjx.eval import main

    shared, single = tmp_path / "shared", tmp_path / "single"
    extra = ["--coordinator", f"localhost:{_free_port()}"] if cluster else []
    procs = [_eval("--out", str(shared), "--num-processes", "2", "--process-id", str(i),
                   *extra) for i in range(2)]
    for proc in procs:
        _finish(proc)
    assert [r["task"] for r in _episodes(shared / "proc-1")] == ["lamp_off"] * 2
    assert main(["--out", str(shared), "--merge", "--quiet"]) == 0
    _finish(_eval("--out", str(single)))
    assert _episodes(shared) == _episodes(single)
    merged, alone = (json.loads((d / "results.json").read_text()) for d in (shared, single))
    assert merged["summary"] == alone["summary"] and merged["complete"]
    assert [p["process_id"] for p in merged["processes"]] == [0, 1]
    assert (shared / "results.csv").read_text() == (single / "results.csv").read_text()
    assert (shared / "results.md").read_text() == (single / "results.md").read_text()


@pytest.mark.slow
def test_local_processes_run_and_merge_like_one(tmp_path: Path) -> None:
    """--local-processes 2 starts both processes itself, logs each, and merges into the
    records one process writes."""
    shared, single = tmp_path / "shared", tmp_path / "single"
    _finish(_eval("--out", str(shared), "--local-processes", "2"))
    assert (shared / "proc-0.log").exists() and (shared / "proc-1.log").exists()
    assert all((shared / f"proc-{i}" / "finished").exists() for i in range(2))
    _finish(_eval("--out", str(single)))
    assert not (single / "finished").exists()  # a process of a queue only
    assert _episodes(shared) == _episodes(single)
    assert (shared / "results.md").read_text() == (single / "results.md").read_text()
    # The merge draws the run's plot; a process draws none of its part.
    assert (shared / "results.png").exists() and not list(shared.glob("proc-*/results.png"))
    # Each task ran in one process, which claimed it in --out/queue.
    owners = {f.name: int(f.read_text()) for f in (shared / "queue").iterdir()}
    assert sorted(owners) == ["lamp_off", "lamp_on"]
    for i in range(2):  # (a process that started late may have found both tasks taken)
        ran = {r["task"] for r in _episodes_or_none(shared / f"proc-{i}")}
        assert ran == {t for t, owner in owners.items() if owner == i}
    # --resume with a third episode: each task stays with the process holding its episodes.
    _finish(_eval("--out", str(shared), "--local-processes", "2", "--resume", "--episodes", "3"))
    for i in range(2):
        ran = [r["task"] for r in _episodes_or_none(shared / f"proc-{i}")]
        assert sorted(set(ran)) == [t for t, owner in sorted(owners.items()) if owner == i]
        assert len(ran) == 3 * len(set(ran))
    assert len(_episodes(shared)) == 6


@pytest.mark.slow
def test_a_long_tasks_seeds_go_to_several_processes(tmp_path: Path) -> None:
    """lamp_on is expected to take 14x close_fridge, more than two mean shares of 3
    processes: its seeds become units of their own (task_queue.split_by_seed), claimed by
    two processes, and the merged records are those of one process running it whole."""
    args = ("--tasks", "lamp_on,close_fridge", "--seeds", "0,1", "--batch", "4")
    shared, single = tmp_path / "shared", tmp_path / "single"
    _finish(_eval("--out", str(shared), "--local-processes", "3", *args))
    _finish(_eval("--out", str(single), *args))
    strip = lambda records: [{k: v for k, v in r.items() if k != "batch_size"}  # noqa: E731
                             for r in records]
    assert strip(_episodes(shared)) == strip(_episodes(single))
    owners = {f.name: int(f.read_text()) for f in (shared / "queue").iterdir()}
    assert sorted(owners) == ["close_fridge", "lamp_on@0", "lamp_on@1"]
    assert owners["lamp_on@0"] != owners["lamp_on@1"]
    for i in range(3):
        ran = {(r["task"], r["seed"], r["batch_size"]) for r in
               _episodes_or_none(shared / f"proc-{i}")}
        assert {(t, s) for t, s, _ in ran} == {
            (t, s) for unit, owner in owners.items() if owner == i
            for t, _, s in [unit.partition("@")] for s in ([int(s)] if s else [0, 1])}
        assert all(b == 2 for t, _, b in ran if t == "lamp_on")  # one seed's 2 episodes
    assert {r["batch_size"] for r in _episodes(single) if r["task"] == "lamp_on"} == {4}
    # --resume with a third episode: each seed stays with the process holding its episodes.
    _finish(_eval("--out", str(shared), "--local-processes", "3", "--resume", *args,
                  "--episodes", "3"))
    for i in range(3):
        seeds = {r["seed"] for r in _episodes_or_none(shared / f"proc-{i}")
                 if r["task"] == "lamp_on"}
        assert seeds == {s for s in (0, 1) if owners[f"lamp_on@{s}"] == i}
    assert len(_episodes(shared)) == 12


def test_local_processes_refuse_an_unknown_task_before_starting(tmp_path: Path, monkeypatch,
                                                                capsys) -> None:
    """A wrong task name is a usage error at once: no warm-up, no process, no output folder
    (the launcher checks the names without importing JAX)."""
    from agnostos_mjx import eval as ev
    from agnostos_mjx import warmup
    from agnostos_mjx.evaluation import processes

    def started(*_, **__):
        raise AssertionError("started before checking the task names")

    monkeypatch.setattr(warmup, "ensure_shared_programs", started)
    monkeypatch.setattr(processes, "run", started)
    out = tmp_path / "run"
    assert ev.main(["--tasks", "lamp_on,nope", "--local-processes", "2", "--out", str(out)]) == 2
    assert "unknown task 'nope'; valid task names: " in capsys.readouterr().err
    assert not out.exists()


FINISHING_CHILD = """
import sys, time
from pathlib import Path
out = Path(sys.argv[sys.argv.index("--spec") + 1]).parent  # --out/run_spec.json
i = sys.argv[sys.argv.index("--process-id") + 1]
merged = out / "merged"
early = merged.exists()  # merged before this process wrote anything: a stale marker counted
(out / f"proc-{i}").mkdir(exist_ok=True)
(out / f"proc-{i}" / "finished").write_text("")
deadline = time.time() + 20  # its teardown, as long as the launcher takes to merge
while not merged.exists() and time.time() < deadline:
    time.sleep(0.02)
(out / f"saw-{i}").write_text(f"{early} {merged.exists()}")
"""


def test_the_launcher_merges_while_its_processes_end(tmp_path: Path, monkeypatch) -> None:
    """Once every process has written its final results (its `finished` marker), the
    launcher merges while they end, not after; a marker left by an earlier run of the folder
    is not taken for one."""
    from agnostos_mjx.evaluation import processes
    from agnostos_mjx.evaluation.config import parse_config

    monkeypatch.setattr(processes, "merge_main",
                        lambda out: (Path(out) / "merged").write_text("") or 0)
    child, out = tmp_path / "child.py", tmp_path / "run"
    child.write_text(FINISHING_CHILD)
    for i in range(2):  # an earlier run's markers
        (out / f"proc-{i}").mkdir(parents=True)
        (out / f"proc-{i}" / "finished").write_text("")
    argv = ["--policy", "oracle", "--local-processes", "2", "--out", str(out), "--quiet",
            "--mps", "off"]
    assert processes.run(parse_config(argv), poll_s=0.02,
                         command=[sys.executable, str(child)]) == 0
    assert [(out / f"saw-{i}").read_text() for i in range(2)] == ["False True"] * 2


CONFIG_CHILD = """
import json, sys
from agnostos_mjx.evaluation.config import parse_config
cfg = parse_config(sys.argv[1:])
folder = __import__("pathlib").Path(cfg.run.out) / f"proc-{cfg.run.process_id}"
folder.mkdir(exist_ok=True)
(folder / "options.json").write_text(json.dumps(cfg.options()))
(folder / "finished").write_text("")
"""


def test_a_process_runs_the_launchers_config(tmp_path: Path, monkeypatch) -> None:
    """--local-processes hands its processes the run's config in a file (--spec), not flags
    parsed again: each process's config is the launcher's, as process I of N on the queue."""
    from agnostos_mjx.evaluation import processes
    from agnostos_mjx.evaluation.config import parse_config

    monkeypatch.setattr(processes, "merge_main", lambda out: 0)
    child, out = tmp_path / "child.py", tmp_path / "run"
    child.write_text(CONFIG_CHILD)
    cfg = parse_config(["--policy", "oracle", "--policy-arg", "k=[1, 2]", "--tasks",
                        "lamp_on,close_jar", "--seeds", "4,1", "--episodes", "3", "--video",
                        "failures", "--gpu-mem-fraction", "0.2", "--local-processes", "2",
                        "--mps", "off", "--out", str(out)])
    assert processes.run(cfg, poll_s=0.02, command=[sys.executable, str(child)]) == 0
    for i in range(2):
        seen = json.loads((out / f"proc-{i}" / "options.json").read_text())
        assert seen == {**cfg.options(), "num_processes": 2, "process_id": i,
                        "local_processes": 1, "task_queue": str(out / "queue"), "quiet": True}


@pytest.mark.slow
def test_local_processes_report_a_failure_once(tmp_path: Path) -> None:
    """A usage error only the processes find fails every process alike: exit 1, the error
    shown once."""
    proc = subprocess.run(
        [sys.executable, "-m", "agnostos_mjx.eval", "--policy", "oracle", "--tasks", "lamp_on",
         "--variations", "99", "--quiet", "--local-processes", "2", "--out",
         str(tmp_path / "run")],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True,
        timeout=300)
    assert proc.returncode == 1
    assert proc.stderr.count("--variations 99: lamp_on has variations") == 1, proc.stderr
    assert "process 1 exited with 2 (the same)" in proc.stderr


@pytest.mark.slow
def test_local_processes_ctrl_c_stops_every_process(tmp_path: Path) -> None:
    """Ctrl-C of --local-processes reaches each process once and ends the run with 130."""
    import time

    out = tmp_path / "run"
    parent = _eval("--out", str(out), "--local-processes", "2", "--episodes", "25",
                   "--batch", "1")
    deadline = time.monotonic() + 120
    while not (out / "proc-1.log").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    time.sleep(1.0)
    parent.send_signal(signal.SIGINT)
    output, _ = parent.communicate(timeout=120)
    assert parent.returncode == 130, output
    assert "--resume" in output


@pytest.mark.parametrize("args, expected", [
    (["--num-processes", "2"], "needs --out"),
    (["--num-processes", "2", "--process-id", "2", "--out", "{tmp}/x"], "expected 0..1"),
    (["--merge", "--out", "{tmp}"], "no proc-*/results.json"),
    (["--merge"], "needs --out"),
    (["--local-processes", "2"], "needs --out"),
    (["--local-processes", "2", "--num-processes", "2", "--out", "{tmp}/x"], "drop --num"),
])
def test_scale_out_usage_errors_are_one_line(args: list[str], expected: str, tmp_path: Path,
                                             capsys: pytest.CaptureFixture) -> None:
    from agnostos_mjx.eval import main

    argv = [a.format(tmp=tmp_path) for a in args]
    assert main(["--policy", "oracle", "--tasks", "lamp_on", "--quiet", *argv]) == 2
    assert expected in capsys.readouterr().err
