"""One key action's plan (`control.plan_arm`: IK + Cartesian path of every world) timed per
planner: the numpy host planner and the jitted device planner (on the GPU where there is one),
in wall and in the calling thread's CPU milliseconds.

    python tools/planner_bench.py [--batch 75] [--tasks a,b] [--calls 20] [--quick]

Each task's first expert key action from a reset batch; the device planner is timed after a
warm-up call (its compile), the host planner from the first call.  Prints one JSON line.
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import numpy as np

from agnostos_mjx.infra.settings import configure_jax

TASKS = "put_knife_on_chopping_board,close_microwave,lamp_on"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=75, help="worlds planned at once")
    p.add_argument("--tasks", default=TASKS, help="comma-separated task names")
    p.add_argument("--calls", type=int, default=20, help="timed calls per planner and task")
    p.add_argument("--quick", action="store_true", help="batch 8, one task, 3 calls (CPU smoke)")
    args = p.parse_args()
    if args.quick:
        args.batch, args.tasks, args.calls = 8, "lamp_on", 3
    configure_jax()
    import jax

    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.sim import control
    from agnostos_mjx.tasks import get_task

    rows = {}
    for name in args.tasks.split(","):
        ep = Episodes(get_task(name), "native", planner="host")
        env = ep.reset(jax.random.split(jax.random.PRNGKey(0), args.batch),
                       np.zeros(args.batch, np.int32))
        first = ep.expert_actions(env)
        q = np.asarray(env.data[:, ep.spec.arm_q], np.float64)
        pos, quat = (np.asarray(x[:, 0], np.float64) for x in (first.pos, first.quat))
        device = control.jit_for_robot(control.plan_arm, ep.kin)
        jax.block_until_ready(device(q, pos, quat))
        timed = {}
        for planner, plan in (("host", functools.partial(control.plan_arm, ep.kin)),
                              ("device", device)):
            t0, cpu0 = time.perf_counter(), time.thread_time()
            for _ in range(args.calls):
                jax.block_until_ready(plan(q, pos, quat))
            timed[f"{planner}_ms"] = round((time.perf_counter() - t0) / args.calls * 1000, 1)
            # The calling thread's CPU time a plan: a GPU wait that spins shows here.
            timed[f"{planner}_cpu_ms"] = round((time.thread_time() - cpu0) / args.calls * 1000, 1)
        rows[name] = timed
    print(json.dumps({"batch": args.batch, "device": str(jax.devices()[0]), "tasks": rows}))


if __name__ == "__main__":
    main()
