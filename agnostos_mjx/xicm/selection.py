"""Choosing the K in-context demonstrations for a query.

A selector ranks the seen-demo memory for each query (instruction + current
front frame) and returns memory indices, most similar first.  Modes:

* ``random``: K demos drawn without replacement from a per-query seed (the
  original's "w/o selection" baseline used one fixed stream, seed 42, for
  every seed; ours follows the evaluation seed);
* ``text``: cosine similarity of hashed character-trigram vectors of the
  instructions, a model-free lexical baseline;
* dynamics-model features (``lang``, ``vis.in``, ``vis.out`` and ``+``
  combinations, default ``lang+vis.out``), cosine over L2-normalised parts,
  or the original's raw dot product with ``metric="dot"`` (dynamics_selector.py).

The query, the selector protocol and top-k live in query.py, shared with dynamics_selector.py.
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Sequence

import numpy as np

from agnostos_mjx.xicm.memory import DemoMemory
from agnostos_mjx.xicm.query import (  # Query: also imported from here
    ImmediateSelector,
    Query,
    Selector,
    top_k,
)

log = logging.getLogger("agnostos_mjx.xicm")
TEXT_DIM = 4096
FEATURE_PARTS = ("lang", "vis.in", "vis.out")


class RandomSelector(ImmediateSelector):
    name = "random"

    def __init__(self, memory: DemoMemory):
        self.memory = memory

    def select(self, queries: Sequence[Query], k: int) -> list[np.ndarray]:
        m = len(self.memory)
        return [np.random.default_rng(q.seed).choice(m, size=min(k, m), replace=False)
                for q in queries]


def text_vector(text: str) -> np.ndarray:
    """L2-normalised hashed character-trigram counts (deterministic across runs)."""
    v = np.zeros(TEXT_DIM, np.float32)
    padded = f"  {text.lower()}  "
    for i in range(len(padded) - 2):
        v[zlib.crc32(padded[i:i + 3].encode()) % TEXT_DIM] += 1.0
    return v / max(np.linalg.norm(v), 1e-8)


class TextSelector(ImmediateSelector):
    name = "text"

    def __init__(self, memory: DemoMemory):
        self.memory = memory
        self._vectors = np.stack([text_vector(str(s)) for s in memory.instruction])

    def select(self, queries: Sequence[Query], k: int) -> list[np.ndarray]:
        return [top_k(self._vectors @ text_vector(q.instruction), k) for q in queries]


DEFAULT_FEATURES = "lang+vis.out"  # the paper's best combination


def resolve_selection(mode: str, memory: DemoMemory) -> str:
    """'auto' -> the paper's lang+vis.out when the memory carries dynamics
    features, else the model-free 'text' ranking (logged)."""
    if mode != "auto":
        return mode
    if memory.features:
        return DEFAULT_FEATURES
    log.warning("the demo memory has no dynamics features: selecting demos by instruction "
                "text ('text'); build a memory with --checkpoint for X-ICM's lang+vis.out")
    return "text"


def make_selector(mode: str, memory: DemoMemory, sample_steps: int | None = None,
                  **kwargs) -> Selector:
    """A selector by mode name; a clear ValueError for unknown or unusable modes.
    `sample_steps` (DDIM steps of query features) only concerns dynamics modes."""
    if mode == "random":
        return RandomSelector(memory)
    if mode == "text":
        return TextSelector(memory)
    unknown = [p for p in mode.split("+") if p not in FEATURE_PARTS]
    if unknown:
        raise ValueError(f"unknown selection {mode!r}: use random, text, or "
                         f"{', '.join(FEATURE_PARTS)} joined with '+'")
    if not memory.features:
        raise ValueError(f"selection {mode!r} needs dynamics features, and this memory has "
                         "none; use --selection random or text, or rebuild the memory with "
                         "python -m agnostos_mjx.xicm.build_memory --checkpoint ...")
    from agnostos_mjx.xicm.dynamics_selector import DynamicsSelector

    if sample_steps is not None:
        kwargs["sample_steps"] = sample_steps
    return DynamicsSelector(memory, mode, **kwargs)
