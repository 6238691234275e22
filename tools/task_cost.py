"""Each task's expected CPU seconds in a run, the source of `task_queue.EXPECTED_S`.

    python tools/task_cost.py RUN [--batch 6] [--json F]

RUN is a run folder with timings.jsonl (or proc-*/timings.jsonl). For each of its tasks this
times native MuJoCo's step on one thread while the task's scripted expert runs `--batch`
episodes (the arm moving and the objects in contact, as in an evaluation), then prints
RUN's world-steps times that step, plus `ROUND_S` per planning round (the policy's work,
a warm H200 run's non-physics CPU per task, ~12 s for 25 rounds).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROUND_S = 12 / 25


def run_timings(run: Path) -> dict[str, dict]:
    """Each task's world-steps and rounds in `run` (one process or several): the last
    timings.jsonl line of the task in each file, the world-steps summed over the files (a
    task split by seed ran in several processes, each unit through all its rounds)."""
    files = [run / "timings.jsonl", *sorted(run.glob("proc-*/timings.jsonl"))]
    out: dict[str, dict] = {}
    for f in files:
        if not f.exists():
            continue
        last = {row["task"]: row for row in map(json.loads, f.read_text().splitlines())
                if "task" in row}
        for task, row in last.items():
            seen = out.setdefault(task, {"world_steps": 0, "rounds": 0})
            seen["world_steps"] += row["world_steps"]
            seen["rounds"] = max(seen["rounds"], row["rounds"])
    if not out:
        sys.exit(f"error: {run}: no timings.jsonl with task lines")
    return out


def step_us(name: str, batch: int) -> float:
    """Microseconds of one world's physics step on one thread under the task's expert."""
    import jax
    import numpy as np

    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    episodes = Episodes(get_task(name), "native", threads=1, planner="host")
    state = episodes.reset(jax.random.split(jax.random.PRNGKey(0), batch),
                           np.zeros(batch, np.int32))
    spent, steps = 0.0, 0
    run = episodes.backend.run_with_qpos

    def timed(physics, ctrl, counts=None):
        nonlocal spent, steps
        t0 = time.perf_counter()
        result = run(physics, ctrl, counts)
        spent += time.perf_counter() - t0
        steps += int(np.sum(counts)) if counts is not None else ctrl.shape[0] * ctrl.shape[1]
        return result

    episodes.backend.run_with_qpos = timed
    episodes.run_expert(state)
    return 1e6 * spent / max(steps, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run folder with timings.jsonl")
    parser.add_argument("--batch", type=int, default=6, help="expert episodes timed per task")
    parser.add_argument("--json", type=Path, help="also write {task: seconds} here")
    args = parser.parse_args()
    rows = run_timings(args.run)
    cost = {}
    print("| task | world-steps | step us | expected s |\n|---|---|---|---|")
    for name, row in rows.items():
        us = step_us(name, args.batch)
        cost[name] = round(row["world_steps"] * us * 1e-6 + ROUND_S * row["rounds"], 1)
        print(f"| {name} | {row['world_steps']} | {us:.1f} | {cost[name]} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(cost, indent=1))


if __name__ == "__main__":
    main()
