"""What every X-ICM demo selector shares: the query it ranks the memory for, the
selector protocol, and the top-k of a similarity row.  The selectors themselves live in
agnostos_mjx.xicm.selection (random, text) and agnostos_mjx.xicm.dynamics_selector
(dynamics-model features); both import this module and neither imports the other at
module level.
"""

from __future__ import annotations

import concurrent.futures
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Query:
    instruction: str
    seed: int  # per (episode, replan): makes random selection reproducible
    frame: np.ndarray | None = None  # (H, W, 3) uint8 front camera, for dynamics features


class Selector(Protocol):
    name: str

    def select(self, queries: Sequence[Query], k: int) -> list[np.ndarray]: ...

    def submit(self, queries: Sequence[Query], k: int) -> concurrent.futures.Future:
        """`select` as a future, so a policy can wait on it while other tasks run."""
        ...


class ImmediateSelector:
    """A selector that answers at once (random, text): `submit` is a finished future."""

    def select(self, queries: Sequence[Query], k: int) -> list[np.ndarray]:
        raise NotImplementedError

    def submit(self, queries: Sequence[Query], k: int) -> concurrent.futures.Future:
        future: concurrent.futures.Future = concurrent.futures.Future()
        future.set_result(self.select(queries, k))
        return future


def top_k(similarity: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k largest values, largest first (ties: lower index first)."""
    k = min(k, similarity.shape[-1])
    return np.argsort(-similarity, kind="stable")[:k]
