"""Throughput benchmark: ``python -m agnostos_mjx.bench.backends``.

Two numbers per task, backend and batch size:

* physics steps/s: physics steps x worlds / wall time of `backend.run` alone
  (a `--steps`-long run holding the settled start pose, timed after one
  warm-up call of the same shape, repeated for at least `--min-time` s);
* episodes/s: whole oracle episodes (reset, expert, control, condition
  checks, physics) per wall second, timed after one warm-up batch.

When native MuJoCo ran in the same process, each backend's steps/s is also
given as a ratio to native's at the same task and batch.  This is a
benchmark, not a test: nothing asserts on the numbers.

Examples::

    python -m agnostos_mjx.bench.backends --quick                  # CPU smoke run, seconds
    python -m agnostos_mjx.bench.backends --backends native,warp --batches 1,75,1024 --out bench.json
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agnostos_mjx.infra.settings import configure_jax

log = logging.getLogger("agnostos_mjx.bench.backends")


def _int_list(text: str) -> list[int]:
    from agnostos_mjx.evaluation.config import int_list

    values = int_list(text)
    if min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def build_parser() -> argparse.ArgumentParser:
    from agnostos_mjx.infra.cli import HelpFormatter

    p = argparse.ArgumentParser(
        prog="python -m agnostos_mjx.bench.backends",
        description="Physics steps/s and oracle episodes/s per task, backend and batch size.",
        formatter_class=HelpFormatter)
    p.add_argument("--tasks", default="all",
                   help="comma-separated task names and/or split names (as in eval)")
    p.add_argument("--backends", default=None,
                   help="comma-separated backends among native, jax, warp "
                        "(default: native, plus warp when a CUDA GPU is usable)")
    p.add_argument("--batches", type=_int_list, default="1,75,1024",
                   help="comma-separated numbers of worlds simulated at once")
    p.add_argument("--steps", type=int, default=200,
                   help="physics steps per timed backend.run call")
    p.add_argument("--min-time", type=float, default=1.0,
                   help="repeat the timed physics call until this many seconds have passed")
    p.add_argument("--reset-only", type=_int_list, default=[],
                   help="comma-separated batches (also listed in --batches) at which only the "
                        "reset is timed (first call with compiles, then a second): e.g. 8192")
    p.add_argument("--no-episodes", action="store_true",
                   help="measure physics steps/s only, skip the full oracle episodes")
    p.add_argument("--quick", action="store_true",
                   help="CPU-friendly smoke run: native backend, batches 1,8, the first task "
                        "only, 50 steps, no repetition")
    p.add_argument("--out", default=None,
                   help="write the rows, config and versions to this JSON file")
    return p


def _block(x: Any) -> Any:
    import jax

    return jax.block_until_ready(x)


def bench_physics(runner, batch: int, steps: int, min_time: float) -> dict[str, float]:
    """steps/s of `runner.backend.run` alone, after a warm-up call of the same shape."""
    from agnostos_mjx.evaluation.protocol import episode_keys

    keys = episode_keys(np.zeros(batch), np.arange(batch))
    env = runner.reset(keys, np.zeros(batch, np.int32))
    ctrl = np.repeat(np.asarray(env.physics.ctrl)[:, None], steps, axis=1)
    t0 = time.perf_counter()
    _block(runner.backend.run(env.physics, ctrl))
    warmup = time.perf_counter() - t0
    seconds, calls = seconds_per_call(lambda: runner.backend.run(env.physics, ctrl), min_time)
    return {"steps_per_s": batch * steps / seconds, "physics_wall_s": seconds,
            "physics_calls": calls, "warmup_s": warmup}


def seconds_per_call(fn, min_time: float) -> tuple[float, int]:
    """Mean wall seconds of `fn()` (already warmed up; results waited for), repeated for
    at least `min_time` s; and the number of calls."""
    calls, t0 = 0, time.perf_counter()
    while calls == 0 or time.perf_counter() - t0 < min_time:
        _block(fn())
        calls += 1
    return (time.perf_counter() - t0) / calls, calls


def oracle_episodes(runner, batch: int, seed: int) -> tuple[Any, float, float]:
    """One batch of oracle episodes: (final EnvState, wall seconds, reset seconds)."""
    from agnostos_mjx.evaluation.protocol import episode_keys
    from agnostos_mjx.policies.base import Round
    from agnostos_mjx.policies.oracle import OraclePolicy

    t0 = time.perf_counter()
    keys = episode_keys(np.full(batch, seed), np.arange(batch))
    env = runner.reset(keys, np.arange(batch) % runner.task.num_variations)
    reset = time.perf_counter() - t0
    policy = OraclePolicy()
    view = Round.for_policy(policy, runner, env, [""] * batch)
    policy.reset(view)
    for _ in range(runner.task.max_key_actions):
        if env.done.all():
            break
        env, _ = runner.step(env, policy.act(view.at(env)))
    return env, time.perf_counter() - t0, reset


def _oracle_batch(runner, batch: int, seed: int) -> tuple[float, float, float]:
    """One batch of oracle episodes: (wall seconds, success fraction, reset seconds)."""
    from agnostos_mjx.runtime.outcome import Outcome

    env, wall, reset = oracle_episodes(runner, batch, seed)
    return wall, float(np.mean(env.outcome == Outcome.SUCCESS)), reset


def bench_episodes(runner, batch: int) -> dict[str, float]:
    """Oracle episodes/s at `batch`, after a warm-up batch (compiles every shape)."""
    warmup, _, _ = _oracle_batch(runner, batch, seed=1)
    wall, success, reset = _oracle_batch(runner, batch, seed=0)
    return {"episodes_per_s": batch / wall, "episode_batch_wall_s": wall,
            "oracle_success": success, "episode_warmup_s": warmup, "reset_s": reset}


def bench_reset(runner, batch: int) -> dict[str, float]:
    """Seconds to reset `batch` worlds (sampling, settling, the expert-reachability check
    and re-sampling of rejected scenes): the first call (compiles) and a second one."""
    from agnostos_mjx.evaluation.protocol import episode_keys

    times = []
    for seed in (1, 0):
        t0 = time.perf_counter()
        env = runner.reset(episode_keys(np.full(batch, seed), np.arange(batch)),
                           np.arange(batch) % runner.task.num_variations)
        _block(env.physics)
        times.append(time.perf_counter() - t0)
    return {"reset_first_s": times[0], "reset_s": times[1]}


def _fmt(value: float | None, digits: int = 0) -> str:
    if value is None:
        return "-"
    return f"{value:,.{digits}f}"


def format_table(rows: list[dict]) -> str:
    lines = ["| task | backend | batch | physics steps/s | vs native | episodes/s | vs native "
             "| reset s | oracle success % |", "|---|---|---|---|---|---|---|---|---|"]
    ratio = lambda x: "-" if x is None else f"{x:.2f}x"  # noqa: E731
    for r in rows:
        lines.append(
            f"| {r['task']} | {r['backend']} | {r['batch']} | {_fmt(r.get('steps_per_s'))} | "
            f"{ratio(r.get('vs_native'))} | {_fmt(r.get('episodes_per_s'), 2)} | "
            f"{ratio(r.get('episodes_vs_native'))} | {_fmt(r.get('reset_s'), 1)} | "
            f"{_fmt(None if r.get('oracle_success') is None else 100 * r['oracle_success'])} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    args = build_parser().parse_args(argv)
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(message)s",
                            datefmt="%H:%M:%S")
    logging.getLogger("agnostos_mjx").setLevel(logging.INFO)

    # tasks before episode: importing episode first trips a world <-> tasks import cycle
    from agnostos_mjx.tasks import parse_tasks

    # isort: split
    from agnostos_mjx.infra.cli import atomic_write, versions
    from agnostos_mjx.physics import BACKENDS, warp_available
    from agnostos_mjx.runtime.env import Episodes

    try:
        tasks = parse_tasks(args.tasks)
    except KeyError as e:
        print(f"error: {e.args[0]}", file=sys.stderr)
        return 2
    steps = args.steps
    if args.quick:
        backends, batches, tasks, steps, min_time = ["native"], [1, 8], tasks[:1], 50, 0.0
    else:
        backends = ([b.strip() for b in args.backends.split(",") if b.strip()] if args.backends
                    else ["native"] + (["warp"] if warp_available() else []))
        batches, min_time = args.batches, args.min_time
    bad = [b for b in backends if b not in BACKENDS or b == "auto"]
    if bad:
        print(f"error: unknown backend(s) {', '.join(bad)}; choose among native, jax, warp",
              file=sys.stderr)
        return 2
    print(f"agnostos_mjx.bench.backends: tasks {', '.join(t.name for t in tasks)}; backends "
          f"{', '.join(backends)}; batches {', '.join(map(str, batches))}; {steps} steps",
          flush=True)

    rows: list[dict] = []
    for task in tasks:
        for backend in backends:
            if backend == "warp" and not warp_available():
                log.warning("skipping warp: no CUDA GPU or mujoco-warp here")
                continue
            runner = Episodes(task, backend)
            for batch in batches:
                row: dict[str, Any] = {"task": task.name, "backend": runner.backend_name,
                                       "batch": batch, "steps": steps}
                if batch in args.reset_only:
                    log.info("%s / %s / batch %d: reset", task.name, backend, batch)
                    rows.append(row | bench_reset(runner, batch))
                    continue
                log.info("%s / %s / batch %d: physics", task.name, backend, batch)
                row |= bench_physics(runner, batch, steps, min_time)
                if not args.no_episodes:
                    log.info("%s / %s / batch %d: oracle episodes", task.name, backend, batch)
                    row |= bench_episodes(runner, batch)
                rows.append(row)
    for key in ("steps_per_s", "episodes_per_s"):
        native = {(r["task"], r["batch"]): r.get(key) for r in rows if r["backend"] == "native"}
        for r in rows:
            base, value = native.get((r["task"], r["batch"])), r.get(key)
            name = "vs_native" if key == "steps_per_s" else "episodes_vs_native"
            r[name] = value / base if base and value else None

    table = format_table(rows)
    print(table, end="", flush=True)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        payload = {"config": vars(args) | {"backends": backends, "batches": batches,
                                           "steps": steps},
                   "versions": versions(), "rows": rows, "table": table}
        atomic_write(out, json.dumps(payload, indent=1) + "\n")
        log.info("wrote %s", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
