"""How many DDIM steps do X-ICM's selection features need?  A table, not a guess.

For each step count (e.g. 50, 20, 10, 5) of the shipped (or a given) dynamics model:
  * prediction: held-out latent MSE of the predicted last frame against copying the first;
  * leave-one-out: the fraction of each bank demo's top-K (lang+vis.out, itself excluded)
    from its own task, with the bank's features at the same step count;
  * agreement with the reference step count (the shipped memory's 50): each held-out demo
    is a query against the rest of the bank featurised at the reference count, as at
    evaluation time (the memory is fixed, only the query's sampler changes); reported as
    the mean overlap of the top-K and how often the top-1 (what `retrieval` replays) agrees;
  * speed: queries per second of the feature extractor at that step count (one batch shape,
    compiled once beforehand, so the figure is steady-state).

    python -m agnostos_mjx.train.sampling_steps --bank data/seen_bank --json steps.json
    python -m agnostos_mjx.train.sampling_steps --synthetic 24 --steps 4,2 --reference 4
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from agnostos_mjx.dynamics.data import FramePairs
from agnostos_mjx.dynamics.features import DEFAULT_K, FeatureIndex, extract, similarity
from agnostos_mjx.dynamics.pipeline import Pipeline
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.train.common import add_data_flags, load_data

MODE = "lang+vis.out"


def _topk_excluding_self(sims: np.ndarray, rows: np.ndarray, k: int) -> np.ndarray:
    """Top-k bank rows per query row, where query i is bank row rows[i] (excluded)."""
    s = sims.copy()
    s[np.arange(len(rows)), rows] = -np.inf
    return np.argsort(-s, axis=1, kind="stable")[:, :k]


def study(pairs: FramePairs, steps: list[int], reference: int, run: Path | None,
          holdout_every: int, k: int, batch: int) -> dict[str, Any]:
    """The table's rows, one per step count (see the module docstring)."""
    from agnostos_mjx.xicm.dynamics_selector import default_checkpoint_path

    run = run or default_checkpoint_path()
    tasks = np.array(pairs.tasks)
    held_rows = np.flatnonzero(np.arange(len(pairs)) % holdout_every == holdout_every - 1)
    held = pairs.subset(held_rows)
    feats: dict[int, dict[str, np.ndarray]] = {}
    rows: list[dict[str, Any]] = []
    for n in sorted(set(steps) | {reference}, reverse=True):
        pipe = Pipeline.load(run, chunk=batch, sample_steps=n)
        z_first, z_last = pipe.encode(held.first), pipe.encode(held.last)
        pipe.predict(z_first[:batch], held.instructions[:batch])  # compile outside the clock
        t0 = time.perf_counter()
        pred = pipe.predict(z_first, held.instructions)
        per_query = (time.perf_counter() - t0) / len(held)
        feats[n] = extract(pipe, pairs.first, pairs.instructions, ("lang", "vis.out"))
        index = FeatureIndex(feats[n], tasks, np.array(pairs.instructions))
        loo = similarity(index.features, index.features, MODE)
        top = _topk_excluding_self(loo, np.arange(len(pairs)), k)
        rows.append({
            "steps": n,
            "mse_predicted": float(np.mean((pred - z_last) ** 2)),
            "mse_first_frame": float(np.mean((z_first - z_last) ** 2)),
            "loo_same_task": float(np.mean(tasks[top] == tasks[:, None])),
            "queries_per_s": 1.0 / per_query,
        })
    ref = feats[reference]
    for row in rows:
        n = row["steps"]
        query = {p: v[held_rows] for p, v in feats[n].items()}
        chosen = _topk_excluding_self(similarity(query, ref, MODE), held_rows, k)
        truth = _topk_excluding_self(similarity({p: v[held_rows] for p, v in ref.items()},
                                                ref, MODE), held_rows, k)
        row["topk_overlap"] = float(np.mean([len(set(a) & set(b)) / k
                                             for a, b in zip(chosen, truth)]))
        row["top1_agreement"] = float(np.mean(chosen[:, 0] == truth[:, 0]))
        row["reduction"] = 1.0 - row["mse_predicted"] / max(row["mse_first_frame"], 1e-12)
    return {"model": str(run), "reference_steps": reference, "k": k, "mode": MODE,
            "demos": len(pairs), "held_out": len(held_rows), "rows": rows}


def markdown(result: dict[str, Any]) -> str:
    ref = result["reference_steps"]
    lines = [f"DDIM steps vs selection quality ({result['mode']}, K={result['k']}, "
             f"{result['demos']} demos, {result['held_out']} held out; agreement against "
             f"{ref} steps)", "",
             "| steps | held-out MSE (copy) | reduction | LOO same-task | top-K overlap | "
             "top-1 agreement | queries/s |", "|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['steps']} | {r['mse_predicted']:.4f} ({r['mse_first_frame']:.4f}) "
                     f"| {100 * r['reduction']:.1f}% | {r['loo_same_task']:.3f} | "
                     f"{r['topk_overlap']:.3f} | {r['top1_agreement']:.3f} | "
                     f"{r['queries_per_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    configure_jax()
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.train.sampling_steps",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, default=None,
                   help="dynamics export or run directory (default: the shipped model)")
    add_data_flags(p, training=False)
    p.add_argument("--steps", default="50,20,10,5", help="DDIM step counts to compare")
    p.add_argument("--reference", type=int, default=50,
                   help="step count the agreement is measured against (the shipped memory's)")
    p.add_argument("--holdout-every", type=int, default=10,
                   help="held-out demos: i %% N == N-1, as in training (default 10)")
    p.add_argument("--k", type=int, default=DEFAULT_K, help="demos selected per query")
    p.add_argument("--batch", type=int, default=64, help="queries per feature call")
    p.add_argument("--json", type=Path, default=None, help="write the table as JSON here "
                   "(and as Markdown next to it)")
    args = p.parse_args(argv)
    try:
        steps = [int(s) for s in args.steps.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"--steps: expected comma-separated integers, got {args.steps!r}") from None
    result = study(load_data(args), steps, args.reference, args.run, args.holdout_every,
                   args.k, args.batch)
    table = markdown(result)
    print(table, end="")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
        args.json.with_suffix(".md").write_text(table)
    return result


if __name__ == "__main__":
    main()
