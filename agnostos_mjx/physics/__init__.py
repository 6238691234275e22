"""Physics backends behind one boundary; `make_backend` picks one by name."""

from __future__ import annotations

import logging

import mujoco

from agnostos_mjx.physics.base import Backend, PhysicsState

BACKENDS = ("auto", "native", "jax", "warp")
# `auto` picks MJX-warp only from this many worlds per batch: below it, native MuJoCo on
# the GPU host's CPU threads is faster (H200 host, lamp_on: 1.41M vs 96k env-steps/s at
# batch 75, 1.49M vs 428k at 1,024, 1.35M vs 2.10M at 8,192; eval/reports/gpu_probe_h200.json;
# the default run, 23 tasks x 75 episodes: 669 s native vs ~1,000 s warp) and is
# bit-reproducible, which warp's atomics are not.  With the device key-action step (key_action.py)
# warp's oracle episodes/s at batch 75 are 0.54x native on lamp_on and 1.11x on stack_blocks
# (H100 host, eval/reports/gpu_h100_session13): still no reason to pick warp at small batches.
WARP_MIN_BATCH = 4096
log = logging.getLogger(__name__)


def warp_available() -> bool:
    """True when JAX sees a CUDA GPU and mujoco-warp's dependency imports."""
    try:
        import jax

        if not any(d.platform == "gpu" for d in jax.devices()):
            return False
        import warp  # noqa: F401
    except Exception:  # noqa: BLE001 - any import/runtime failure means "not available"
        return False
    return True


def resolve_backend(name: str, batch: int | None = None) -> str:
    """`auto` means warp for batches of at least WARP_MIN_BATCH worlds on a CUDA GPU with
    mujoco-warp, else native; an unknown `batch` counts as small."""
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")
    if name == "auto":
        big = batch is not None and batch >= WARP_MIN_BATCH
        return "warp" if big and warp_available() else "native"
    return name


def make_backend(name: str, model: mujoco.MjModel, threads: int | None = None) -> Backend:
    """`threads`: CPU threads of the native backend (default: all cores); ignored by MJX."""
    name = resolve_backend(name)
    if name == "native":
        from agnostos_mjx.physics.native import NativeBackend

        return NativeBackend(model, threads)
    from agnostos_mjx.physics.mjx_backend import MjxBackend

    return MjxBackend(model, impl=name)


__all__ = ["Backend", "PhysicsState", "BACKENDS", "WARP_MIN_BATCH", "make_backend",
           "resolve_backend"]
