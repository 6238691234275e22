"""Dynamics-model throughput: ``python -m agnostos_mjx.dynamics.bench``.

Two numbers the evaluation and the training depend on:

* training steps/s of the dynamics model (text encoder + UNet, AdamW, one batch of
  random latents), timed after a warm-up step;
* feature queries/s: ``lang`` + ``vis.out`` of N first frames + instructions (the 50-step
  guided DDIM sampler), for each batch size, timed after a warm-up call of that size.

Targets (printed beside the numbers; nothing asserts on them): on one H100/H200 the
default preset should train at >= 20 steps/s (measured 12.5 in the training run, so a
fixed per-step cost is suspected) and answer >= 75 queries/s, so that a replan of 75
worlds costs about a second.  ``--quick`` uses the tiny preset and 8 DDIM steps: a CPU
smoke run in seconds.

Examples::

    python -m agnostos_mjx.dynamics.bench --quick
    python -m agnostos_mjx.dynamics.bench --batches 1,8,75 --out dyn_bench.json
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import jax
import numpy as np
from flax import nnx

from agnostos_mjx.bench import seconds_per_call
from agnostos_mjx.cli import HelpFormatter, atomic_write
from agnostos_mjx.dynamics.autoencoder import Autoencoder
from agnostos_mjx.dynamics.config import FEATURE_DIM, LATENT_CHANNELS, LATENT_SIZE, PRESETS
from agnostos_mjx.dynamics.diffusion import DynamicsModel, diffusion_loss
from agnostos_mjx.dynamics.features import extract
from agnostos_mjx.dynamics.layers import create
from agnostos_mjx.dynamics.pipeline import Pipeline
from agnostos_mjx.dynamics.text import tokenize

TARGET_STEPS_PER_S = 20.0
TARGET_QUERIES_PER_S = 75.0


def bench_training(preset: str, min_time: float) -> dict[str, float]:
    from agnostos_mjx.train.common import make_step, optimizer

    p = PRESETS[preset]
    model = create(lambda: DynamicsModel(p.text, p.unet, rngs=nnx.Rngs(0)))
    graphdef, params = nnx.split(model)
    tx = optimizer(p.dyn_train)
    opt_state = tx.init(params)
    step = make_step(graphdef, tx, lambda m, b, key: diffusion_loss(m, p.diffusion, *b, key))
    b = p.dyn_train.batch_size
    rng = np.random.default_rng(0)
    shape = (b, LATENT_SIZE, LATENT_SIZE, LATENT_CHANNELS)
    ids, mask = tokenize(["push the red block left"] * b, p.text.max_len)
    batch = (rng.normal(size=shape).astype(np.float32), rng.normal(size=shape).astype(np.float32),
             ids, mask)
    state = {"params": params, "opt": opt_state, "i": 0}

    def one() -> jax.Array:
        state["params"], state["opt"], loss = step(state["params"], state["opt"], batch,
                                                   jax.random.key(state["i"]))
        state["i"] += 1
        return loss

    one()  # compile
    jax.block_until_ready(one())  # and a second call: optax's state may change weak types once
    seconds, _ = seconds_per_call(one, min_time)
    return {"preset": preset, "batch": b, "steps_per_s": 1.0 / seconds}


def bench_features(pipeline: Pipeline, batches: Sequence[int], min_time: float) -> list[dict]:
    rows = []
    rng = np.random.default_rng(0)
    for n in batches:
        frames = rng.integers(0, 255, (n, 128, 128, 3), dtype=np.uint8)
        words = [f"press the button number {i}" for i in range(n)]
        call = lambda f=frames, w=words: extract(pipeline, f, w, ("lang", "vis.out"))  # noqa: E731
        call()  # compile this size
        seconds, _ = seconds_per_call(call, min_time)
        rows.append({"batch": n, "queries_per_s": n / seconds, "seconds_per_call": seconds})
    return rows


def quick_pipeline() -> Pipeline:
    """Untrained tiny-preset pipeline (the quick preset's 8 DDIM steps)."""
    p = PRESETS["quick"]
    ae = create(lambda: Autoencoder(p.ae, rngs=nnx.Rngs(0)))
    model = create(lambda: DynamicsModel(p.text, p.unet, rngs=nnx.Rngs(0)))
    return Pipeline(ae, 1.0, model, p.text, p.diffusion, chunk=8)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.dynamics.bench",
                                formatter_class=HelpFormatter, description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true",
                   help="tiny untrained model, quick preset, batches 1,4: a CPU smoke run")
    p.add_argument("--checkpoint", type=Path, default=None,
                   help="export or run directory for the feature benchmark (default: the "
                        "shipped model)")
    p.add_argument("--preset", default="default", choices=tuple(PRESETS),
                   help="model sizes for the training benchmark")
    p.add_argument("--batches", default="1,8,75",
                   help="comma-separated query counts for the feature benchmark")
    p.add_argument("--min-time", type=float, default=2.0,
                   help="seconds each measurement repeats for (after its warm-up)")
    p.add_argument("--out", type=Path, default=None, help="also write the numbers as JSON")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    batches = [int(x) for x in a.batches.split(",") if x.strip()]
    if a.quick:
        a.preset, batches, a.min_time = "quick", [1, 4], min(a.min_time, 0.5)
        pipeline = quick_pipeline()
    else:
        from agnostos_mjx.xicm.dynamics_selector import load_pipeline

        pipeline = load_pipeline(a.checkpoint)
    device = f"{jax.default_backend()} ({jax.devices()[0].device_kind})"
    training = bench_training(a.preset, a.min_time)
    features = bench_features(pipeline, batches, a.min_time)
    print(f"device: {device}; feature dim {FEATURE_DIM}")
    print(f"training ({training['preset']} preset, batch {training['batch']}): "
          f"{training['steps_per_s']:.1f} steps/s (GPU target >= {TARGET_STEPS_PER_S:.0f})")
    print("| queries per call | queries/s | s per call |\n|---|---|---|")
    for r in features:
        print(f"| {r['batch']} | {r['queries_per_s']:.1f} | {r['seconds_per_call']:.3f} |")
    print(f"(GPU target >= {TARGET_QUERIES_PER_S:.0f} queries/s at 75)")
    if a.out is not None:
        atomic_write(a.out, json.dumps({"device": device, "training": training,
                                        "features": features}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
