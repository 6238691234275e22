"""Worlds of a batch sharded across the local accelerators (issue 16).

Every batched computation here is per row (a world, a query), so splitting the batch
axis over devices needs no communication: the arrays are placed with
``NamedSharding(mesh, P("worlds"))`` and ``jax.jit`` partitions the program over the
mesh.  A batch is padded to a multiple of the device count (repeating its last row, a
valid input) and the padding is cut from the results, so outputs match one device.

`configure(n)` (``--devices N``) picks the first n local devices; the default is all.
One device means no placement at all: the single-device code path is unchanged.
"""

from __future__ import annotations

from typing import Any, TypeVar

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

AXIS = "worlds"
T = TypeVar("T")
_devices: int | None = None
_mesh: Mesh | None = None


def configure(devices: int | None) -> None:
    """Use the first `devices` local devices (None: all); takes effect for new work."""
    global _devices, _mesh
    if devices is not None and devices < 1:
        raise ValueError(f"devices must be positive, got {devices}")
    _devices, _mesh = devices, None


def mesh() -> Mesh:
    """The 1-D mesh over the configured local devices (local, so each process of a
    multi-process run shards its own batches)."""
    global _mesh
    if _mesh is None:
        local = jax.local_devices()
        if _devices is not None and _devices > len(local):
            raise ValueError(f"--devices {_devices}: only {len(local)} local devices "
                             f"({local[0].platform})")
        _mesh = Mesh(np.array(local[: _devices or len(local)]), (AXIS,))
    return _mesh


def device_count(m: Mesh | None = None) -> int:
    return (m or mesh()).devices.size


def padded_batch(n: int, m: Mesh | None = None) -> int:
    """n rounded up to a multiple of the device count."""
    k = device_count(m)
    return -(-n // k) * k


def pad(tree: T, size: int) -> T:
    """Pad every leaf's leading axis to `size` by repeating its last row."""
    def grow(x: Any) -> Any:
        n = x.shape[0]
        if n == size:
            return x
        lib = np if isinstance(x, np.ndarray) else jax.numpy
        return lib.concatenate([x, lib.repeat(x[-1:], size - n, axis=0)])
    return jax.tree.map(grow, tree)


def batch_sharding(m: Mesh | None = None) -> NamedSharding:
    return NamedSharding(m or mesh(), P(AXIS))


def shard(tree: T, m: Mesh | None = None) -> tuple[T, int]:
    """(the batch-leading `tree` padded to a multiple of the device count and placed
    with its batch axis split over the mesh, the original batch size).  With one
    device it is returned as is."""
    m = m or mesh()
    n = jax.tree.leaves(tree)[0].shape[0]
    if device_count(m) == 1:
        return tree, n
    return jax.device_put(pad(tree, padded_batch(n, m)), batch_sharding(m)), n


def unpad(tree: T, n: int) -> T:
    """The first n rows of every leaf (undoes `shard`'s padding)."""
    return jax.tree.map(lambda x: x if x.shape[0] == n else x[:n], tree)
