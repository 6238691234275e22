"""Run a jitted function over a large array in fixed-size chunks.

The last chunk is padded to the chunk size, so one compiled program serves any N >= size.
On an accelerator a smaller job is padded to the full size too (padding rows cost almost
nothing there), so a whole run compiles each network once; on the CPU, where every padded
row costs as much as a real one, a smaller job is padded to the next power of two (at most
log2(size) + 1 programs, at most 2x the work), and JAX's persistent cache keeps them.

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
    size = sharding.padded_batch(padded_size(n, size, fixed))
    outs = []
    for start in range(0, n, size):
        chunk = sharding.pad([a[start : start + size] for a in arrays], size)
        chunk, _ = sharding.shard(chunk)
        outs.append(np.asarray(jax.device_get(fn(*chunk)))[: min(size, n - start)])
    return np.concatenate(outs)
