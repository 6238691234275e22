"""Run the networks over rows in chunks of one fixed shape (`map_chunks`), and say where
chunks may mix the rows of several requests as they come.

Every chunk is padded to `size` rows, so each network compiles one program.  XLA's result
for a row changes with the batch shape (~1e-5 between 4 and 8 rows on the CPU).  On the CPU
it does not change with the row's place in a call or the rows beside it, so the selection's
`gather.RowBatcher` puts the rows of several tasks' replanning rounds in one call as they
come without changing any task's records.  On a GPU it can change with the place (on a
GPU, 64-row calls: the sampler's latents of 18 of 64 rows moved by up to 1e-2 when the rows were
rotated by 40 places, the scores by 7e-5; the encoder and the similarity did not move:
`python tools/row_place_probe.py`), so there the batcher gathers (agnostos_mjx/infra/gather.py).

With several local devices (agnostos_mjx.infra.sharding) each chunk, rounded up to a multiple of
the device count, is split over them; rows are independent, so results do not change."""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np

from agnostos_mjx.infra import sharding


def map_chunks(fn: Callable[..., jax.Array], *arrays: np.ndarray, size: int) -> np.ndarray:
    """`fn` over `arrays` (sharing their leading axis) in chunks of exactly `size` rows (the
    last one padded)."""
    n = len(arrays[0])
    outs, start = [], 0
    chunk_size = sharding.padded_batch(size)
    while start < n:
        rows = min(size, n - start)
        chunk = sharding.pad([a[start : start + rows] for a in arrays], chunk_size)
        chunk, _ = sharding.shard(chunk)
        outs.append(np.asarray(jax.device_get(fn(*chunk)))[:rows])
        start += rows
    return np.concatenate(outs)


def rows_share_calls() -> bool:
    """Whether calls may mix the rows of requests as they come (see the module docstring);
    elsewhere a batcher gathers them."""
    return jax.default_backend() == "cpu"
