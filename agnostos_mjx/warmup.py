"""Warm a machine's caches before a run, so that the run itself starts warm.

    python -m agnostos_mjx.warmup --tasks unseen --backend warp

On a fresh GPU machine the first MuJoCo Warp step of a scene builds Warp's CUDA kernels,
one module after another (minutes for the first scene, more for each further size;
docs/performance.md), and every process of a `--local-processes` run would build the same kernels
at once.  Warp keeps built kernels on disk and JAX keeps compiled programs in its
persistent cache (agnostos_mjx.infra.settings.configure_jax), so this command does each build
once, three things at the same time:
- on warp, every kernel module of the tasks' scenes, found by a dry run and built by
  `--kernel-jobs` processes, each its share (physics/warp_build.py);
- the run's policy's programs that are the same at every task (`Policy.warm_up`: the
  default policies' demo selection, the reference VLA's network), once: without this
  every process of the first run compiled them at once;
- the device planner's programs (a key action's plan, the reset's reachability checks),
  which every task shares: the robot is the same in every scene.
Then, with `--task-runs` (the default off warp), tasks run once in parallel processes
(`--jobs`): reset and settle, one key action of the expert, on warp one rendered frame.
A second run on the same machine finds everything built.  The key-action programs that
call Warp through JAX's FFI are cached per scene (physics/warp_chunk.py names them so).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import importlib.util
import json
import logging
import os
import subprocess
import sys
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from agnostos_mjx.evaluation.config import (
    EvalConfig,
    UsageError,
    loading_policy,
    policy_arg,
    positive_int,
    resolve_policy,
)
from agnostos_mjx.infra.cli import HelpFormatter, prog
from agnostos_mjx.infra.settings import (
    cache_root,
    configure_jax,
    gpu_plugin_installed,
    usable_cores,
)
from agnostos_mjx.physics import CAPABILITIES
from agnostos_mjx.policies.base import options_type, shares_programs

log = logging.getLogger("agnostos_mjx.warmup")


POLICY_WORKER = "(policy)"  # --worker name of the policy's step
USAGE_ERROR = 2  # exit code of a step (and then of this command) given input it cannot use
PLANNER_WORKER = "(planner)"  # --worker name of the planner step


def warm_policy(spec: str, args: Mapping[str, Any], batch: int) -> dict:
    """The policy's programs that are the same at every task (`Policy.warm_up`), its
    options resolved as a run's processes resolve them (``auto``: the default policy);
    no scene, no physics.  A policy that cannot load is a UsageError, as in a run."""
    from agnostos_mjx.policies.base import warm_up_policy

    spec, kwargs, _ = resolve_policy(EvalConfig.of(policy=spec, policy_args=dict(args)))
    with loading_policy(spec):
        return {"policy": spec, "compiled": warm_up_policy(spec, batch, **kwargs)}


def policy_flags(cfg: EvalConfig) -> list[str]:
    """This command's --policy flags for the run `cfg`: its policy with the options its
    shared programs are built from (`PolicyOptions.program_fields`) as the run's processes
    resolve them (JSON values, as --policy-arg reads them), or ``--policy none`` for a
    policy with no programs shared by its tasks."""
    spec, kwargs, _ = resolve_policy(cfg)
    if not shares_programs(spec):
        return NO_POLICY
    used = options_type(spec).program_fields()
    return _policy_flags(spec, {k: v for k, v in kwargs.items() if k in used})


NO_POLICY = ["--policy", "none"]


def _policy_flags(spec: str, args: Mapping[str, Any]) -> list[str]:
    """--policy SPEC and a --policy-arg KEY=JSON per option (as --policy-arg reads them)."""
    pairs = [f"{key}={json.dumps(value)}" for key, value in sorted(args.items())]
    return ["--policy", spec, *(flag for pair in pairs for flag in ("--policy-arg", pair))]


def warm_planner(batch: int, planner: str = "auto") -> dict:
    """The device planner's programs, which every task of a run shares (one robot,
    control.jit_for_robot): a key action's plan (control.plan_arm) and the reset's
    reachability check at each multiple of REACH_STEPS key actions up to the longest
    task, all at the run's batch.  Without this every process compiled them at its first
    reset (docs/performance.md).  Traced one by one, compiled at once on threads (XLA
    compiles without the GIL) into JAX's persistent cache, not run.  The host planner
    (numpy) has nothing to compile."""
    import numpy as np

    from agnostos_mjx.runtime.env import REACH_STEPS, resolve_planner
    from agnostos_mjx.sim import control
    from agnostos_mjx.sim.world import HOME_QPOS, build_scene
    from agnostos_mjx.tasks import get_task, list_tasks

    if resolve_planner(planner) != "device":
        return {"programs": 0}
    kin = control.PandaKinematics.from_model(build_scene(get_task("lamp_on")).model)
    # The dtypes and shapes the runtime passes (Episodes._plan_on_host, expert_reachable).
    q = np.tile(np.asarray(HOME_QPOS, np.float64), (batch, 1))
    pos = np.tile(np.array([0.3, 0.0, 1.0]), (batch, 1))
    quat = np.tile(np.array([0.0, 1.0, 0.0, 0.0]), (batch, 1))
    lowered = [control.jit_for_robot(control.plan_arm, kin).lower(q, pos, quat)]
    reachable = control.jit_for_robot(control.reachable, kin)
    longest = max(get_task(name).max_key_actions for name in list_tasks())
    for k in range(REACH_STEPS, longest + REACH_STEPS, REACH_STEPS):
        lowered.append(reachable.lower(q, np.repeat(pos[:, None], k, 1).astype(np.float32),
                                       np.repeat(quat[:, None], k, 1).astype(np.float32),
                                       np.ones((batch, k), bool)))
    with ThreadPoolExecutor(len(lowered)) as pool:
        list(pool.map(lambda program: program.compile(), lowered))
    return {"programs": len(lowered)}


def warm_task(name: str, backend: str, batch: int, planner: str = "auto") -> dict:
    """Run what an evaluation runs for one task once: reset (settle steps), the expert's
    first key action, on warp one rendered frame.  Returns the stage timings (s)."""
    import jax
    import numpy as np

    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.observation import ObservationSpec
    from agnostos_mjx.tasks import get_task

    t0 = time.perf_counter()
    episodes = Episodes(get_task(name), backend, planner=planner)
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    env = episodes.reset(keys, np.zeros(batch, np.int32))
    t1 = time.perf_counter()
    first = jax.tree.map(lambda x: x[:, 0], episodes.expert_actions(env))
    env, _ = episodes.step(env, first)
    t2 = time.perf_counter()
    if episodes.capabilities.renderer is not None:  # the renderer beside the physics
        episodes.observe(env, ObservationSpec(cameras=("front",), width=64, height=64))
    t3 = time.perf_counter()
    episodes.close()
    return {"task": name, "backend": episodes.backend_name, "nv": int(episodes.scene.model.nv),
            "reset_s": round(t1 - t0, 2), "key_action_s": round(t2 - t1, 2),
            "render_s": round(t3 - t2, 2), "wall_s": round(t3 - t0, 2)}


def build_kernels(names: list[str], batch: int, part: int = 0, parts: int = 1) -> dict:
    """Part `part` of `parts` of Warp's kernels of these tasks' scenes at this batch
    (physics/warp_build.py; one process per part).  Returns its timings."""
    from agnostos_mjx.physics.mjx_backend import CONSTRAINTS_PER_WORLD, CONTACTS_PER_WORLD
    from agnostos_mjx.physics.warp_build import build_scenes
    from agnostos_mjx.sim.world import build_scene
    from agnostos_mjx.tasks import get_task

    t0 = time.perf_counter()
    models = [build_scene(get_task(name)).model for name in names]
    done = build_scenes(models, batch, naconmax=batch * CONTACTS_PER_WORLD,
                        njmax=CONSTRAINTS_PER_WORLD, part=part, parts=parts)
    return {"task": "(Warp kernels)", **done, "wall_s": round(time.perf_counter() - t0, 2)}


def one_per_size(names: list[str]) -> list[str]:
    """The first task of each distinct scene size (`nv`): `--task-runs per-size` runs these,
    a sample of the programs the run's tasks compile (programs specialise on sizes)."""
    from agnostos_mjx.sim.world import build_scene
    from agnostos_mjx.tasks import get_task

    seen: dict[int, str] = {}
    for name in names:
        seen.setdefault(int(build_scene(get_task(name)).model.nv), name)
    return list(seen.values())


def _worker(name: str, args: argparse.Namespace) -> dict:
    """warm_task (or with name "kernels:I/N", part I of N of build_kernels of args.tasks;
    POLICY_WORKER, warm_policy; PLANNER_WORKER, warm_planner) in its own process
    (its GPU memory and Warp context go away with it)."""
    cmd = [sys.executable, "-m", "agnostos_mjx.warmup", "--worker", name, "--tasks", args.tasks,
           "--backend", args.backend, "--batch", str(args.batch), "--planner", args.planner,
           *_policy_flags(args.policy, dict(args.policy_args or []))]
    # Several JAX processes share the GPU: none may take JAX's default 75% of its memory.
    env = dict(os.environ)
    if not any(v in env for v in ("XLA_PYTHON_CLIENT_PREALLOCATE", "XLA_PYTHON_CLIENT_MEM_FRACTION")):
        env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = "\n".join(proc.stderr.splitlines()[-15:])
        return {"task": name, "error": f"exit {proc.returncode}", "stderr_tail": tail,
                "code": proc.returncode}
    return json.loads(lines[-1])


def default_kernel_jobs() -> int:
    """Processes building Warp's kernels at once: half the machine's cores, at most 8 (more
    were slower on a 16-core host: docs/performance.md)."""
    return max(1, min(usable_cores() // 2, 8))


def kernels_marker(tasks: str, batch: int) -> Path:
    """The file that says this machine built Warp's kernels of `tasks` (the --tasks text) at
    this batch (under the agnostos cache, keyed by the Warp and MJX versions and
    $WARP_CACHE_PATH; if Warp's own cache is wiped, a run builds what it misses as it goes,
    only slower).  Needs no task import: a run's parent process must not start JAX on the
    GPU (JAX would take most of its memory from the run's processes)."""
    key = json.dumps([_installed("warp-lang"), _installed("mujoco-mjx"),
                      os.environ.get("WARP_CACHE_PATH", ""), tasks, batch])
    return cache_root() / "warp_kernels" / f"{hashlib.sha1(key.encode()).hexdigest()[:16]}.json"


def _installed(package: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return "none"


def device_planner_possible(planner: str) -> bool:
    """Whether a run's `planner` may resolve to the jitted device planner, found without
    starting JAX (the parent of a GPU run must not: runtime.env.resolve_planner picks
    `device` where JAX has an accelerator, which needs a GPU plugin installed)."""
    return planner == "device" or (planner == "auto" and gpu_plugin_installed())


def shared_marker(batch: int, policy: list[str]) -> Path:
    """The file that says this machine compiled the programs every process of a run at
    `batch` shares (the device planner's, and those of the policy `policy_flags` gives)
    into JAX's persistent cache (keyed by the jax and agnostos-mjx versions and the cache's
    folder; a wiped cache only makes the processes compile again as they go)."""
    from agnostos_mjx.infra.settings import JAX_CACHE

    # "one GPU": the warm-up sees one GPU (one_gpu_env); a marker of a warm-up that saw
    # several names programs the processes do not find.
    key = json.dumps([_installed("jax"), _installed("agnostos-mjx"), JAX_CACHE.get(), batch,
                      "planner", policy, "one GPU"])
    return cache_root() / "warm_shared" / f"{hashlib.sha1(key.encode()).hexdigest()[:16]}.json"


def ensure_shared_programs(cfg: EvalConfig) -> int | None:
    """Before the run `cfg` of several processes (on a backend without Warp's kernel step,
    which does this too): the programs every process would compile alike, compiled once in
    a process of its own: the device planner's (warm_planner) and its policy's
    (warm_policy), unless this machine did it already (shared_marker).  Returns its exit
    code, None if skipped; on failure the processes compile as they go."""
    tasks, batch, planner = cfg.protocol.tasks, cfg.protocol.batch, cfg.protocol.planner
    policy = policy_flags(cfg)
    if not device_planner_possible(planner) and policy == NO_POLICY:
        return None
    marker = shared_marker(batch, policy)
    if marker.exists():
        return None
    log.info("compiling the programs every process shares once, before them "
             "(python -m agnostos_mjx.warmup does it ahead of time)")
    t0 = time.perf_counter()
    code = _warmup_process(tasks, "native", batch, planner, policy,
                           what="compiling the shared programs", env=one_gpu_env(os.environ))
    if code == 0:
        _write_marker(marker, {"wall_s": round(time.perf_counter() - t0, 2)})
    return code


def one_gpu_env(environ: Mapping[str, str]) -> dict[str, str]:
    """`environ` showing its first GPU alone when it shows several, as --local-processes
    shows each process its one GPU: JAX's persistent cache keys a program by the topology
    of the devices JAX sees, so a program compiled where 2 GPUs were visible is not found
    by a process that sees 1 (every process would compile the selection again:
    docs/performance.md)."""
    from agnostos_mjx.infra import mps

    gpus, _ = mps.visible_gpus(environ)
    return {**environ, "CUDA_VISIBLE_DEVICES": gpus[0]} if len(gpus) > 1 else dict(environ)


def _warmup_process(tasks: str, backend: str, batch: int, planner: str, policy: list[str],
                    what: str, env: Mapping[str, str] | None = None) -> int:
    """This command's kernel, planner and policy step (no task runs; `policy`: its
    --policy flags) in a process of its own (with `env`, default this one's); its exit
    code, a failure logged (the run then does `what` as it goes)."""
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "agnostos_mjx.warmup", "--tasks", tasks, "--backend", backend,
           "--batch", str(batch), "--planner", planner, "--task-runs", "none", *policy]
    code = subprocess.run(cmd, env=None if env is None else dict(env)).returncode
    if code == USAGE_ERROR:  # it said why in one line; the run would fail the same way
        return code
    if code:
        log.warning("%s ahead failed (exit %d); the run does it as it goes", what, code)
    else:
        log.info("%s: done in %.0f s", what, time.perf_counter() - t0)
    return code


def _write_marker(marker: Path, content: dict) -> None:
    marker.parent.mkdir(parents=True, exist_ok=True)
    tmp = marker.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(content))
    os.replace(tmp, marker)


def builds_kernels(backend: str) -> bool:
    """Whether a run on `backend` has per-scene kernels to build first (Capabilities.kernels;
    "auto" is not resolved here: its run builds what it needs as it goes)."""
    return backend in CAPABILITIES and CAPABILITIES[backend].kernels


def ensure_warp_kernels(cfg: EvalConfig) -> int | None:
    """Before the warp run `cfg`: this command's kernel step (Warp's kernels of its tasks in
    parallel processes, its policy's shared programs meanwhile) in a process of its own,
    unless this machine did it already (kernels_marker); for a run of --local-processes
    seeing one GPU as each process does (`one_gpu_env`).  Returns its exit code, None if
    skipped.  A failed build is logged and the run goes on (it then builds what it needs as
    it goes)."""
    tasks, batch = cfg.protocol.tasks, cfg.protocol.batch
    if importlib.util.find_spec("warp") is None or kernels_marker(tasks, batch).exists():
        return None  # without warp-lang the run says what is missing
    log.info("warp: building Warp's kernels of the tasks' scenes in %d processes first, once "
             "per machine (python -m agnostos_mjx.warmup does it ahead of time)",
             default_kernel_jobs())
    return _warmup_process(tasks, "warp", batch, cfg.protocol.planner, policy_flags(cfg),
                           what="warp: building the kernels",
                           env=one_gpu_env(os.environ) if (cfg.run.local_processes or 1) > 1 else None)


def build_kernels_in_parallel(args: argparse.Namespace, pool: ThreadPoolExecutor | None = None
                              ) -> dict:
    """build_kernels of args.tasks in --kernel-jobs processes, each building its share; on
    success the machine's marker for these tasks (kernels_marker) is written."""
    t0 = time.perf_counter()
    parts = args.kernel_jobs or default_kernel_jobs()
    with contextlib.ExitStack() as stack:
        pool = pool or stack.enter_context(ThreadPoolExecutor(parts))
        done = list(pool.map(lambda i: _worker(f"kernels:{i}/{parts}", args), range(parts)))
    failed = [d for d in done if "error" in d]
    if failed:
        return failed[0]
    result = {"task": "(Warp kernels)", "modules": done[0]["modules"], "parts": parts,
              "build_s": max(d["build_s"] for d in done),
              "wall_s": round(time.perf_counter() - t0, 2)}
    _write_marker(kernels_marker(args.tasks, args.batch), result)
    return result


def kernels_and_shared_programs(args: argparse.Namespace) -> list[dict]:
    """At once, each in processes of its own: on warp every scene's Warp kernels (many
    processes), the device planner's programs (warm_planner), and the --policy's shared
    programs (warm_policy: no scene, no physics).  The results, logged."""
    results = []
    with ThreadPoolExecutor((args.kernel_jobs or default_kernel_jobs()) + 2) as pool:
        shared = ([pool.submit(_worker, PLANNER_WORKER, args)]
                  if device_planner_possible(args.planner) else [])
        if args.policy != "none":
            shared.append(pool.submit(_worker, POLICY_WORKER, args))
        if builds_kernels(args.backend):
            results.append(build_kernels_in_parallel(args, pool))
        results.extend(future.result() for future in shared)
    for result in results:  # the failed ones are reported at the end
        if "error" not in result:
            log.info("warmup: %s", result)
    return results


def _task_names(spec: str) -> list[str]:
    from agnostos_mjx.tasks import parse_tasks

    return [task.name for task in parse_tasks(spec)]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=prog("agnostos_mjx.warmup"), description=__doc__,
                                formatter_class=HelpFormatter)
    p.add_argument("--tasks", default="unseen",
                   help="task names and/or splits (seen, unseen, unseen_level1, unseen_level2, "
                        "all), as eval takes them")
    p.add_argument("--backend", default="warp", choices=tuple(CAPABILITIES),
                   help="the backend the run will use (native has no kernels to build: only "
                        "JAX's reset and planner programs are cached)")
    p.add_argument("--batch", type=positive_int, default=75,
                   help="worlds per batch, as the run's --batch (JAX caches programs per shape)")
    p.add_argument("--planner", default="auto", choices=("auto", "host", "device"),
                   help="as eval's --planner")
    p.add_argument("--jobs", type=positive_int, default=8,
                   help="processes running tasks at once (--task-runs)")
    p.add_argument("--kernel-jobs", type=positive_int, default=None, metavar="N",
                   help="warp: processes building Warp's kernels at once, before anything "
                        "runs (default: half the machine's cores, at most 8; 1: one process)")
    p.add_argument("--task-runs", choices=("auto", "none", "per-size", "every"), default="auto",
                   help="which tasks then run once (reset, an expert key action, a frame) to "
                        "fill JAX's cache with their programs: none, the first task of each "
                        "scene size, or every task.  auto: none on warp (its kernels are "
                        "built directly, and a run compiles a task's own programs in seconds), "
                        "per-size otherwise")
    p.add_argument("--policy", default="auto",
                   help="the run's policy, as eval's --policy, whose programs that are the "
                        "same at every task are compiled (the default policies' demo "
                        "selection, the reference VLA's network; auto: the default policy); "
                        "none: no policy step.  The device planner's programs are compiled "
                        "either way")
    p.add_argument("--policy-arg", dest="policy_args", metavar="KEY=VALUE", type=policy_arg,
                   action="append", help="an option of --policy, as eval's --policy-arg "
                                         "(repeat for more)")
    p.add_argument("--worker", metavar="TASK", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    configure_jax()
    args = parse_args(argv)
    if args.worker and args.worker.startswith("kernels:"):
        part, parts = (int(x) for x in args.worker.removeprefix("kernels:").split("/"))
        print(json.dumps(build_kernels(_task_names(args.tasks), args.batch, part, parts)))
        return 0
    if args.worker == POLICY_WORKER:
        t0 = time.perf_counter()
        try:
            done = warm_policy(args.policy, dict(args.policy_args or []), args.batch)
        except UsageError as e:
            print(f"error: {e}", file=sys.stderr)
            return USAGE_ERROR
        print(json.dumps({"task": POLICY_WORKER, **done,
                          "policy_s": round(time.perf_counter() - t0, 2)}))
        return 0
    if args.worker == PLANNER_WORKER:
        t0 = time.perf_counter()
        done = warm_planner(args.batch, args.planner)
        print(json.dumps({"task": PLANNER_WORKER, **done,
                          "planner_s": round(time.perf_counter() - t0, 2)}))
        return 0
    if args.worker:
        print(json.dumps(warm_task(args.worker, args.backend, args.batch, args.planner)))
        return 0
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    runs = args.task_runs if args.task_runs != "auto" else (
        "none" if builds_kernels(args.backend) else "per-size")
    try:  # the planner and the policy's step are the same for every task: no names needed
        names = _task_names(args.tasks) if runs != "none" or builds_kernels(args.backend) else []
    except (KeyError, ValueError) as err:
        print(f"warmup: {err.args[0] if err.args else err}", file=sys.stderr)
        return 2
    todo = {"none": [], "per-size": one_per_size(names), "every": names}[runs]
    t0 = time.perf_counter()
    results = kernels_and_shared_programs(args)
    with ThreadPoolExecutor(args.jobs) as pool:
        for result in pool.map(lambda n: _worker(n, args), todo):
            log.info("warmup: %s", result)
            results.append(result)
    failed = [r for r in results if "error" in r]
    log.info("warmup: %d of %d steps done in %.1f s%s", len(results) - len(failed),
             len(results), time.perf_counter() - t0,
             f"; failed: {', '.join(r['task'] for r in failed)}" if failed else "")
    usage = [r for r in failed if r.get("code") == USAGE_ERROR]
    if usage:  # input the run cannot use either (a policy that cannot load): its one line
        print(usage[0]["stderr_tail"].splitlines()[-1], file=sys.stderr)
        return USAGE_ERROR
    for r in failed:
        log.error("%s: %s\n%s", r["task"], r["error"], r["stderr_tail"])
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
