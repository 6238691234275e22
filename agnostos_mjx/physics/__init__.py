"""Physics backends behind one boundary; `make_backend` picks one by name."""

from __future__ import annotations

import logging

import mujoco

from agnostos_mjx.physics.base import Backend, PhysicsState

BACKENDS = ("auto", "native", "jax", "warp")
# `auto` picks MJX-warp only from this many worlds per batch, by measurement (H100 host, lamp_on,
# oracle, one run per line; eval/reports/gpu_h100_session13): with warp's key action one device
# program, warp's episodes/s against native MuJoCo on 16 threads are 0.54x at 75 worlds, 1.48x at
# 256, 1.42x at 512, 2.25x at 1,024 and 6.87x at 4,096; but warp compiles ~10 s of programs per
# task (native: none), so for a task's few batches native finishes first below ~4,096 worlds
# (1,024 x 3 seeds: ~11.5 s native vs ~5 s + 10 s warp).  Native is also bit-reproducible,
# which warp's atomics are not.  Since then warp's key action runs 1.5x-1.8x faster (graph mode
# WARP, 16 steps per loop iteration) and the main job is fastest as 8 warp processes under MPS
# (274 s vs native's 786 s single-process, eval/reports/gpu_h100_floor).  But on a 32-core host
# with both as 8 processes, native finished the main job first: 103-109 s against warp's 140 s
# with warm caches (eval/reports/gpu_h100_x2_session15), so `auto` keeps native at batch 75.
# With MuJoCo Warp stepped directly, K steps per FFI call, on one 16-core H100: warp 128 s with
# 8 processes, 118 s with 12-16, native 118 s with 8 (eval/reports/gpu_h100_session17): still no
# faster, so still native.  On a one-GPU H200 host (eval/reports/gpu_session18): warp 133 s
# warm, native 123 s: native again.
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
