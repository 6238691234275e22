"""Physics backends behind one boundary; `make_backend` picks one by name."""

from __future__ import annotations

import logging

import mujoco

from agnostos_mjx.physics.base import Backend, PhysicsState

BACKENDS = ("auto", "native", "jax", "warp")
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


def resolve_backend(name: str) -> str:
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")
    if name == "auto":
        return "warp" if warp_available() else "native"
    return name


def make_backend(name: str, model: mujoco.MjModel, threads: int | None = None) -> Backend:
    """`threads`: CPU threads of the native backend (default: all cores); ignored by MJX."""
    name = resolve_backend(name)
    if name == "native":
        from agnostos_mjx.physics.native import NativeBackend

        return NativeBackend(model, threads)
    from agnostos_mjx.physics.mjx_backend import MjxBackend

    return MjxBackend(model, impl=name)


__all__ = ["Backend", "PhysicsState", "BACKENDS", "make_backend", "resolve_backend"]
