"""Each task's expected seconds in a run: writes agnostos_mjx/evaluation/task_costs.json,
which the task queue balances its processes' shares by.

    python tools/task_cost.py RUN [--backend native|warp] [--wall [--first-s S]]
                              [--batch 6] [--write [FILE]] [--json F]

RUN is a run folder with timings.jsonl (or proc-*/timings.jsonl).  By default a task's cost
is its CPU work: this times native MuJoCo's step on one thread while the task's scripted
expert runs `--batch` episodes (the arm moving and the objects in contact, as in an
evaluation), and prices RUN's world-steps at that step, plus `ROUND_S` per planning round
(the policy's work).  With --wall it is the task's measured wall seconds instead, less
--first-s for each process's first task (its compiles, which a warm run does not repeat).
--write merges the costs into the backend's table of the costs file (tasks of other runs
keep theirs); docs/performance.md (Task costs) says which runs the shipped table comes from.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROUND_S = 12 / 25  # a warm run's non-physics CPU per planning round (docs/performance.md)
COSTS_FILE = Path(__file__).resolve().parents[1] / "agnostos_mjx/evaluation/task_costs.json"


def _timing_files(run: Path) -> list[Path]:
    files = [run / "timings.jsonl", *sorted(run.glob("proc-*/timings.jsonl"))]
    return [f for f in files if f.exists()]


def run_timings(run: Path) -> dict[str, dict]:
    """Each task's world-steps and rounds in `run` (one process or several): the last
    timings.jsonl line of the task in each file, the world-steps summed over the files (a
    task split by seed ran in several processes, each unit through all its rounds)."""
    out: dict[str, dict] = {}
    for f in _timing_files(run):
        last = {row["task"]: row for row in map(json.loads, f.read_text().splitlines())
                if "task" in row}
        for task, row in last.items():
            seen = out.setdefault(task, {"world_steps": 0, "rounds": 0})
            seen["world_steps"] += row["world_steps"]
            seen["rounds"] = max(seen["rounds"], row["rounds"])
    if not out:
        sys.exit(f"error: {run}: no timings.jsonl with task lines")
    return out


def wall_costs(run: Path, first_s: float) -> dict[str, float]:
    """Each task's wall seconds in `run`, summed over the files (a task split by seed), less
    `first_s` for each file's first task (least ``start_s``, else its first line)."""
    out: dict[str, float] = {}
    for f in _timing_files(run):
        rows = [row for row in map(json.loads, f.read_text().splitlines()) if "task" in row]
        if not rows:
            continue
        first = min(range(len(rows)), key=lambda i: (rows[i].get("start_s", 0.0), i))
        for i, row in enumerate(rows):
            wall = row["wall_s"] - (first_s if i == first else 0.0)
            out[row["task"]] = out.get(row["task"], 0.0) + max(wall, 0.0)
    if not out:
        sys.exit(f"error: {run}: no timings.jsonl with task lines")
    return {task: round(s, 1) for task, s in out.items()}


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


def write_costs(path: Path, backend: str, cost: dict[str, float]) -> None:
    """Merge `cost` into `backend`'s table of the costs file at `path`, longest first."""
    table = json.loads(path.read_text()) if path.exists() else {}
    merged = {**table.get(backend, {}), **cost}
    table[backend] = dict(sorted(merged.items(), key=lambda kv: -kv[1]))
    path.write_text(json.dumps(table, indent=1) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder with timings.jsonl")
    parser.add_argument("--backend", choices=("native", "warp"), default="native",
                        help="the table --write updates (MJX-jax runs count as warp)")
    parser.add_argument("--wall", action="store_true",
                        help="cost = the task's measured wall seconds, not its priced CPU work")
    parser.add_argument("--first-s", type=float, default=0.0,
                        help="with --wall: seconds taken off each process's first task "
                             "(its compiles)")
    parser.add_argument("--batch", type=int, default=6,
                        help="expert episodes timed per task (CPU pricing)")
    parser.add_argument("--write", type=Path, nargs="?", const=COSTS_FILE,
                        help=f"merge the costs into this file (default {COSTS_FILE.name} "
                             "in the package)")
    parser.add_argument("--json", type=Path, help="also write {task: seconds} here")
    args = parser.parse_args()
    if args.wall:
        cost = wall_costs(args.run, args.first_s)
        print("| task | expected s |\n|---|---|")
        for name, s in cost.items():
            print(f"| {name} | {s} |")
    else:
        rows = run_timings(args.run)
        cost = {}
        print("| task | world-steps | step us | expected s |\n|---|---|---|---|")
        for name, row in rows.items():
            us = step_us(name, args.batch)
            cost[name] = round(row["world_steps"] * us * 1e-6 + ROUND_S * row["rounds"], 1)
            print(f"| {name} | {row['world_steps']} | {us:.1f} | {cost[name]} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(cost, indent=1))
    if args.write:
        write_costs(args.write, args.backend, cost)


if __name__ == "__main__":
    main()
