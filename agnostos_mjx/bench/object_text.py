"""How much X-ICM's query text changes when object positions come from segmented point clouds.

X-ICM writes each named object of the scene as a voxel index (xicm_reference.md 3.4). The
original takes the mean of the object's segmented points per camera, averaged over the five
cameras that see it; we default to the object's ground-truth frame position. For each task
this resets the protocol's episodes (the eval's seeds, episodes and variations), renders the
five cameras at 128 px (the policy's `objects=segmented` spec) and compares the two texts:

* voxel indices that differ, out of 3 per object seen by some camera, and by how much;
* objects no camera sees (the original omits them from the text);
* query lines that differ (what the LLM would be shown), as a share of the episodes.

    python -m agnostos_mjx.bench.object_text --out eval/reports/object_text_segmented
    python -m agnostos_mjx.bench.object_text --quick        # 2 tasks x 4 episodes
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from agnostos_mjx.infra.cli import atomic_write


def compare_texts(truth: list[dict[str, list[int]]], segmented: list[dict[str, list[int]]]
                  ) -> dict[str, Any]:
    """Counts over worlds: indices that differ, their |difference|, omitted objects."""
    diffs, omitted, objects, worlds_differing = [], 0, 0, 0
    for t, s in zip(truth, segmented, strict=True):
        objects += len(t)
        omitted += sum(name not in s for name in t)
        d = [abs(a - b) for name in s for a, b in zip(s[name], t[name], strict=True)]
        diffs.extend(d)
        worlds_differing += int(any(d) or len(s) != len(t))
    d = np.asarray(diffs, int)
    return {"worlds": len(truth), "objects": objects, "omitted_objects": omitted,
            "indices": int(d.size), "indices_differing": int(np.count_nonzero(d)),
            "max_index_difference": int(d.max()) if d.size else 0,
            "mean_abs_difference_where_differing": float(d[d > 0].mean()) if np.any(d) else 0.0,
            "queries_differing": worlds_differing}


def task_row(name: str, seeds: list[int], episodes: int) -> dict[str, Any]:
    """One task: reset its protocol episodes, observe five cameras, compare the two texts."""
    import jax

    from agnostos_mjx.evaluation.protocol import episode_keys, episode_variations
    from agnostos_mjx.policies.xicm import SEGMENTED_SPEC
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task
    from agnostos_mjx.xicm.scene_text import object_voxels, segmented_object_voxels

    task = get_task(name)
    runner = Episodes(task, "native")
    seed_col = np.repeat(np.asarray(seeds, np.int64), episodes)
    keys = episode_keys(seed_col, np.tile(np.arange(episodes), len(seeds)))
    variations = episode_variations(keys, task.num_variations, task.split.value, "protocol")
    env = runner.reset(jax.numpy.asarray(keys), variations)
    truth = object_voxels(task, env.obs)
    segmented = segmented_object_voxels(runner.observe(env, SEGMENTED_SPEC))
    return {"task": name, "split": task.split.value, **compare_texts(truth, segmented)}


def markdown(rows: list[dict[str, Any]]) -> str:
    total = {k: sum(r[k] for r in rows) for k in
             ("worlds", "objects", "omitted_objects", "indices", "indices_differing",
              "queries_differing")}
    lines = ["| task | episodes | objects | omitted (unseen) | voxel indices differing | "
             "max difference | query lines differing |", "|---|---|---|---|---|---|---|"]
    for r in [*rows, {"task": "**all**", **total,
                      "max_index_difference": max(r["max_index_difference"] for r in rows)}]:
        share = r["indices_differing"] / max(r["indices"], 1)
        lines.append(f"| {r['task']} | {r['worlds']} | {r['objects']} | {r['omitted_objects']} | "
                     f"{r['indices_differing']}/{r['indices']} ({100 * share:.1f}%) | "
                     f"{r['max_index_difference']} | {r['queries_differing']}/{r['worlds']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from agnostos_mjx.infra.cli import setup_logging
    from agnostos_mjx.tasks import parse_tasks

    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.bench.object_text",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", default="unseen", help="task names and/or split names")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (as eval)")
    p.add_argument("--episodes", type=int, default=25, help="episodes per seed (as eval)")
    p.add_argument("--quick", action="store_true", help="first 2 tasks, seed 0, 4 episodes")
    p.add_argument("--out", type=Path, default=None,
                   help="folder for object_text.json and object_text.md (default: print only)")
    a = p.parse_args(argv)
    setup_logging(False)
    try:
        tasks = parse_tasks(a.tasks)
        seeds = [int(s) for s in a.seeds.split(",")]
    except (KeyError, ValueError) as e:
        print(f"error: {e.args[0] if e.args else e}")
        return 2
    if a.quick:
        tasks, seeds, a.episodes = tasks[:2], seeds[:1], 4
    rows = []
    for t in tasks:
        rows.append(task_row(t.name, seeds, a.episodes))
        print(json.dumps(rows[-1]), flush=True)
    table = markdown(rows)
    print(table, end="")
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        atomic_write(a.out / "object_text.json", json.dumps({"rows": rows}, indent=1) + "\n")
        atomic_write(a.out / "object_text.md", table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
