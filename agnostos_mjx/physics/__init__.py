"""Physics backends behind one boundary; `make_backend` picks one by name."""

from __future__ import annotations

import functools
import logging
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # light at import: the launcher of --local-processes reads BACKENDS only
    import mujoco

    from agnostos_mjx.physics.base import Backend


from agnostos_mjx.physics.capabilities import (
    CAPABILITIES,
    RENDER_ROUTES,
    Capabilities,
    RenderRoute,
)

BACKENDS = ("auto", *CAPABILITIES)
# Where observations are rendered: MuJoCo's OpenGL renderer on CPU threads, or MJX-Warp's
# batch ray tracer on the GPU (beside any physics backend: the worlds' state goes to it).
RENDERERS = ("auto", *RENDER_ROUTES)
GPU_RENDERER_HINT = ("a CUDA GPU but no warp-lang: observations render on the CPU; "
                     "pip install -e '.[gpu]' renders them on the GPU")
# `auto` picks MJX-warp only from this many worlds per batch.  Warp's episodes/s grow with
# the batch (slower than native MuJoCo's threads at 75 worlds, faster from a few hundred), but
# warp compiles programs for each task and native none, so below ~4,096 worlds native
# finishes a task's few batches first; the main job (75 worlds) is no faster on warp
# either, in processes on one GPU or several (docs/performance.md).  Native is also bit-reproducible, which warp's atomics are not.
WARP_MIN_BATCH = 4096
log = logging.getLogger(__name__)


@functools.cache
def cuda_gpu() -> bool:
    """True when JAX sees a CUDA GPU (asked once: every CPU-route observation reads it)."""
    try:
        import jax

        return any(d.platform == "gpu" for d in jax.devices())
    except Exception:  # noqa: BLE001 - any runtime failure means "no GPU"
        return False


@functools.cache
def warp_available() -> bool:
    """True when JAX sees a CUDA GPU and warp-lang (mujoco-warp's dependency) is installed.
    Looked up, not imported: the import takes seconds, and a run on the warp route makes it
    on a thread of its own (render.warp.preload); a broken install fails when the renderer
    loads."""
    import importlib.util

    return cuda_gpu() and importlib.util.find_spec("warp") is not None


def resolve_renderer(name: str, backend: str = "native") -> str:
    """`auto` means the renderer next to the physics backend where it has one, else the
    GPU's batch ray tracer ("warp") wherever it can run, else MuJoCo's OpenGL renderer
    ("cpu"); a GPU without warp-lang gets a one-line hint.  The route is chosen once per run
    and recorded in its results."""
    if name not in RENDERERS:
        raise ValueError(f"unknown renderer {name!r}; choose one of {', '.join(RENDERERS)}")
    if name != "auto":
        return name
    beside = CAPABILITIES[backend].renderer
    if beside is not None:
        return beside
    if warp_available():
        return "warp"
    if cuda_gpu():
        _hint_once()
    return "cpu"


def render_route(name: str, backend: str = "native") -> RenderRoute:
    """The route `name` resolves to (`resolve_renderer`), with what it offers."""
    return RENDER_ROUTES[resolve_renderer(name, backend)]


@functools.cache
def _hint_once() -> None:
    log.warning("%s", GPU_RENDERER_HINT)


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


__all__ = ["BACKENDS", "CAPABILITIES", "RENDERERS", "RENDER_ROUTES", "WARP_MIN_BATCH",
           "Capabilities", "RenderRoute", "cuda_gpu", "make_backend", "render_route",
           "resolve_backend", "resolve_renderer", "warp_available"]
