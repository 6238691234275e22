"""Evaluate a trained dynamics model; print and write JSON.

(a) Prediction: on held-out demos, MSE(predicted last latent, true last latent)
    against the copy baseline MSE(first latent, true last latent); the target is
    a reduction of at least 30%.
(b) Selection: leave-one-out over the whole bank, the mean fraction of each
    demo's top-K (K = 18) that come from its own task, per selection mode.

    python -m agnostos_mjx.train.evaluate --run runs/dyn --bank BANK
    python -m agnostos_mjx.train.evaluate --run EXPORT_DIR --bank BANK --json eval.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from agnostos_mjx.dynamics.data import FramePairs
from agnostos_mjx.dynamics.export_format import is_export
from agnostos_mjx.dynamics.features import (
    DEFAULT_K,
    FeatureIndex,
    build_index,
    leave_one_out_same_task,
)
from agnostos_mjx.dynamics.pipeline import Pipeline
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.train.common import add_data_flags, load_data

TARGET_REDUCTION = 0.30
MODES = (
    "random",
    "lang",
    "vis.in",
    "vis.out",
    "lang+vis.in",
    "lang+vis.out",
    "vis.in+vis.out",
    "lang+vis.in+vis.out",
)


def prediction_error(pipe: Pipeline, held: FramePairs) -> dict[str, Any]:
    """(a): latent MSE of the model's prediction and of copying the first frame."""
    z_first, z_last = pipe.encode(held.first), pipe.encode(held.last)
    pred = pipe.predict(z_first, held.instructions)
    mse_pred = float(np.mean((pred - z_last) ** 2))
    mse_copy = float(np.mean((z_first - z_last) ** 2))
    reduction = 1.0 - mse_pred / mse_copy if mse_copy > 0 else 0.0
    return {
        "demos": len(held),
        "mse_predicted": mse_pred,
        "mse_first_frame": mse_copy,
        "reduction": reduction,
        "target_reduction": TARGET_REDUCTION,
        "target_met": reduction >= TARGET_REDUCTION,
    }


def selection_quality(
    index: FeatureIndex, modes: tuple[str, ...] = MODES, k: int = DEFAULT_K, metric: str = "cosine"
) -> dict[str, float]:
    """(b): leave-one-out same-task fraction of the top-k, per mode."""
    return {mode: leave_one_out_same_task(index, mode, k, metric) for mode in modes}


def evaluate(
    pipe: Pipeline,
    pairs: FramePairs,
    holdout_every: int,
    index_path: Path | None = None,
    k: int = DEFAULT_K,
    metric: str = "cosine",
) -> dict[str, Any]:
    _, held = pairs.split(holdout_every)
    t0 = time.perf_counter()
    pred = prediction_error(pipe, held)
    index = build_index(pipe, pairs, index_path, pipe.identity)
    return {
        "model": pipe.identity,
        "sampling": {
            "steps": pipe.diffusion.sample_steps,
            "image_guidance": pipe.diffusion.image_guidance,
            "text_guidance": pipe.diffusion.text_guidance,
            "seed": pipe.diffusion.sample_seed,
        },
        "prediction": pred,
        "selection": {
            "k": k,
            "metric": metric,
            "demos": len(index),
            "same_task_fraction": selection_quality(index, MODES, k, metric),
        },
        "seconds": round(time.perf_counter() - t0, 1),
    }


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m agnostos_mjx.train.evaluate",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--run",
        type=Path,
        required=True,
        help="dynamics run directory (python -m agnostos_mjx.train.dynamics) or an export "
        "(python -m agnostos_mjx.train.export; then give --json, nothing is written into it)",
    )
    p.add_argument(
        "--ae",
        type=Path,
        help="autoencoder run directory (default: the one the dynamics run recorded)",
    )
    add_data_flags(p, training=False)
    p.add_argument(
        "--holdout-every",
        type=int,
        default=10,
        help="held-out demos for (a): i %% N == N-1; must match training (default 10)",
    )
    p.add_argument(
        "--k", type=int, default=DEFAULT_K, help=f"demos selected per query (default {DEFAULT_K})"
    )
    p.add_argument(
        "--metric",
        choices=("cosine", "dot"),
        default="cosine",
        help="cosine (default) or the original's raw dot product",
    )
    p.add_argument("--sample-steps", type=int, help="DDIM steps (default: the model's config, 50)")
    p.add_argument("--image-guidance", type=float, help="image guidance scale (default 2.5)")
    p.add_argument("--text-guidance", type=float, help="text guidance scale (default 2.5)")
    p.add_argument("--batch", type=int, default=64, help="demos per inference batch (default 64)")
    p.add_argument(
        "--index",
        type=Path,
        help="feature index cache (default RUN/index.npz, none for an export); rebuilt when "
        "model or bank change",
    )
    p.add_argument("--json", type=Path, help="where to write the results (default RUN/eval.json)")
    return p


def main(argv: list[str] | None = None) -> dict[str, Any]:
    configure_jax()
    args = parser().parse_args(argv)
    sampling = {
        k: v
        for k, v in (
            ("sample_steps", args.sample_steps),
            ("image_guidance", args.image_guidance),
            ("text_guidance", args.text_guidance),
        )
        if v is not None
    }
    exported = is_export(args.run)
    if exported and args.json is None:
        raise SystemExit(f"--run {args.run} is an export (shipped files): give --json PATH")
    pipe = Pipeline.load(args.run, args.ae, chunk=args.batch, **sampling)
    result = evaluate(
        pipe,
        load_data(args),
        args.holdout_every,
        args.index or (None if exported else args.run / "index.npz"),
        args.k,
        args.metric,
    )
    out = args.json or args.run / "eval.json"
    out.write_text(json.dumps(result, indent=2))
    p = result["prediction"]
    print(
        f"(a) held-out latent MSE: predicted {p['mse_predicted']:.4f} vs first frame {p['mse_first_frame']:.4f}: "
        f"{100 * p['reduction']:.1f}% lower (target >= {100 * TARGET_REDUCTION:.0f}%: {'met' if p['target_met'] else 'NOT met'})"
    )
    print(f"(b) leave-one-out top-{args.k} same-task fraction ({args.metric}):")
    for mode, frac in result["selection"]["same_task_fraction"].items():
        print(f"    {mode:22s} {frac:.3f}")
    print(f"written {out}")
    return result


if __name__ == "__main__":
    main()
