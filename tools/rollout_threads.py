"""Native physics throughput of several processes sharing a machine's cores.

    python tools/rollout_threads.py TASK SECONDS PxT [PxT ...]

For each PxT, P processes each step TASK's settled scene in `mujoco.rollout` calls of 75
worlds x 16 steps on a persistent pool of T threads for SECONDS, and the machine's
world-steps per second (their sum) are printed: how much oversubscribing the cores (8
processes x 16 threads on 16 cores) costs against fewer threads per process.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import time

import numpy as np


def _stepper(task: str, nthread: int, seconds: float, results) -> None:
    import mujoco
    from mujoco import rollout

    from agnostos_mjx.sim.world import build_scene
    from agnostos_mjx.tasks import get_task

    scene = build_scene(get_task(task))
    model, data = scene.model, mujoco.MjData(scene.model)
    data.qpos[:] = scene.initial_qpos
    for _ in range(200):  # settle
        mujoco.mj_step(model, data)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.zeros(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    worlds, steps = 75, 16
    state0, ctrl = np.tile(state, (worlds, 1)), np.tile(data.ctrl, (worlds, steps, 1))
    datas = [mujoco.MjData(model) for _ in range(nthread)]
    rollout.rollout(model, datas, state0, ctrl, persistent_pool=True)
    done, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        rollout.rollout(model, datas, state0, ctrl, persistent_pool=True)
        done += worlds * steps
    results.put(done / (time.perf_counter() - t0))


def main() -> None:
    if len(sys.argv) < 4 or any("x" not in a for a in sys.argv[3:]):
        sys.exit(__doc__)
    task, seconds = sys.argv[1], float(sys.argv[2])
    context = multiprocessing.get_context("spawn")
    for config in sys.argv[3:]:
        processes, nthread = map(int, config.split("x"))
        results = context.Queue()
        workers = [context.Process(target=_stepper, args=(task, nthread, seconds, results))
                   for _ in range(processes)]
        for w in workers:
            w.start()
        total = sum(results.get() for _ in workers)
        for w in workers:
            w.join()
        print(f"{task} {processes} processes x {nthread} threads: {total / 1e3:.1f} k "
              f"world-steps/s ({1e6 * os.cpu_count() / total:.1f} us per step and core)",
              flush=True)


if __name__ == "__main__":
    main()
