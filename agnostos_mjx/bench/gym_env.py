"""Environment steps/s of the gymnasium VectorEnv that ``lerobot-eval`` drives:
``python -m agnostos_mjx.bench.gym_env [--quick]``.

Builds ``AgnostosVectorEnv`` (agnostos_mjx/gym) once per renderer route, resets it and
steps it with rows that hold every gripper where it is (a policy that answers at once, so
the figure is the env's own cost: physics, rendering, the rows' parsing), and reports
vector steps/s and environment steps/s (worlds x steps), with each route's ratio to the
first.  Episodes that end restart (autoreset), as in ``lerobot-eval``.  Needs gymnasium,
not lerobot.  A benchmark, not a test.

    python -m agnostos_mjx.bench.gym_env                        # cpu then auto, 75 envs
    python -m agnostos_mjx.bench.gym_env --quick                # CPU-sized: 4 envs, 64 px
    python -m agnostos_mjx.bench.gym_env --control-mode keyaction --steps 10
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

log = logging.getLogger("agnostos_mjx.bench.gym_env")


def build_parser() -> argparse.ArgumentParser:
    from agnostos_mjx.infra.cli import HelpFormatter

    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.bench.gym_env",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--task", default="lamp_on", help="the env's task")
    p.add_argument("--num-envs", type=int, default=75, help="worlds of the vector env")
    p.add_argument("--control-mode", default="dense", choices=("dense", "keyaction"),
                   help="one step = one control period (dense) or one key action")
    p.add_argument("--cameras", default="front,wrist", help="the policy's cameras")
    p.add_argument("--size", type=int, default=128, help="image height and width, pixels")
    p.add_argument("--steps", type=int, default=100, help="timed steps per route")
    p.add_argument("--warmup", type=int, default=3,
                   help="untimed steps first (renderer build, compiles)")
    p.add_argument("--renderers", default="cpu,auto",
                   help="routes, comma-separated among auto, cpu, warp (the first is the "
                        "ratios' base)")
    p.add_argument("--json", type=Path, help="write the rows here as JSON")
    p.add_argument("--quick", action="store_true",
                   help="a CPU-sized run: 4 envs, 64 px, 5 steps, cpu route only")
    return p


def hold_rows(agent_pos: np.ndarray) -> np.ndarray:
    """Action rows (x y z qx qy qz qw gripper) that keep each gripper at its pose, open,
    from the rlbench state rows (x y z qx qy qz qw open)."""
    rows = np.array(agent_pos[:, :8], np.float32)
    rows[:, 7] = 1.0
    return rows


def time_route(args: argparse.Namespace, renderer: str) -> dict:
    """One route's row: seconds, vector steps/s and environment steps/s over --steps."""
    from agnostos_mjx.gym_env import AgnostosVectorEnv, EnvOptions, render_route

    opts = EnvOptions(cameras=args.cameras, size=args.size, control_mode=args.control_mode,
                      renderer=renderer)
    env = AgnostosVectorEnv(args.task, args.num_envs, opts)
    try:
        t = time.perf_counter()
        obs, _ = env.reset(seed=0)
        for _ in range(args.warmup):
            obs, *_ = env.step(hold_rows(obs["agent_pos"]))
        start_s = time.perf_counter() - t
        t = time.perf_counter()
        for _ in range(args.steps):
            obs, *_ = env.step(hold_rows(obs["agent_pos"]))
        seconds = time.perf_counter() - t
    finally:
        env.close()
    return {"renderer": renderer, "route": render_route(opts), "task": args.task,
            "num_envs": args.num_envs, "control_mode": args.control_mode,
            "cameras": args.cameras, "size": args.size, "steps": args.steps,
            "start_s": round(start_s, 2), "seconds": round(seconds, 3),
            "vector_steps_per_s": round(args.steps / seconds, 2),
            "env_steps_per_s": round(args.steps * args.num_envs / seconds, 1)}


def main(argv: Sequence[str] | None = None) -> int:
    from agnostos_mjx.infra.settings import configure_jax

    args = build_parser().parse_args(argv)
    if args.quick:
        args.num_envs, args.size, args.steps, args.warmup = 4, 64, 5, 1
        args.renderers = "cpu"
    if min(args.num_envs, args.size, args.steps) < 1 or args.warmup < 0:
        build_parser().error("--num-envs, --size and --steps must be at least 1, "
                             "--warmup at least 0")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%X")
    configure_jax()
    rows = []
    for renderer in args.renderers.split(","):
        rows.append(time_route(args, renderer.strip()))
        rows[-1]["ratio_to_first"] = round(rows[-1]["env_steps_per_s"]
                                           / rows[0]["env_steps_per_s"], 2)
        log.info("%s", rows[-1])
    print("| renderer | env steps/s | vector steps/s | ratio | seconds | start s |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['renderer']} | {r['env_steps_per_s']} | {r['vector_steps_per_s']} | "
              f"{r['ratio_to_first']} | {r['seconds']} | {r['start_s']} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
