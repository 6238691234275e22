"""Run a jitted function over a large array in fixed-size chunks.

On an accelerator the last chunk, and a smaller job, is padded to the full size (padding
rows cost almost nothing there), so one compiled program serves any N and a whole run
compiles each network once.  On the CPU, where every padded row costs as much as a real
one, the rows left after the full chunks (or a smaller job) are padded to the next power
of two only: at most log2(size) + 1 programs, which JAX's persistent cache keeps, and
less than 2x the work of the remainder (75 rows in chunks of 8: 76 rows, not 80).

With several local devices (agnostos_mjx.sharding) each chunk, rounded up to a multiple of
the device count, is split over them; rows are independent, so results do not change."""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np

from agnostos_mjx import sharding


def padded_size(n: int, size: int, fixed: bool | None = None) -> int:
    """The batch shape a job of n rows runs at (see the module docstring); `fixed`
    defaults to "running on an accelerator"."""
    if fixed is None:
        fixed = jax.default_backend() != "cpu"
    return size if fixed else min(size, 1 << max(n - 1, 0).bit_length())


def map_chunks(fn: Callable[..., jax.Array], *arrays: np.ndarray, size: int,
               fixed: bool | None = None) -> np.ndarray:
    """`fn` over `arrays` (sharing their leading axis) in chunks of `padded_size` rows."""
    n = len(arrays[0])
    outs, start = [], 0
    while start < n:
        rows = min(size, n - start)
        chunk_size = sharding.padded_batch(padded_size(rows, size, fixed))
        chunk = sharding.pad([a[start : start + rows] for a in arrays], chunk_size)
        chunk, _ = sharding.shard(chunk)
        outs.append(np.asarray(jax.device_get(fn(*chunk)))[:rows])
        start += rows
    return np.concatenate(outs)
