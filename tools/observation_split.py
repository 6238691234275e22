"""Where one observation's time goes on the GPU route, call by call.

On one task's batch (native physics, the states of --steps dense control steps that hold
the gripper still), times the start (imports, Warp's start, the renderer's build, the first
observation) and then, per call averaged over the states: the evaluator's observation as
numpy and as device arrays, the bare renderer from a state (pose, BVH refit, trace), the
images unpacked, their copy to numpy (device_get against pinned host memory), and the
host-side pieces (proprioception, state to the device).  Needs a
CUDA GPU and warp-lang (`--warp-cpu`: Warp's CPU backend, which checks the tool only).  A
profile, not a test.

    python tools/observation_split.py --json split.json
    python tools/observation_split.py --task close_microwave --batch 1024
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python tools/observation_split.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="lamp_on", help="the task whose batch is observed")
    p.add_argument("--batch", type=int, default=75, help="worlds")
    p.add_argument("--cameras", default="front,wrist", help="cameras, comma-separated")
    p.add_argument("--size", type=int, default=128, help="image height and width, pixels")
    p.add_argument("--steps", type=int, default=30,
                   help="dense control steps whose states are observed (each timed once)")
    p.add_argument("--json", type=Path, help="also write the figures here")
    p.add_argument("--warp-cpu", action="store_true",
                   help="without a CUDA GPU, run on Warp's CPU backend (checks the tool, "
                        "its figures say nothing of a GPU)")
    args = p.parse_args(argv)
    if min(args.batch, args.size, args.steps) < 1:
        p.error("--batch, --size and --steps must be at least 1")
    return args


def main(argv: list[str] | None = None) -> int:
    t_start = time.perf_counter()
    args = parse_args(argv)
    import jax
    import jax.numpy as jnp
    import numpy as np

    from agnostos_mjx.physics import warp_available
    from agnostos_mjx.runtime.dense import DenseControl
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.observation import ObservationSpec
    from agnostos_mjx.sim.actions import KeyActions
    from agnostos_mjx.tasks import get_task

    out: dict[str, Any] = {"task": args.task, "batch": args.batch, "cameras": args.cameras,
                           "size": args.size}

    def mark(name: str, t: float) -> None:
        out[f"{name}_s"] = round(time.perf_counter() - t, 3)
        print(f"{name}: {out[f'{name}_s']} s", flush=True)

    mark("imports", t_start)
    if not (warp_available() or (args.warp_cpu and importlib.util.find_spec("warp"))):
        print("needs a CUDA GPU and warp-lang (or --warp-cpu and warp-lang)", file=sys.stderr)
        return 2
    b = args.batch
    t = time.perf_counter()
    runner = Episodes(get_task(args.task), "native", renderer="warp")
    env = runner.reset(jax.random.split(jax.random.PRNGKey(0), b), np.zeros(b, np.int32))
    mark("build_and_reset", t)
    t = time.perf_counter()
    from agnostos_mjx.physics.quiet_mjx import mjx  # noqa: F401 - Warp's modules load here
    mark("mjx_warp_import", t)
    spec = ObservationSpec(cameras=tuple(args.cameras.split(",")), height=args.size,
                           width=args.size, renderer="warp")
    t = time.perf_counter()
    renderer = runner.observer.warp_renderer(spec, b)
    mark("renderer_build", t)
    t = time.perf_counter()
    runner.observe(env, spec)
    mark("first_observation", t)

    ctl = DenseControl.at(20.0, runner.dt, runner.task.max_key_actions, args.steps)
    hold = KeyActions(np.asarray(env.obs["tip.pos"], np.float64),
                      np.asarray(env.obs["tip.quat"], np.float64), np.ones(b), np.ones(b, bool))
    states = []
    for _ in range(args.steps):
        env, _ = runner.step_dense(env, hold, ctl)
        states.append(env)

    def per_call(name: str, call: Callable[[Any], Any]) -> None:
        call(states[0])  # compiles
        jax.effects_barrier()
        t = time.perf_counter()
        for s in states:
            call(s)
        jax.effects_barrier()
        out[f"{name}_ms"] = round((time.perf_counter() - t) / len(states) * 1e3, 3)
        print(f"{name}: {out[f'{name}_ms']} ms a call", flush=True)

    def state(s: Any) -> tuple:
        return s.physics.qpos, s.physics.mocap_pos, s.physics.mocap_quat

    def rgba(s: Any) -> Any:
        return jnp.asarray(s.geom_rgba, jnp.float32)

    on_device = replace(spec, numpy=False)
    per_call("observation_numpy", lambda s: runner.observe(s, spec))
    per_call("observation_device", lambda s: jax.block_until_ready(
        {k: c.rgb for k, c in runner.observe(s, on_device).cameras.items()}))
    per_call("bare_renderer", lambda s: renderer.state_buffers(*state(s), rgba(s)))
    per_call("images_unpacked", lambda s: renderer.state_views(*state(s), rgba(s)))
    # The images' copy to numpy, device_get against pinned host memory (what the numpy
    # observation takes on a GPU), each from a fresh copy: device_get caches its result.
    from agnostos_mjx.infra.host_copy import to_numpy

    images = {k: c.rgb for k, c in runner.observe(states[0], on_device).cameras.items()}
    fresh = jax.jit(lambda t: jax.tree.map(lambda x: x + 0, t))
    per_call("images_fresh_copy", lambda s: jax.block_until_ready(fresh(images)))
    per_call("images_device_get", lambda s: jax.device_get(fresh(images)))
    per_call("images_pinned_host", lambda s: to_numpy(fresh(images), pinned=True))
    per_call("proprioception", lambda s: runner.observer.proprioception(s))
    per_call("qpos_to_device", lambda s: jax.block_until_ready(
        jnp.asarray(s.physics.qpos, jnp.float32)))
    frames = b * len(spec.cameras)
    for name in ("observation_numpy", "observation_device", "bare_renderer"):
        out[f"{name}_frames_per_s"] = round(frames / out[f"{name}_ms"] * 1e3)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
