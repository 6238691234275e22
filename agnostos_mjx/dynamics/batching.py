"""Run a jitted function over a large array in chunks of at most `size` rows.

The rows left after the full chunks (or a smaller job) are padded to the next power of two,
so a job never pays for more than twice its rows and a run compiles at most log2(size) + 1
programs per network, which JAX's persistent cache keeps (75 rows in chunks of 8: 76 rows,
not 80).  On an accelerator, where rounds of a few rows are bound by latency, not rows,
the smallest shape is MIN_ACCELERATOR_ROWS: 3 programs for chunks of 64 (16, 32, 64), each a
~25 s compile of the sampler on a fresh GPU host.

With several local devices (agnostos_mjx.sharding) each chunk, rounded up to a multiple of
the device count, is split over them; rows are independent, so results do not change."""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np

from agnostos_mjx import sharding

MIN_ACCELERATOR_ROWS = 16


def on_accelerator() -> bool:
    return jax.default_backend() != "cpu"


def padded_size(n: int, size: int, accelerator: bool | None = None) -> int:
    """The batch shape a job of n rows runs at (see the module docstring); `accelerator`
    defaults to where JAX runs."""
    if accelerator is None:
        accelerator = on_accelerator()
    floor = MIN_ACCELERATOR_ROWS if accelerator else 1
    return min(size, max(floor, 1 << max(n - 1, 0).bit_length()))


def bucket_sizes(size: int, accelerator: bool | None = None) -> list[int]:
    """Every batch shape `map_chunks` runs at for chunks of `size` rows, smallest first
    (what a warm-up compiles)."""
    return sorted({padded_size(n, size, accelerator) for n in range(1, size + 1)})


def map_chunks(fn: Callable[..., jax.Array], *arrays: np.ndarray, size: int,
               accelerator: bool | None = None) -> np.ndarray:
    """`fn` over `arrays` (sharing their leading axis) in chunks of `padded_size` rows."""
    n = len(arrays[0])
    outs, start = [], 0
    while start < n:
        rows = min(size, n - start)
        chunk_size = sharding.padded_batch(padded_size(rows, size, accelerator))
        chunk = sharding.pad([a[start : start + rows] for a in arrays], chunk_size)
        chunk, _ = sharding.shard(chunk)
        outs.append(np.asarray(jax.device_get(fn(*chunk)))[:rows])
        start += rows
    return np.concatenate(outs)
