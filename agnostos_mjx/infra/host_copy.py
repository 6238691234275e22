"""Device arrays to numpy through pinned host memory: `to_numpy`.

``jax.device_get`` copies a GPU array into pageable host memory, which the driver stages
through a pinned buffer of its own; moving the arrays into JAX's ``pinned_host`` memory
first and reading them there goes straight over the bus, several times faster for the
megabytes of images a numpy policy gets every control step (docs/performance.md).  Arrays
that are not on a GPU, or a backend without pinned host memory, take ``device_get``.
"""

from __future__ import annotations

import functools
import logging
from typing import Any

import jax
import numpy as np

PINNED = "pinned_host"
log = logging.getLogger(__name__)
_pinned_failed = False  # set by the first refusal: the process copies by device_get after it


@functools.cache
def _has_pinned(device: Any) -> bool:
    try:
        return any(m.kind == PINNED for m in device.addressable_memories())
    except Exception:  # noqa: BLE001 - a backend without memory kinds has no pinned memory
        return False


def _pinned_here(x: jax.Array) -> bool:
    return (x.sharding.memory_kind != PINNED
            and all(d.platform == "gpu" and _has_pinned(d) for d in x.sharding.device_set))


def to_numpy(tree: Any, pinned: bool | None = None) -> Any:
    """`tree` with every array as numpy, the same values ``jax.device_get`` gives.
    `pinned`: None takes pinned host memory for the arrays on a GPU that has it; True for
    every JAX array (a test's way to run this path on the CPU); False never."""
    global _pinned_failed
    leaves, treedef = jax.tree.flatten(tree)
    use = [isinstance(x, jax.Array) and not _pinned_failed
           and (_pinned_here(x) if pinned is None else pinned) for x in leaves]
    pinned_out: list[np.ndarray] = []
    if any(use):
        try:
            moved = jax.device_put([x for x, u in zip(leaves, use) if u],
                                   [x.sharding.with_memory_kind(PINNED)
                                    for x, u in zip(leaves, use) if u])
            pinned_out = [np.asarray(x) for x in moved]
        except Exception as e:  # noqa: BLE001 - a runtime that refuses it: the usual copy
            _pinned_failed = True
            log.warning("no copies through pinned host memory here (%s: %s); arrays come "
                        "to numpy by device_get", type(e).__name__, e)
            use = [False] * len(leaves)
    done = iter(pinned_out)
    rest = iter(jax.device_get([x for x, u in zip(leaves, use) if not u]))  # one wait for all
    return jax.tree.unflatten(treedef, [next(done) if u else next(rest) for u in use])
