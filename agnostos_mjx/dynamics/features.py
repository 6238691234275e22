"""Dynamics features of demos and queries, and X-ICM's demonstration selection.

Per demo or query (first frame + instruction), three 1,024-d features:
  vis.in  - the first-frame latent;
  vis.out - the last-frame latent the diffusion model predicts (guided DDIM);
  lang    - the pooled, prompt-dependent instruction feature.
Selection ranks a bank by cosine similarity over a combination of them (each
part L2-normalised, similarities averaged) and keeps the top K, most similar
first.  The original's raw dot product (xicm_reference.md, flaw 2) is an option.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from agnostos_mjx.dynamics.batching import map_chunks
from agnostos_mjx.dynamics.data import FramePairs
from agnostos_mjx.dynamics.pipeline import Pipeline, first_and_predicted_latents

PARTS = ("lang", "vis.in", "vis.out")
DEFAULT_MODE = "lang+vis.out"  # the paper's best combination
DEFAULT_K = 18
INDEX_VERSION = 1


def extract(
    pipeline: Pipeline, first: np.ndarray, instructions: list[str], parts: tuple[str, ...] = PARTS
) -> dict[str, np.ndarray]:
    """Features {part: (N, 1024) float32} of N first frames + instructions."""
    out: dict[str, np.ndarray] = {}
    z = pipeline.encode(first)
    if "vis.in" in parts:
        out["vis.in"] = z.reshape(len(z), -1)
    if "vis.out" in parts:
        out["vis.out"] = pipeline.predict(z, instructions).reshape(len(z), -1)
    if "lang" in parts:
        out["lang"] = pipeline.lang(instructions)
    return {k: v.astype(np.float32) for k, v in out.items()}


def parse_mode(mode: str) -> tuple[str, ...]:
    """'lang+vis.out' (or the original's 'lang_vis.out') -> ('lang', 'vis.out'); 'random' -> ()."""
    if mode == "random":
        return ()
    parts = tuple(p for p in mode.replace("_", "+").split("+") if p)
    bad = [p for p in parts if p not in PARTS]
    if bad or not parts:
        raise ValueError(
            f"bad selection mode {mode!r}: use 'random' or parts of {PARTS} joined by '+'"
        )
    return parts


def normalised(features: dict[str, np.ndarray], mode: str, metric: str = "cosine"
               ) -> dict[str, jax.Array]:
    """The rows `similarity` compares, on the default device: per part of `mode`, float32
    and, for cosine, L2-normalised.  A fixed bank (the seen-demo memory) is prepared once
    per run and stays on the device."""
    parts = parse_mode(mode)
    if not parts:
        raise ValueError("'random' has no similarity")
    if metric not in ("cosine", "dot"):
        raise ValueError(f"unknown metric {metric!r} (cosine or dot)")
    return {p: _normalise(np.atleast_2d(np.asarray(features[p], np.float32)), metric == "cosine")
            for p in parts}


@functools.partial(jax.jit, static_argnums=1)
def _normalise(x: jax.Array, cosine: bool) -> jax.Array:
    return x / jnp.maximum(jnp.linalg.norm(x, axis=1, keepdims=True), 1e-12) if cosine else x


def normalised_similarity(query: dict[str, jax.Array], bank: dict[str, jax.Array],
                          metric: str = "cosine") -> np.ndarray:
    """`similarity` (Q, M) float32 of rows that `normalised` prepared (the parts are the
    dicts' keys), computed on the device."""
    parts = tuple(query)
    return np.asarray(_similarity(tuple(query[p] for p in parts),
                                  tuple(bank[p] for p in parts), metric == "cosine"))


@functools.partial(jax.jit, static_argnums=2)
def _similarity(query: tuple[jax.Array, ...], bank: tuple[jax.Array, ...], cosine: bool
                ) -> jax.Array:
    total = sum(q @ b.T for q, b in zip(query, bank))
    return total / len(query) if cosine else total


def query_similarity(pipeline: Pipeline, frames: np.ndarray, instructions: list[str],
                     lang: np.ndarray | None, bank: dict[str, jax.Array],
                     metric: str = "cosine") -> np.ndarray:
    """`similarity` (N, M) of N queries (first frames + instructions; `lang`, their
    instruction features when the bank compares lang) to a bank `normalised` prepared, with
    one compiled program per chunk from the frames to the scores: the same numbers as
    `extract`, `normalised` and `normalised_similarity` one after the other."""
    parts = tuple(bank)
    if parts == ("lang",):  # no network runs on the frames
        return normalised_similarity(normalised({"lang": lang}, "lang", metric), bank, metric)
    ids, mask = pipeline.tokens(instructions)
    lang = np.zeros((len(frames), 0), np.float32) if lang is None else np.asarray(lang, np.float32)
    (ae_graph, ae_state), (graph, state) = pipeline.ae_split, pipeline.model_split
    static = (ae_graph, graph, pipeline.diffusion, pipeline.latent_scale, parts,
              metric == "cosine")
    rows = tuple(bank[p] for p in parts)
    return map_chunks(lambda f, i, m, la: _query_similarity(static, ae_state, state, rows,
                                                            f, i, m, la),
                      frames, ids, mask, lang, size=pipeline.chunk_size)


@functools.partial(jax.jit, static_argnums=0)
def _query_similarity(static: tuple, ae_state: Any, state: Any, bank: tuple[jax.Array, ...],
                      frames: jax.Array, ids: jax.Array, mask: jax.Array, lang: jax.Array
                      ) -> jax.Array:
    ae_graph, graph, cfg, latent_scale, parts, cosine = static
    z_in, z_out = first_and_predicted_latents(ae_graph, ae_state, graph, state, cfg,
                                              latent_scale, frames, ids, mask,
                                              predict="vis.out" in parts)
    features = {"lang": lang, "vis.in": z_in.reshape(len(z_in), -1)}
    if z_out is not None:
        features["vis.out"] = z_out.reshape(len(z_out), -1)
    query = tuple(_normalise(features[p], cosine) for p in parts)
    return _similarity(query, bank, cosine)


def similarity(
    query: dict[str, np.ndarray], bank: dict[str, np.ndarray], mode: str, metric: str = "cosine"
) -> np.ndarray:
    """Similarities (Q, M) of queries to bank items over the parts in `mode`.

    cosine: mean over parts of the cosine similarity (= dot product of the
    concatenated, per-part L2-normalised features, divided by the part count);
    dot: the original's unnormalised dot product of the concatenated features."""
    return normalised_similarity(normalised(query, mode, metric),
                                 normalised(bank, mode, metric), metric)


def select(
    query: dict[str, np.ndarray],
    bank: dict[str, np.ndarray],
    mode: str = DEFAULT_MODE,
    k: int = DEFAULT_K,
    metric: str = "cosine",
    seed: int = 0,
    exclude: np.ndarray | None = None,
) -> np.ndarray:
    """Indices of the top-k bank items for one query, most similar first (ties by index).
    mode 'random': k distinct items drawn with `seed`.  `exclude`: a boolean mask of
    bank items that may not be chosen (e.g. the query itself in leave-one-out)."""
    m = len(next(iter(bank.values())))
    allowed = np.ones(m, bool) if exclude is None else ~np.asarray(exclude, bool)
    candidates = np.flatnonzero(allowed)
    k = min(k, len(candidates))
    if mode == "random":
        return np.random.default_rng(seed).choice(candidates, k, replace=False)
    sims = similarity(query, bank, mode, metric)[0]
    sims = np.where(allowed, sims, -np.inf)
    return np.argsort(-sims, kind="stable")[:k]


# ---- an index of a demonstration bank ----


@dataclass(frozen=True)
class FeatureIndex:
    """Features of every demo in a bank plus its metadata, saved as one .npz.
    Row r is demo `positions[r]` of task `tasks[r]` (DemoBank.demo(task, position))."""

    features: dict[str, np.ndarray]
    tasks: np.ndarray
    instructions: np.ndarray
    fingerprint: str = ""

    def __len__(self) -> int:
        return len(self.tasks)

    @property
    def positions(self) -> np.ndarray:
        """Position of each row among the rows of its task (bank order is task, then demo)."""
        seen: dict[str, int] = {}
        out = np.empty(len(self.tasks), np.int64)
        for r, t in enumerate(self.tasks):
            out[r] = seen.get(t, 0)
            seen[t] = out[r] + 1
        return out

    def select(self, query: dict[str, np.ndarray], **kw: Any) -> np.ndarray:
        return select(query, self.features, **kw)

    def save(self, path: str | Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(
            tmp,
            version=INDEX_VERSION,
            fingerprint=self.fingerprint,
            tasks=self.tasks,
            instructions=self.instructions,
            **{f"feat/{k}": v for k, v in self.features.items()},
        )
        os.replace(tmp, path)  # atomic: a reader never sees half an index

    @classmethod
    def load(cls, path: str | Path) -> FeatureIndex:
        with np.load(path) as z:
            version = int(z["version"]) if "version" in z else None
            if version != INDEX_VERSION:
                raise ValueError(
                    f"index {path} has version {version}, this code reads {INDEX_VERSION}; rebuild it"
                )
            feats = {k.removeprefix("feat/"): z[k] for k in z.files if k.startswith("feat/")}
            return cls(feats, z["tasks"], z["instructions"], str(z["fingerprint"]))


def fingerprint(pipeline_id: str, pairs: FramePairs) -> str:
    """Identifies (model, bank): a cached index is reused only when both match."""
    h = hashlib.sha256(pipeline_id.encode())
    h.update(json.dumps([pairs.tasks, pairs.instructions]).encode())
    h.update(pairs.first.tobytes())
    return h.hexdigest()[:16]


def build_index(
    pipeline: Pipeline, pairs: FramePairs, cache: str | Path | None = None, pipeline_id: str = ""
) -> FeatureIndex:
    """Features of a bank, built once: reuses `cache` when its version and fingerprint
    (model id + bank contents) match, otherwise builds and writes it."""
    fp = fingerprint(pipeline_id, pairs)
    if cache is not None and Path(cache).exists():
        try:
            index = FeatureIndex.load(cache)
            if index.fingerprint == fp:
                return index
        except ValueError:
            pass  # old version: rebuild below
    feats = extract(pipeline, pairs.first, pairs.instructions)
    index = FeatureIndex(feats, np.array(pairs.tasks), np.array(pairs.instructions), fp)
    if cache is not None:
        index.save(cache)
    return index


@dataclass
class DemoSelector:
    """What the X-ICM policy calls: the K bank demos for a query (first frame +
    instruction) as (task, position) pairs, most similar first."""

    pipeline: Pipeline | None  # unused (may be None) in mode "random"
    index: FeatureIndex
    mode: str = DEFAULT_MODE
    k: int = DEFAULT_K
    metric: str = "cosine"
    seed: int = 0  # for mode "random"; pass the evaluation seed (the original fixed it at 42)

    def __call__(self, first_frame: np.ndarray, instruction: str) -> list[tuple[str, int]]:
        parts = parse_mode(self.mode)
        query = {} if not parts else extract(self.pipeline, first_frame[None], [instruction], parts)
        rows = self.index.select(
            query, mode=self.mode, k=self.k, metric=self.metric, seed=self.seed
        )
        positions = self.index.positions
        return [(str(self.index.tasks[r]), int(positions[r])) for r in rows]


def leave_one_out_same_task(
    index: FeatureIndex,
    mode: str = DEFAULT_MODE,
    k: int = DEFAULT_K,
    metric: str = "cosine",
    seed: int = 0,
) -> float:
    """Mean over bank items of the fraction of its top-k (itself excluded) from its own task."""
    n = len(index)
    fractions = []
    sims = None if mode == "random" else similarity(index.features, index.features, mode, metric)
    rng = np.random.default_rng(seed)
    for i in range(n):
        if sims is None:
            chosen = rng.choice(np.delete(np.arange(n), i), min(k, n - 1), replace=False)
        else:
            s = sims[i].copy()
            s[i] = -np.inf
            chosen = np.argsort(-s, kind="stable")[: min(k, n - 1)]
        fractions.append(np.mean(index.tasks[chosen] == index.tasks[i]))
    return float(np.mean(fractions))
