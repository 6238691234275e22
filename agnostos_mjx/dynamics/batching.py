"""Run a jitted function over a large array in fixed-size chunks.

The last chunk is padded to the chunk size, so one compiled program serves any N >= size;
a smaller job is padded to the next power of two, so replanning a varying number of
worlds compiles at most log2(size) + 1 programs instead of one per count (each compile of
the 50-step DDIM sampler costs seconds to minutes)."""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np


def map_chunks(fn: Callable[..., jax.Array], *arrays: np.ndarray, size: int) -> np.ndarray:
    n = len(arrays[0])
    size = min(size, 1 << max(n - 1, 0).bit_length())
    outs = []
    for start in range(0, n, size):
        chunk = [a[start : start + size] for a in arrays]
        m = len(chunk[0])
        if m < size:
            chunk = [np.concatenate([c, np.repeat(c[-1:], size - m, axis=0)]) for c in chunk]
        outs.append(np.asarray(jax.device_get(fn(*chunk)))[:m])
    return np.concatenate(outs)
