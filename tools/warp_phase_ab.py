"""A/B in one process: the device key action's Warp graph mode and steps per iteration.

    python tools/warp_phase_ab.py --tasks lamp_on,stack_blocks --variants WARP:16,DIRECT:16 --batch 75

A variant DIRECT:K steps MuJoCo Warp directly, K steps per FFI call (physics/warp_chunk.py,
the default since 2026-11-26; DIRECT_WARP:K with that call in graph mode WARP instead of
its default; a suffix +U, e.g. DIRECT+U:16, checks the conditions of the K rows unrolled);
the others step through MJX's `mjx.step` in that graph mode.

Per task one MJX-Warp runner (its reset and settle as a run does them); per variant
(graph mode : physics steps per while-loop iteration) a DevicePhysics of its own
(`MjxBackend(graph_mode=...)`) and a compiled key-action program (timed in a warm-up
batch), then timed oracle batches in the order V1 V2 ... V1 V2 ... (`--rounds`), best wall
per variant.  Outcomes and per-world step counts are compared with the first variant: the
graph mode and K must not change them (Warp's atomics may, a little).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np


def oracle_batch(runner, batch: int, seed: int, physics, unroll: int):
    """(wall s, outcomes, per-world physics steps, physics steps run) of one oracle batch."""
    keys = jax.random.split(jax.random.PRNGKey(seed), batch)
    env = runner.reset(keys, np.zeros(batch, np.int32))
    actions = runner.expert_actions(env)
    t0 = time.perf_counter()
    for k in range(actions.pos.shape[1]):
        step = jax.tree.map(lambda x, k=k: x[:, k], actions)
        if not step.valid.any() or env.done.all():
            break
        env = runner.step_on_device(env, step, physics=physics, unroll=unroll)
    wall = time.perf_counter() - t0
    return wall, np.asarray(env.outcome), np.asarray(env.sim_steps)


def main() -> None:
    from agnostos_mjx.physics.mjx_backend import MjxBackend
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.outcome import Outcome
    from agnostos_mjx.tasks import get_task

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="lamp_on,stack_blocks")
    p.add_argument("--variants", default="WARP:16,DIRECT:16",
                   help="graph mode (or DIRECT):K pairs, comma-separated")
    p.add_argument("--batch", type=int, default=75)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--out", default=None)
    a = p.parse_args()
    variants = [(v.split(":")[0], int(v.split(":")[1])) for v in a.variants.split(",")]
    rows = []
    for task in a.tasks.split(","):
        runner = Episodes(get_task(task), "warp")
        model = runner.scene.model
        physics = {}
        for mode, k in variants:
            t0 = time.perf_counter()
            direct = mode.startswith("DIRECT")
            os.environ["AGNOSTOS_WARP_STEPS"] = "direct" if direct else "mjx"
            os.environ["AGNOSTOS_UNROLL_CONDITIONS"] = "1" if mode.endswith("+U") else "0"
            chunk_mode = mode.removesuffix("+U")[len("DIRECT_"):]
            os.environ["AGNOSTOS_WARP_CHUNK_GRAPH_MODE"] = chunk_mode or "auto"
            graph_mode = "WARP" if direct else mode
            dev = MjxBackend(model, impl="warp", graph_mode=graph_mode).device_physics(a.batch)
            oracle_batch(runner, a.batch, 1, dev, k)
            physics[(mode, k)] = (dev, time.perf_counter() - t0)
        walls: dict = {v: [] for v in variants}
        results = {}
        for _ in range(a.rounds):
            for v in variants:
                wall, outcome, sim = oracle_batch(runner, a.batch, 0, physics[v][0], v[1])
                walls[v].append(wall)
                results[v] = (outcome, sim)
        ref_o, ref_s = results[variants[0]]
        for v in variants:
            o, s = results[v]
            row = {"task": task, "graph_mode": v[0], "steps_per_iteration": v[1],
                   "batch": a.batch, "best_wall_s": round(min(walls[v]), 3),
                   "walls_s": [round(w, 3) for w in walls[v]],
                   "warmup_s": round(physics[v][1], 1),
                   "sequential_steps": int(s.max()),
                   "ms_per_sequential_step": round(1e3 * min(walls[v]) / max(int(s.max()), 1), 3),
                   "speedup_vs_first": round(min(walls[variants[0]]) / min(walls[v]), 3),
                   "same_outcomes_as_first": int(np.sum(o == ref_o)),
                   "max_sim_steps_diff": int(np.max(np.abs(s - ref_s))),
                   "success": float(np.mean(o == Outcome.SUCCESS))}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
