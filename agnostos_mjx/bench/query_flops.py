"""The demo selection's arithmetic per query and this machine's rate for it:
``python -m agnostos_mjx.bench.query_flops``.

A query's features are guided DDIM: each step runs the UNet on three conditionings (first
frame and instruction, frame only, neither).  XLA's cost analysis gives the floating-point
operations of one such UNet call (a scan's body counts once, so the step is analysed
alone); times the DDIM steps, per row of a chunk, that is the work of one query.  The
rates are measured on the selection's own calls (one thread, and as many threads as the
selector runs) and, for reference, on a 1024^3 matmul, about the best this machine's XLA
does.  With ``--queries N`` (the main job has ~5,900, counted from its records' plans) it
prints the time that many queries need at each rate: a floor for a run on this machine.

    python -m agnostos_mjx.bench.query_flops --queries 5916
    python -m agnostos_mjx.bench.query_flops --quick
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.config import LATENT_CHANNELS, LATENT_SIZE
from agnostos_mjx.dynamics.pipeline import Pipeline
from agnostos_mjx.infra.cli import HelpFormatter, atomic_write
from agnostos_mjx.infra.settings import configure_jax


def unet_call_flops(pipeline: Pipeline, rows: int) -> float:
    """Floating-point operations of one UNet call on `rows` rows (text encoder included)."""
    graph, state = pipeline.model_split
    x = jnp.zeros((rows, LATENT_SIZE, LATENT_SIZE, LATENT_CHANNELS))
    ids, mask = pipeline.tokens(["press the button"] * rows)

    def call(state, x, ids, mask):
        model = nnx.merge(graph, state)
        ctx, pooled = model.text(ids, mask)
        return model.unet(x, x, jnp.full((rows,), 500), ctx, mask, pooled)

    cost = jax.jit(call).lower(state, x, ids, mask).compile().cost_analysis()
    return float((cost[0] if isinstance(cost, list) else cost)["flops"])


def seconds_per_chunk(pipeline: Pipeline, threads: int, repeats: int) -> float:
    """Wall seconds per chunk of vis.out features with `threads` threads calling at once."""
    n = pipeline.chunk_size
    frames = np.random.default_rng(0).normal(size=(n, LATENT_SIZE, LATENT_SIZE,
                                                   LATENT_CHANNELS)).astype(np.float32)
    words = ["press the button"] * n
    pipeline.predict(frames, words)  # compile
    t0 = time.perf_counter()
    workers = [threading.Thread(target=lambda: [pipeline.predict(frames, words)
                                                for _ in range(repeats)])
               for _ in range(threads)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    return (time.perf_counter() - t0) / (threads * repeats)


def matmul_rate(size: int = 1024, repeats: int = 10) -> float:
    """FLOP/s of a size^3 float32 matmul."""
    a = jnp.ones((size, size))
    f = jax.jit(lambda a: a @ a)
    f(a).block_until_ready()
    t0 = time.perf_counter()
    for _ in range(repeats):
        out = f(a)
    out.block_until_ready()
    return 2 * size**3 * repeats / (time.perf_counter() - t0)


def measure(pipeline: Pipeline, threads: int, repeats: int) -> dict:
    n, steps = pipeline.chunk_size, pipeline.diffusion.sample_steps
    per_query = unet_call_flops(pipeline, 3 * n) * steps / n
    out = {"device": f"{jax.default_backend()} ({jax.devices()[0].device_kind})",
           "chunk": n, "ddim_steps": steps, "gflop_per_query": per_query / 1e9,
           "matmul_gflops": matmul_rate() / 1e9}
    for k in sorted({1, threads}):
        s = seconds_per_chunk(pipeline, k, repeats)
        out[f"s_per_query_{k}_threads"] = s / n
        out[f"gflops_{k}_threads"] = per_query * n / s / 1e9
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.bench.query_flops",
                                formatter_class=HelpFormatter,
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true",
                   help="the tiny untrained model of the quick preset: a smoke run in seconds")
    p.add_argument("--checkpoint", type=Path, default=None,
                   help="export or run directory (default: the shipped model)")
    p.add_argument("--queries", type=int, default=0,
                   help="also print the time this many queries need at each rate")
    p.add_argument("--repeats", type=int, default=3, help="timed chunks per thread")
    p.add_argument("--out", type=Path, default=None, help="also write the numbers as JSON")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    a = build_parser().parse_args(argv)
    from agnostos_mjx.xicm.dynamics_selector import (
        ACCELERATOR_WORKERS,
        CPU_WORKERS,
        QUERY_SAMPLE_STEPS,
        load_pipeline,
    )

    if a.quick:
        from agnostos_mjx.bench.dynamics import quick_pipeline

        pipeline = quick_pipeline()
    else:
        pipeline = load_pipeline(a.checkpoint, QUERY_SAMPLE_STEPS)
    threads = CPU_WORKERS if jax.default_backend() == "cpu" else ACCELERATOR_WORKERS
    r = measure(pipeline, threads, a.repeats)
    print(f"device: {r['device']}; {r['ddim_steps']} DDIM steps x 3 guided UNet passes, "
          f"chunks of {r['chunk']}: {r['gflop_per_query']:.1f} GFLOP per query")
    rates = [(f"selection, {k} thread{'s' * (k > 1)}", r[f"gflops_{k}_threads"])
             for k in sorted({1, threads})] + [("1024^3 matmul", r["matmul_gflops"])]
    print("| rate of | GFLOP/s | s per query |" + (f" {a.queries} queries |" if a.queries else "")
          + "\n|---|---|---|" + ("---|" if a.queries else ""))
    for name, gflops in rates:
        per = r["gflop_per_query"] / gflops
        print(f"| {name} | {gflops:.1f} | {per:.3f} |"
              + (f" {a.queries * per / 60:.1f} min |" if a.queries else ""))
    if a.out is not None:
        atomic_write(a.out, json.dumps({**r, "queries": a.queries}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
