"""Demonstration selection by dynamics-model features (X-ICM's "lang_vis.out").

The query's features come from the shipped (or a given) dynamics checkpoint:
its current front frame and instruction -> ``lang``, ``vis.in``, ``vis.out``;
the memory holds the same features of every seen demo, computed once by
`python -m agnostos_mjx.xicm.build_memory --checkpoint ...`.
"""

from __future__ import annotations

import concurrent.futures
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from agnostos_mjx.dynamics.batching import rows_share_calls
from agnostos_mjx.infra.gather import RowBatcher, content_key, send_alone, then
from agnostos_mjx.xicm.memory import DemoMemory
from agnostos_mjx.xicm.query import Query, top_k

log = logging.getLogger("agnostos_mjx.xicm")
# DDIM steps of a query's vis.out.  Measured against the shipped model's 50 on 1,800 seen
# demos (docs/performance.md, `python -m agnostos_mjx.train.sampling_steps`):
# 10 steps keep the held-out prediction error (54.5% vs 54.3% below copying the first
# frame) and the leave-one-out same-task fraction (0.947 vs 0.946), share 97.8% of the
# top-18 with 50 steps, and cost a fifth; 5 steps lose prediction quality (51.3%) and
# top-1 agreement (0.86).  The memory's features stay at 50 steps.
QUERY_SAMPLE_STEPS = 10
# Threads that run chunks of queries at once.  One XLA CPU call keeps ~1.5 of 2 cores busy,
# so two calls fill them (docs/performance.md); a GPU runs one chunk after another either
# way.
CPU_WORKERS, ACCELERATOR_WORKERS = 2, 1


def default_checkpoint_path() -> Path:
    return Path(__file__).resolve().parents[1] / "assets" / "dynamics"


def load_pipeline(checkpoint: str | Path | None = None, sample_steps: int | None = None):
    """The feature pipeline; `sample_steps` overrides the checkpoint's DDIM steps."""
    from agnostos_mjx.dynamics.pipeline import Pipeline

    path = Path(checkpoint) if checkpoint else default_checkpoint_path()
    return Pipeline.load(path, **({} if sample_steps is None else {"sample_steps": sample_steps}))


def bank_features(bank, checkpoint: str | Path | None = None) -> dict[str, np.ndarray]:
    """lang / vis.in / vis.out of every demo of a bank (first frame + instruction)."""
    from agnostos_mjx.dynamics.features import extract

    first, _, instructions, _ = bank.frame_pairs("front")
    return extract(load_pipeline(checkpoint), first, instructions)


def request_key(queries: Sequence[Query]) -> tuple:
    """What orders gathered requests: their content (instructions, seeds, frames), which
    the run's tasks and seeds fix, unlike the order in which tasks reach the selector."""
    return (tuple(q.instruction for q in queries), tuple(q.seed for q in queries),
            content_key([q.frame for q in queries]))


class DynamicsSelector:
    def __init__(self, memory: DemoMemory, mode: str, checkpoint: str | Path | None = None,
                 metric: str = "cosine", sample_steps: int = QUERY_SAMPLE_STEPS):
        from agnostos_mjx.dynamics.features import parse_mode

        self.parts = parse_mode(mode)
        missing = [p for p in self.parts if p not in memory.features]
        if missing:
            raise ValueError(f"the memory lacks feature(s) {missing}; rebuild it with "
                             "python -m agnostos_mjx.xicm.build_memory --checkpoint ...")
        from agnostos_mjx.dynamics.features import normalised

        self.memory, self.mode, self.metric = memory, mode, metric
        self._bank = normalised(memory.features, mode, metric)  # once, not per round
        self._lang_cache: dict[str, np.ndarray] = {}
        self.name = mode
        if sample_steps < 1:
            raise ValueError(f"DDIM steps must be positive, got {sample_steps}")
        self.pipeline = load_pipeline(checkpoint, sample_steps)
        import jax

        workers = CPU_WORKERS if jax.default_backend() == "cpu" else ACCELERATOR_WORKERS
        # The queries of every task waiting on this selector share its chunks (one task's
        # replanning round rarely fills one): as they come on the CPU, gathered into a
        # deterministic order on a GPU; see agnostos_mjx/infra/gather.py.
        self._batcher = RowBatcher(self._similarities, self.pipeline.chunk_size, workers,
                                   gather=not rows_share_calls(), name="selection")

        if jax.default_backend() == "cpu" and "vis.out" in self.parts:
            # A CPU core's rate per DDIM step, from the 2-core figure per query at 10
            # steps (docs/performance.md).
            log.info("dynamics features run on the CPU here: about %.2f s per query per core "
                     "(%d DDIM steps x 3 guided passes), once per (re)plan; --selection text "
                     "is the fast model-free mode", 0.07 * sample_steps, sample_steps)

    def select(self, queries: Sequence[Query], k: int) -> list[np.ndarray]:
        future = self.submit(queries, k)
        send_alone(future)
        return future.result()

    def submit(self, queries: Sequence[Query], k: int) -> concurrent.futures.Future:
        """A future of the top-k memory indices per query (`select`)."""
        if any(q.frame is None for q in queries):
            raise ValueError("dynamics selection needs each query's front frame")
        rows = self._batcher.submit([(q.frame, q.instruction) for q in queries],
                                    key=request_key(queries))
        return then(rows, lambda sims: [top_k(s, k) for s in sims])

    def _similarities(self, rows: list[tuple[np.ndarray, str]]) -> list[np.ndarray]:
        """Similarity to every memory demo of up to one chunk of (frame, instruction) rows,
        padded to the chunk so that each network and the similarity run at one shape."""
        from agnostos_mjx.dynamics.features import query_similarity

        n, pad = len(rows), self.pipeline.chunk_size - len(rows)
        frames = np.stack([f for f, _ in rows] + [rows[-1][0]] * pad)
        instructions = [t for _, t in rows] + [rows[-1][1]] * pad
        lang = self.lang_features(instructions) if "lang" in self.parts else None
        sims = query_similarity(self.pipeline, frames, instructions, lang, self._bank,
                                self.metric)
        return list(sims[:n])

    def lang_features(self, instructions: list[str]) -> np.ndarray:
        """The instruction feature depends on the text alone, and a task's episodes share a
        few instructions: each is encoded once per run (on the GPU host this was a third
        of the selection time)."""
        new = sorted({t for t in instructions if t not in self._lang_cache})
        if new:
            self._lang_cache.update(zip(new, self.pipeline.lang(new).astype(np.float32)))
        return np.stack([self._lang_cache[t] for t in instructions])
