"""Which seen tasks does X-ICM draw its demonstrations from, per unseen task?

For each task, `--scenes` initial scenes (seed 0, episodes 0..N-1, protocol variation) are
rendered from the front camera and the top-K demos are selected exactly as the policies do
(default `lang+vis.out` with the shipped model and memory).  The report gives the histogram of
seen tasks over all selected demos, the majority task's share, and how stable that is across
scenes: in how many scenes the same seen task holds the most demos.

    python -m agnostos_mjx.bench.selection --out selection_report
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from agnostos_mjx.infra.cli import atomic_write


def task_histogram(name: str, selector: Any, memory: Any, scenes: int, k: int) -> dict[str, Any]:
    """One task's row: seen-task counts over its scenes' top-k, and per-scene majorities."""
    import jax

    from agnostos_mjx.evaluation.protocol import episode_keys, episode_variations
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task
    from agnostos_mjx.xicm.query import Query

    task = get_task(name)
    runner = Episodes(task, "native")
    keys = episode_keys(np.zeros(scenes, np.int64), np.arange(scenes))
    variations = episode_variations(keys, task.num_variations, task.split.value, "protocol")
    env = runner.reset(jax.numpy.asarray(keys), variations)
    frames = runner.render(env, "front", 128, 128)
    queries = [Query(task.descriptions(int(v))[0], i, frames[i]) for i, v in enumerate(variations)]
    chosen = selector.select(queries, k)
    per_scene = [Counter(memory.task[idx].tolist()) for idx in chosen]
    total = sum(per_scene, Counter())
    majority, count = total.most_common(1)[0]
    scene_majorities = Counter(c.most_common(1)[0][0] for c in per_scene)
    return {"task": name, "split": task.split.value, "scenes": scenes, "k": k,
            "histogram": dict(total.most_common()), "majority": majority,
            "majority_share": count / (scenes * k),
            "scenes_with_that_majority": scene_majorities.get(majority, 0),
            "distinct_scene_majorities": len(scene_majorities)}


def markdown(rows: list[dict[str, Any]], mode: str) -> str:
    lines = [f"Seen tasks of the selected demos ({mode}; K={rows[0]['k']}, "
             f"{rows[0]['scenes']} scenes per task)", "",
             "| unseen task | majority seen task | share of all selected | scenes where it is the "
             "majority | top 3 (demos) |", "|---|---|---|---|---|"]
    for r in rows:
        top = ", ".join(f"{t} {n}" for t, n in list(r["histogram"].items())[:3])
        lines.append(f"| {r['task']} | {r['majority']} | {100 * r['majority_share']:.0f}% | "
                     f"{r['scenes_with_that_majority']}/{r['scenes']} | {top} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.bench.selection",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", default="unseen", help="task names and/or split names")
    p.add_argument("--scenes", type=int, default=10, help="scenes per task (seed 0)")
    p.add_argument("--k", type=int, default=18, help="demos selected per scene")
    p.add_argument("--selection", default="auto", help="as eval's --selection")
    p.add_argument("--out", type=Path, default=None,
                   help="folder for selection.json and selection.md (default: print only)")
    args = p.parse_args(argv)
    from agnostos_mjx.tasks import parse_tasks
    from agnostos_mjx.xicm.memory import DemoMemory, default_memory_path
    from agnostos_mjx.xicm.selection import make_selector, resolve_selection

    try:
        tasks = parse_tasks(args.tasks)
    except KeyError as e:
        print(f"error: {e.args[0] if e.args else e}")
        return 2
    memory = DemoMemory.load(default_memory_path())
    mode = resolve_selection(args.selection, memory)
    selector = make_selector(mode, memory)
    rows = [task_histogram(t.name, selector, memory, args.scenes, args.k) for t in tasks]
    table = markdown(rows, mode)
    print(table, end="")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write(args.out / "selection.json", json.dumps({"mode": mode, "rows": rows},
                                                             indent=1) + "\n")
        atomic_write(args.out / "selection.md", table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
