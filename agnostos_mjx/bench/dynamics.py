"""Dynamics-model throughput: ``python -m agnostos_mjx.bench.dynamics``.

Two numbers the evaluation and the training depend on:

* training steps/s of the dynamics model (text encoder + UNet, AdamW, one batch of
  random latents), timed after a warm-up step;
* feature queries/s: ``lang`` + ``vis.out`` of N first frames + instructions (the 50-step
  guided DDIM sampler), for each batch size, timed after a warm-up call of that size.

Targets (printed beside the numbers; nothing asserts on them): on one data-centre GPU the
default preset should train at >= 20 steps/s (the training run's rate, below it, is in
docs/performance.md) and answer >= 75 queries/s, so that a replan of 75 worlds costs
about a second.  ``--quick`` uses the tiny preset and 8 DDIM steps: a CPU
smoke run in seconds.

``--old-vs-new`` (issue 13) times instead the evaluation's query features (encode + ``vis.out``
at its 10 DDIM steps, what `DynamicsSelector.select` computes per (re)plan) of the code before
the CPU work (flax's GroupNorm and attention, the same weights, chunks of 64 with the last one
padded to 64) against the current code, alternating in this one process, and checks that
both give the same features (vis.in, vis.out, lang) up to float round-off.

Examples::

    python -m agnostos_mjx.bench.dynamics --quick
    python -m agnostos_mjx.bench.dynamics --batches 1,8,75 --out dyn_bench.json
    python -m agnostos_mjx.bench.dynamics --old-vs-new --batches 8,75 --repeats 5
    python -m agnostos_mjx.bench.dynamics --old-vs-new --quick
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import jax
import numpy as np
from flax import nnx

from agnostos_mjx.bench.backends import seconds_per_call
from agnostos_mjx.dynamics.autoencoder import Autoencoder
from agnostos_mjx.dynamics.config import FEATURE_DIM, LATENT_CHANNELS, LATENT_SIZE, PRESETS
from agnostos_mjx.dynamics.diffusion import DynamicsModel, diffusion_loss
from agnostos_mjx.dynamics.features import extract
from agnostos_mjx.dynamics.layers import GroupNorm, create
from agnostos_mjx.dynamics.pipeline import Pipeline
from agnostos_mjx.dynamics.text import tokenize
from agnostos_mjx.infra.cli import HelpFormatter, atomic_write
from agnostos_mjx.infra.settings import configure_jax

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


OLD_CHUNK = 64  # rows per call before issue 13, on every backend


def stock_layers(module: nnx.Module) -> nnx.Module:
    """A copy of `module` (sharing nothing it could change) that runs flax's own GroupNorm and
    dot-product attention, as the dynamics code did before issue 13: the reference the
    CPU-specialised layers must reproduce."""
    module = nnx.clone(module)
    for _, sub in nnx.iter_modules(module):
        if isinstance(sub, nnx.MultiHeadAttention):
            sub.attention_fn = nnx.dot_product_attention
        if type(sub) is GroupNorm:
            sub.__class__ = nnx.GroupNorm  # same fields and parameters: flax's __call__
    return module


def reference_pipeline(pipeline: Pipeline) -> Pipeline:
    """`pipeline` as it ran before issue 13: stock layers, chunks of 64 (`old_rows`)."""
    model = None if pipeline.model is None else stock_layers(pipeline.model)
    return replace(pipeline, ae=stock_layers(pipeline.ae), model=model, chunk=OLD_CHUNK)


def old_rows(n: int) -> int:
    """Rows the old `map_chunks` computed for n queries: a job of more than a chunk had its
    last chunk padded to the full chunk (75 queries: 128 rows); a smaller one was padded to
    the next power of two."""
    return n if n <= OLD_CHUNK else -(-n // OLD_CHUNK) * OLD_CHUNK


def relative_diff(a: np.ndarray, b: np.ndarray) -> float:
    """max over rows of max |a - b| / ||a||."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    norm = np.maximum(np.linalg.norm(a, axis=1), 1e-12)
    return float((np.abs(a - b).max(axis=1) / norm).max())


def query_inputs(n: int, seed: int = 0) -> tuple[np.ndarray, list[str]]:
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 255, (n, 128, 128, 3), dtype=np.uint8)
    return frames, [f"press the button number {i}" for i in range(n)]


def bench_old_vs_new(pipeline: Pipeline, batches: Sequence[int], repeats: int) -> list[dict]:
    """Seconds per query of the query features, old (`reference_pipeline`, with the old
    padding) against `pipeline`, alternating old/new and new/old, medians over `repeats`."""
    old = reference_pipeline(pipeline)
    rows = []
    for n in batches:
        frames, words = query_inputs(n)
        m = old_rows(n)
        pad = np.concatenate([np.arange(n), np.full(m - n, n - 1)]).astype(int)
        old_frames, old_words = frames[pad], [words[i] for i in pad]
        runs = {
            "old": (old, old_frames, old_words),
            "new": (pipeline, frames, words),
        }
        a = extract(old, frames, words)  # warm-up (compiles) and the features to compare
        extract(*runs["old"], ("vis.out",))
        b = extract(pipeline, frames, words)
        times: dict[str, list[float]] = {"old": [], "new": []}
        for r in range(repeats):
            for name in ("old", "new") if r % 2 == 0 else ("new", "old"):
                t0 = time.perf_counter()
                extract(*runs[name], ("vis.out",))
                times[name].append((time.perf_counter() - t0) / n)
        old_s, new_s = float(np.median(times["old"])), float(np.median(times["new"]))
        rows.append({
            "batch": n, "old_rows": m, "old_chunk": OLD_CHUNK, "new_chunk": pipeline.chunk_size,
            "old_s_per_query": old_s, "new_s_per_query": new_s, "ratio": old_s / new_s,
            "ratios": [o / w for o, w in zip(times["old"], times["new"])],
            "diff": {k: relative_diff(a[k], b[k]) for k in a},
        })
    return rows


def quick_pipeline() -> Pipeline:
    """Untrained tiny-preset pipeline (the quick preset's 8 DDIM steps)."""
    p = PRESETS["quick"]
    ae = create(lambda: Autoencoder(p.ae, rngs=nnx.Rngs(0)))
    model = create(lambda: DynamicsModel(p.text, p.unet, rngs=nnx.Rngs(0)))
    return Pipeline(ae, 1.0, model, p.text, p.diffusion, chunk=8)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.bench.dynamics",
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
    p.add_argument("--old-vs-new", action="store_true",
                   help="time the query features of the code before issue 13 against the "
                        "current code, alternating in this process (default batches 8,75; "
                        "--quick: 1,4); skips the training benchmark")
    p.add_argument("--steps", type=int, default=None,
                   help="DDIM steps of --old-vs-new (default: the evaluation's query steps, "
                        "10; --quick: 8)")
    p.add_argument("--repeats", type=int, default=3,
                   help="timed calls of each of old and new per batch size (--old-vs-new)")
    p.add_argument("--out", type=Path, default=None, help="also write the numbers as JSON")
    return p


def main_old_vs_new(a: argparse.Namespace, batches: list[int]) -> int:
    if a.quick:
        pipeline = quick_pipeline()
        pipeline = replace(pipeline, chunk=None,
                           diffusion=replace(pipeline.diffusion, sample_steps=a.steps or 8))
        batches = [1, 4] if a.batches == "1,8,75" else batches
    else:
        from agnostos_mjx.xicm.dynamics_selector import QUERY_SAMPLE_STEPS, load_pipeline

        pipeline = load_pipeline(a.checkpoint, a.steps or QUERY_SAMPLE_STEPS)
        batches = [8, 75] if a.batches == "1,8,75" else batches
    device = f"{jax.default_backend()} ({jax.devices()[0].device_kind})"
    rows = bench_old_vs_new(pipeline, batches, a.repeats)
    steps = pipeline.diffusion.sample_steps
    print(f"device: {device}; query features (encode + vis.out, {steps} DDIM steps), "
          f"median of {a.repeats} alternating calls")
    print("| queries per call | old rows (chunk) | new chunk | old ms/query | new ms/query "
          "| old/new | max relative feature diff |\n|---|---|---|---|---|---|---|")
    for r in rows:
        diff = max(r["diff"].values())
        print(f"| {r['batch']} | {r['old_rows']} ({r['old_chunk']}) | {r['new_chunk']} | "
              f"{1000 * r['old_s_per_query']:.0f} | {1000 * r['new_s_per_query']:.0f} | "
              f"{r['ratio']:.2f} | {diff:.1e} |")
    if a.out is not None:
        atomic_write(a.out, json.dumps({"device": device, "sample_steps": steps,
                                        "old_vs_new": rows}, indent=1) + "\n")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    a = build_parser().parse_args(argv)
    batches = [int(x) for x in a.batches.split(",") if x.strip()]
    if a.old_vs_new:
        return main_old_vs_new(a, batches)
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
