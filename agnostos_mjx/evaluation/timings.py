"""Where an evaluation's time went: ``python -m agnostos_mjx.evaluation.timings RUN...``.

Every task an evaluation runs appends one line to ``<out>/timings.jsonl`` (a
``--local-processes`` run: ``<out>/proc-I/timings.jsonl``): its wall time split into
building the runner, resetting batches, rendering the policy's observations, the policy and
the physics, and the rest
(rollout.TimeSplit), the policy's rounds, and the physics steps run for the worlds against
those their episodes needed (live: a world that ended waits for its batch's slowest world on
the device backends, and a batch's padding worlds are not live).  This prints them as a
markdown table with the shares of the summed task time, the profile that says whether
physics and policy dominate a run.  Each process also appends one line when its tasks are
done: its start-up (from its start, interpreter included, to its first task) and the time
its tasks took, printed as a second table.  A task's "process s" is the span of its
process's age it ran in (start-up included), so the rows read as the run's timeline.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable
from pathlib import Path

TIMINGS_FILE = "timings.jsonl"
MEASURED = ("build", "reset", "render", "policy", "physics")  # timed by rollout.TimeSplit
STAGES = (*MEASURED, "other")  # "other": the task's wall time less the measured stages


def read_timings(runs: Iterable[Path], kind: str = "task") -> list[dict]:
    """The lines of `kind` ("task" or "process") of each run folder and of its per-process
    folders (proc-I)."""
    rows: list[dict] = []
    for run in map(Path, runs):
        files = [run / TIMINGS_FILE, *sorted(run.glob(f"proc-*/{TIMINGS_FILE}"))]
        for f in files:
            if f.is_file():
                rows += [json.loads(line) for line in f.read_text().splitlines() if line]
    return [r for r in rows if kind in r]


STARTUP_PARTS = (("imports_s", "imports"), ("policy_s", "policy load"))


def _cell(value: float | None, fmt: str = ".1f") -> str:
    """A number as a table cell; a field the run did not record prints empty."""
    return "" if value is None else format(value, fmt)


def process_table(runs: Iterable[Path]) -> str:
    """Per process: start-up seconds (start to first task), split into its parts where the
    run recorded them (the seconds up to the end of the imports, then each part's own), and
    the seconds its tasks took; empty when the runs have no process lines."""
    rows = sorted(read_timings(runs, "process"), key=lambda r: r["process"])
    if not rows:
        return ""

    def parts(r: dict) -> list[str]:  # each part's own seconds, from the process's ages
        ages = [r.get("startup", {}).get(key) for key, _ in STARTUP_PARTS]
        ages.append(r.get("startup_s"))
        if None in ages:
            return [""] * len(ages)
        return [_cell(ages[0])] + [_cell(b - a) for a, b in zip(ages, ages[1:])]

    head = ["process", "tasks", "start-up s", *(f"{name} s" for _, name in STARTUP_PARTS),
            "rest s", "tasks s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join([str(r["process"]), str(r.get("tasks", "")),
                                 _cell(r.get("startup_s")), *parts(r),
                                 _cell(r.get("tasks_s"))]) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def time_split_table(runs: Iterable[Path]) -> str:
    """Per task and in all: wall seconds and each stage's seconds (share of the wall).  A
    field a run did not record prints as an empty cell, so any run folder makes a table."""
    rows = read_timings(runs)
    if not rows:
        raise ValueError("no timings.jsonl with task lines in these run folders")
    head = ["task", "backend", "episodes", "wall s", "process s", *(f"{s} s" for s in STAGES),
            "rounds", "world-steps (M)", "live"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def line(name: str, backend: str, episodes: int | str, r: dict) -> str:
        wall, start, executed = r.get("wall_s"), r.get("start_s"), r.get("world_steps")
        end = r.get("end_s", start + wall if start is not None and wall is not None else None)
        span = f"{_cell(start)}-{_cell(end)}" if start is not None else ""
        cells = [f"{_cell(r.get(s + '_s'))} ({100 * r.get(s + '_s', 0.0) / wall:.0f}%)"
                 if wall and s + "_s" in r else "" for s in STAGES]
        steps = [str(r.get("rounds", "")),
                 _cell(executed / 1e6, ".3f") if executed else "",
                 f"{100 * r['live_steps'] / executed:.0f}%"
                 if executed and "live_steps" in r else ""]
        return (f"| {name} | {backend} | {episodes} | {_cell(wall)} | {span} | "
                + " | ".join(cells + steps) + " |")

    for r in rows:
        lines.append(line(r["task"], r.get("backend", ""), r.get("episodes", ""), r))
    counts = ("wall_s", *(s + "_s" for s in STAGES), "rounds", "world_steps", "live_steps")
    total = {k: sum(r[k] for r in rows if k in r) for k in counts if any(k in r for r in rows)}
    starts = [r.get("start_s") for r in rows]
    if None not in starts:  # the span of the processes' ages
        total.update(start_s=min(starts),
                     end_s=max(r["start_s"] + r.get("wall_s", 0.0) for r in rows))
    backends = ",".join(sorted({r.get("backend", "") for r in rows} - {""}))
    lines.append(line("all", backends, sum(r.get("episodes", 0) for r in rows), total))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.evaluation.timings",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="evaluation --out folders")
    args = p.parse_args(argv)
    try:
        print(time_split_table(args.runs), end="")
        if processes := process_table(args.runs):
            print("\n" + processes, end="")
    except (ValueError, KeyError) as err:
        print(f"timings: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
