"""A/B in one process: physics steps per while-loop iteration of the device key action.

    python tools/warp_unroll_ab.py --tasks lamp_on,stack_blocks --ks 1,2,4,8 --batch 75

Per task, one MJX-Warp runner; per K a fresh KeyActionStep (compiled in a warm-up batch),
then the timed oracle batches in the order K1 K2 ... K1 K2 ... (`--rounds`), best wall per K.
Outcomes and per-world step counts are compared with K=first (unrolling must not change them).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def oracle_batch(runner, batch: int, seed: int):
    """(wall seconds, outcomes, per-world physics steps) of one oracle batch."""
    from agnostos_mjx.bench import oracle_episodes

    env, wall, _ = oracle_episodes(runner, batch, seed)
    return wall, np.asarray(env.outcome), np.asarray(env.sim_steps)


def main() -> None:
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.outcome import Outcome
    from agnostos_mjx.tasks import get_task

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="lamp_on,stack_blocks")
    p.add_argument("--ks", default="1,2,4,8")
    p.add_argument("--batch", type=int, default=75)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--backend", default="warp")
    p.add_argument("--out", default=None)
    a = p.parse_args()
    ks = [int(k) for k in a.ks.split(",")]
    rows = []
    for task in a.tasks.split(","):
        runner = Episodes(get_task(task), a.backend)
        steps = {}
        for k in ks:  # compile each K's program in a warm-up batch
            os.environ["AGNOSTOS_STEPS_PER_ITERATION"] = str(k)
            runner._device_steps.clear()
            t0 = time.perf_counter()
            oracle_batch(runner, a.batch, seed=1)
            steps[k] = (dict(runner._device_steps), time.perf_counter() - t0)
        walls: dict[int, list[float]] = {k: [] for k in ks}
        results = {}
        for _ in range(a.rounds):
            for k in ks:
                runner._device_steps.clear()
                runner._device_steps.update(steps[k][0])
                wall, outcome, sim = oracle_batch(runner, a.batch, seed=0)
                walls[k].append(wall)
                results[k] = (outcome, sim)
        ref_o, ref_s = results[ks[0]]
        for k in ks:
            o, s = results[k]
            row = {"task": task, "steps_per_iteration": k, "batch": a.batch,
                   "best_wall_s": round(min(walls[k]), 3), "walls_s": [round(w, 3) for w in walls[k]],
                   "warmup_s": round(steps[k][1], 1),
                   "speedup_vs_first": round(min(walls[ks[0]]) / min(walls[k]), 3),
                   "same_outcomes_as_first": int(np.sum(o == ref_o)),
                   "max_sim_steps_diff": int(np.max(np.abs(s - ref_s)))}
            row["success"] = float(np.mean(o == Outcome.SUCCESS))
            rows.append(row)
            print(json.dumps(row), flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
