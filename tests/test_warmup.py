"""The cache warm-up command (agnostos_mjx/warmup.py)."""

from __future__ import annotations

import pytest

from agnostos_mjx import warmup
from agnostos_mjx.evaluation.config import EvalConfig


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


FIRST_KEY_ACTION = """
import logging, jax, numpy as np
from agnostos_mjx.infra.settings import configure_jax
configure_jax()
hits = []
class Hits(logging.Handler):
    def emit(self, record):
        hits.append(record.getMessage())
log = logging.getLogger("jax._src.compiler")
log.setLevel(logging.DEBUG)
log.addHandler(Hits())
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.tasks import get_task
ep = Episodes(get_task("phone_on_base"), "native", planner="device")
env = ep.reset(jax.random.split(jax.random.PRNGKey(0), 4), np.zeros(4, np.int32))
env, _ = ep.step(env, jax.tree.map(lambda x: x[:, 0], ep.expert_actions(env)))
print(sorted({m.split("'")[1] for m in hits if m.startswith("Persistent compilation cache hit")}))
"""


@pytest.mark.slow
def test_the_planner_warm_up_leaves_what_a_first_reset_and_key_action_plan(tmp_path):
    """After the planner step of the warm-up (one process, no scene), a new process's reset
    and first key action of a task on the device planner find the plan and the reset's
    reachability check in JAX's persistent cache: the run's processes do not compile them."""
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "AGNOSTOS_JAX_CACHE": str(tmp_path)}
    warm = subprocess.run([sys.executable, "-m", "agnostos_mjx.warmup", "--worker",
                           warmup.PLANNER_WORKER, "--planner", "device", "--batch", "4"],
                          env=env, capture_output=True, text=True, timeout=600)
    assert warm.returncode == 0, warm.stderr[-2000:]
    assert json.loads(warm.stdout.strip().splitlines()[-1])["programs"] == 5
    first = subprocess.run([sys.executable, "-c", FIRST_KEY_ACTION], env=env,
                           capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-2000:]
    hits = first.stdout.strip().splitlines()[-1]
    assert "jit_plan_arm" in hits and "jit_reachable" in hits, hits


@pytest.mark.slow
def test_the_policy_step_compiles_what_the_default_policy_runs():
    """After the default policy's warm-up (one blank query, no scene), its (= X-ICM's)
    first plan of a task's batch compiles nothing: the networks every process of a first
    run would otherwise compile at once are the ones the warm-up left in the cache."""
    import jax
    import numpy as np

    from agnostos_mjx.policies.base import Round
    from agnostos_mjx.policies.retrieval import RetrievalPolicy
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task
    from tests.test_compile_once import count_compiles

    jax.clear_caches()  # so that only the warm-up can have compiled them in this process
    task = get_task("lamp_on")
    episodes = Episodes(task, "native")
    env = episodes.reset(jax.random.split(jax.random.PRNGKey(0), 2), np.zeros(2, np.int32))
    with count_compiles() as warmed:
        assert warmup.warm_policy("auto", {}, 2) == {"policy": "retrieval", "compiled": True}
    assert warmed  # the networks were compiled (or fetched from the disk cache) here
    policy = RetrievalPolicy()
    view = Round.for_policy(policy, episodes, env, [task.descriptions(0)[0]] * 2)
    policy.reset(view)
    with count_compiles() as compiled:
        plans = policy.plan(view, np.arange(2))
    assert len(plans) == 2 and compiled == []
    episodes.close()


def test_task_runs_choice(caplog, monkeypatch):
    """--task-runs none with --policy none warms the device planner's programs alone
    (nothing with the host planner, and says so); a bad choice is a usage error, not a
    trace."""
    import logging

    import pytest

    with caplog.at_level(logging.INFO, logger="agnostos_mjx.warmup"):
        assert warmup.main(["--tasks", "lamp_on", "--backend", "native", "--task-runs", "none",
                            "--policy", "none", "--planner", "host"]) == 0
    assert "0 of 0 steps done" in caplog.text
    # (the planner step's compile is tested by the slow test above; here, that it runs)
    monkeypatch.setattr(warmup, "_worker", lambda name, args: {"task": name, "programs": 5})
    with caplog.at_level(logging.INFO, logger="agnostos_mjx.warmup"):
        assert warmup.main(["--tasks", "lamp_on", "--backend", "native", "--task-runs", "none",
                            "--policy", "none", "--planner", "device"]) == 0
    assert "1 of 1 steps done" in caplog.text and "(planner)" in caplog.text
    with pytest.raises(SystemExit) as exit_:
        warmup.parse_args(["--task-runs", "sometimes"])
    assert exit_.value.code == 2


def test_ensure_warp_kernels_builds_once_per_machine(tmp_path, monkeypatch):
    """A warp run first runs the warm-up's kernel step in a process of its own, unless this
    machine's marker for those tasks and batch says it did; the kernel step writes the
    marker only when every part succeeded."""
    import importlib.util
    import subprocess
    import types

    monkeypatch.setenv("AGNOSTOS_CACHE", str(tmp_path))
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",  # as if warp-lang were installed
                        lambda name, *a: object() if name == "warp" else real_find_spec(name, *a))
    commands = []
    monkeypatch.setattr(subprocess, "run", lambda cmd, **kw: (
        commands.append(cmd), types.SimpleNamespace(returncode=0))[1])
    run = EvalConfig.of(tasks="lamp_on,lamp_off", policy="oracle")
    assert warmup.ensure_warp_kernels(run) == 0
    assert commands[-1][1:3] == ["-m", "agnostos_mjx.warmup"]
    assert commands[-1][-2:] == ["--policy", "none"]  # the oracle compiles nothing of its own
    warmup.ensure_warp_kernels(run.with_options(policy="auto"))
    assert commands[-1][commands[-1].index("--policy") + 1] == "retrieval"

    # the kernel step (its parts faked) writes the marker; then the run skips it
    monkeypatch.setattr(warmup, "_worker", lambda name, *a, **k: {
        "task": "(Warp kernels)", "modules": 7, "built": 3, "build_s": 1.0})
    monkeypatch.setattr(warmup, "default_kernel_jobs", lambda: 2)
    args = warmup.parse_args(["--tasks", "lamp_on,lamp_off", "--batch", "75"])
    assert warmup.build_kernels_in_parallel(args)["modules"] == 7
    assert warmup.kernels_marker("lamp_on,lamp_off", 75).exists()
    n = len(commands)
    assert warmup.ensure_warp_kernels(run) is None and len(commands) == n
    assert not warmup.kernels_marker("lamp_on,lamp_off", 16).exists()  # per batch
    monkeypatch.setattr(warmup, "_worker", lambda *a, **k: {"task": "kernels:0/2",
                                                            "error": "exit 1", "stderr_tail": ""})
    args = warmup.parse_args(["--tasks", "lamp_on", "--batch", "75"])
    assert warmup.build_kernels_in_parallel(args)["error"] == "exit 1"
    assert not warmup.kernels_marker("lamp_on", 75).exists()


def test_a_run_of_several_processes_compiles_the_shared_programs_once(tmp_path, monkeypatch):
    """eval --local-processes N first compiles the programs every process shares (the
    device planner's; the policy's, here the default selection's networks) in one warm-up
    process (native physics, no task runs), once per machine: a success writes the marker
    and the next run skips it; a failure writes none."""
    import subprocess
    import types

    from agnostos_mjx import eval as ev

    monkeypatch.setenv("AGNOSTOS_CACHE", str(tmp_path))
    codes, commands = [1, 0], []
    monkeypatch.setattr(subprocess, "run", lambda cmd, **kw: (
        commands.append(cmd), types.SimpleNamespace(returncode=codes.pop(0)))[1])
    monkeypatch.setattr(ev.processes, "main", lambda cfg: 0)  # not the processes
    args = ["--tasks", "lamp_on,lamp_off", "--local-processes", "2", "--out", str(tmp_path / "r")]
    markers = lambda: sorted((tmp_path / "warm_shared").glob("*.json"))  # noqa: E731
    assert ev.main(args) == 0 and not markers()  # failed
    assert ev.main(args) == 0 and len(markers()) == 1
    assert commands[-1][1:3] == ["-m", "agnostos_mjx.warmup"]
    assert commands[-1][commands[-1].index("--backend") + 1] == "native"
    assert commands[-1][commands[-1].index("--policy") + 1] == "retrieval"
    assert "--policy-arg" in commands[-1] and "none" in commands[-1]  # --task-runs none
    n = len(commands)
    assert ev.main(args) == 0 and len(commands) == n  # this machine did it
    # Other options are another policy step (its own marker).
    codes.append(0)
    assert ev.main([*args, "--ddim-steps", "4"]) == 0 and len(commands) == n + 1
    assert 'sample_steps=4' in commands[-1] and len(markers()) == 2
    # A policy without shared programs: the device planner's programs alone, once; the
    # host planner (numpy, the CPU's auto) compiles nothing: no warm-up.
    assert ev.main([*args, "--policy", "oracle", "--planner", "host"]) == 0
    assert len(commands) == n + 1
    codes.append(0)
    assert ev.main([*args, "--policy", "oracle", "--planner", "device"]) == 0
    assert len(commands) == n + 2 and commands[-1][-2:] == ["--policy", "none"]
    assert ev.main([*args, "--policy", "oracle", "--planner", "device"]) == 0
    assert len(commands) == n + 2
    codes.append(0)
    assert ev.main([*args, "--batch", "16"]) == 0 and len(commands) == n + 3  # per batch


def test_policy_flags_give_the_warm_up_the_runs_own_options():
    """The warm-up's policy step resolves the policy's options as the run's processes do
    (the run's flags, e.g. --ddim-steps, included), and only built-in policies whose class
    has a warm-up say they share programs."""
    from agnostos_mjx.evaluation.config import resolve_policy
    from agnostos_mjx.policies.base import _REGISTRY, Builtin, Policy, load_object, shares_programs

    run = EvalConfig.of(tasks="lamp_on", ddim_steps=4, selection="lang+vis.out")
    args = warmup.parse_args(["--tasks", "lamp_on", *warmup.policy_flags(run)])
    again = EvalConfig.of(policy=args.policy, policy_args=dict(args.policy_args))
    assert resolve_policy(again)[:2] == resolve_policy(run)[:2]
    assert resolve_policy(run)[1]["sample_steps"] == 4
    assert warmup.policy_flags(run.with_options(policy="timing")) == ["--policy", "none"]
    for name, entry in _REGISTRY.items():
        if isinstance(entry, Builtin):
            cls = load_object(entry.policy)
            overrides = cls.warm_up.__func__ is not Policy.warm_up.__func__
            assert shares_programs(name) == overrides, name


def test_an_xicm_runs_warm_up_is_keyed_by_its_selection_alone(tmp_path):
    """X-ICM's shared programs are its demo selection's: two runs in other folders (so
    other LLM caches) or with another LLM share the warm-up's marker; another DDIM step
    count does not."""
    llm = {"llm_url": "http://localhost:1/v1", "llm_model": "m"}
    a = EvalConfig.of(policy="xicm", tasks="lamp_on", out=str(tmp_path / "a"), **llm)
    b = EvalConfig.of(policy="xicm", tasks="lamp_on", out=str(tmp_path / "b"),
                      llm_url="http://elsewhere:2/v1", llm_model="other")
    flags = warmup.policy_flags(a)
    assert flags == warmup.policy_flags(b)
    assert not any("llm" in flag or str(tmp_path) in flag for flag in flags)
    assert warmup.shared_marker(75, flags) == warmup.shared_marker(75, warmup.policy_flags(b))
    steps = warmup.policy_flags(a.with_options(ddim_steps=4))
    assert steps != flags and "sample_steps=4" in steps
    args = warmup.parse_args(["--tasks", "lamp_on", *flags])  # the warm-up takes them
    assert args.policy == "xicm"


def test_the_shared_programs_compile_where_one_gpu_is_visible(tmp_path, monkeypatch):
    """JAX's cache keys a program by the devices JAX sees: the warm-up of a run on several
    GPUs sees the first alone, as each process sees its own; on one GPU nothing changes."""
    import subprocess
    import types

    from agnostos_mjx.infra import mps

    monkeypatch.setenv("AGNOSTOS_CACHE", str(tmp_path))
    envs = []
    monkeypatch.setattr(subprocess, "run", lambda cmd, env=None, **kw: (
        envs.append(env), types.SimpleNamespace(returncode=0))[1])
    monkeypatch.setattr(mps, "visible_gpus", lambda environ: (["2", "3"], "test"))
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")
    warmup.ensure_shared_programs(EvalConfig.of(tasks="lamp_on", planner="device"))
    assert envs[-1]["CUDA_VISIBLE_DEVICES"] == "2"
    monkeypatch.setattr(mps, "visible_gpus", lambda environ: (["3"], "test"))
    assert warmup.one_gpu_env({"CUDA_VISIBLE_DEVICES": "3", "A": "b"}) == {
        "CUDA_VISIBLE_DEVICES": "3", "A": "b"}


def test_the_parent_of_a_warp_run_does_not_start_jax():
    """The run's parent process checks the marker and starts the kernel step without
    starting JAX: on a GPU, JAX there would take most of the memory from the run's
    processes (a fresh run's 8 processes all failed with CUDA out of memory)."""
    import subprocess
    import sys

    script = (
        "import importlib.util, subprocess, types\n"
        "real = importlib.util.find_spec\n"
        "importlib.util.find_spec = lambda n, *a: object() if n == 'warp' else real(n, *a)\n"
        "subprocess.run = lambda *a, **k: types.SimpleNamespace(returncode=0)\n"
        "from agnostos_mjx import eval as _\n"
        "from agnostos_mjx import warmup\n"
        "from agnostos_mjx.evaluation.config import EvalConfig\n"
        "assert warmup.ensure_warp_kernels(EvalConfig.of(tasks='unseen')) == 0\n"
        "from jax._src import xla_bridge\n"
        "print('backends', sorted(xla_bridge._backends))\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env={**__import__("os").environ, "AGNOSTOS_CACHE": "/nonexistent/x"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert "backends []" in out.stdout


def test_a_policy_that_cannot_load_stops_the_run_in_one_line(tmp_path, monkeypatch, capfd):
    """The warm-up's policy step builds the run's policy first: one that cannot load (here
    no checkpoint) ends the run before its processes start, with the processes' one line."""
    from agnostos_mjx import eval as ev

    monkeypatch.setenv("AGNOSTOS_CACHE", str(tmp_path))
    started = []
    monkeypatch.setattr(ev.processes, "main", lambda cfg: started.append(cfg) or 0)
    assert ev.main(["--policy", "reference-vla", "--tasks", "lamp_on", "--local-processes", "2",
                    "--planner", "host", "--out", str(tmp_path / "r")]) == 2
    err = capfd.readouterr().err  # the warm-up process's own stderr
    assert started == [] and "Traceback" not in err
    assert "error: cannot load policy 'reference-vla': reference-vla needs its run " in err
    assert not list((tmp_path / "warm_shared").glob("*.json"))
