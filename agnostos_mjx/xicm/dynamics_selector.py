"""Demonstration selection by dynamics-model features (X-ICM's "lang_vis.out").

The query's features come from the shipped (or a given) dynamics checkpoint:
its current front frame and instruction -> ``lang``, ``vis.in``, ``vis.out``;
the memory holds the same features of every seen demo, computed once by
`python -m agnostos_mjx.xicm.build_memory --checkpoint ...`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from agnostos_mjx.xicm.memory import DemoMemory
from agnostos_mjx.xicm.selection import Query, top_k

log = logging.getLogger("agnostos_mjx.xicm")


def default_checkpoint_path() -> Path:
    return Path(__file__).resolve().parents[1] / "assets" / "dynamics"


def load_pipeline(checkpoint: str | Path | None = None):
    from agnostos_mjx.dynamics.pipeline import Pipeline

    path = Path(checkpoint) if checkpoint else default_checkpoint_path()
    return Pipeline.load(path)


def bank_features(bank, checkpoint: str | Path | None = None) -> dict[str, np.ndarray]:
    """lang / vis.in / vis.out of every demo of a bank (first frame + instruction)."""
    from agnostos_mjx.dynamics.features import extract

    first, _, instructions, _ = bank.frame_pairs("front")
    return extract(load_pipeline(checkpoint), first, instructions)


class DynamicsSelector:
    def __init__(self, memory: DemoMemory, mode: str, checkpoint: str | Path | None = None,
                 metric: str = "cosine"):
        from agnostos_mjx.dynamics.features import parse_mode

        self.parts = parse_mode(mode)
        missing = [p for p in self.parts if p not in memory.features]
        if missing:
            raise ValueError(f"the memory lacks feature(s) {missing}; rebuild it with "
                             "python -m agnostos_mjx.xicm.build_memory --checkpoint ...")
        self.memory, self.mode, self.metric = memory, mode, metric
        self.name = mode
        self.pipeline = load_pipeline(checkpoint)
        import jax

        if jax.default_backend() == "cpu" and "vis.out" in self.parts:
            log.warning("dynamics features run on the CPU here: about 2-4 s per query (50 DDIM "
                        "steps x 3 guided passes per core), and every (re)plan queries; a full "
                        "evaluation takes hours this way. Use a GPU, or --selection lang / "
                        "text for a fast run without the diffusion sampler")

    def select(self, queries: Sequence[Query], k: int) -> list[np.ndarray]:
        from agnostos_mjx.dynamics.features import extract, similarity

        if any(q.frame is None for q in queries):
            raise ValueError("dynamics selection needs each query's front frame")
        frames = np.stack([q.frame for q in queries])
        feats = extract(self.pipeline, frames, [q.instruction for q in queries], self.parts)
        sims = similarity(feats, self.memory.features, self.mode, self.metric)
        return [top_k(s, k) for s in sims]
