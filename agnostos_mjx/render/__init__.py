"""RGB rendering of named cameras for a batch of worlds (package: one module per renderer).

Two implementations behind one small interface (``width``, ``height``, ``camera_names``,
``camera_id``, ``render``, ``close`` and context-manager use):

* :class:`CpuRenderer` - native ``mujoco.Renderer`` (OpenGL, offscreen), one world at a time.
  Works on any machine with a headless GL (Mesa EGL or OSMesa); the evaluation path on CPU.
  ``render(qpos, mocap_pos, mocap_quat, camera, geom_rgba=None)`` takes numpy state arrays.
* :class:`ThreadedCpuRenderer` - N CpuRenderers, each owned by its own persistent thread
  (an OpenGL context is current in one thread only), splitting the worlds of a
  ``render_views`` call into N contiguous chunks rendered in parallel (MuJoCo and llvmpipe
  release the GIL); results are byte-identical to one CpuRenderer. :func:`cpu_renderer`
  builds it with :func:`render_threads` threads, or a plain CpuRenderer when that is 1.
* :class:`WarpRenderer` - MJX ``impl="warp"`` batch ray-tracer on a CUDA GPU, all worlds in
  one call: ``render`` takes the same state arrays (host or device), ``state_views`` every
  camera at once as device arrays.

Modules: ``common`` (CameraImages, camera names, clipping planes, the GL install hint),
``cpu`` (CpuRenderer), ``threaded`` (ThreadedCpuRenderer, cpu_renderer, render_threads),
``warp`` (WarpRenderer, FixedCamLight).  Every public name is importable from
``agnostos_mjx.render`` itself.

Headless GL selection (``MUJOCO_GL``): mujoco picks its GL backend when ``mujoco`` is first
imported, from ``MUJOCO_GL``. An existing ``MUJOCO_GL`` is always respected. Otherwise this
package's __init__ (which runs before any of its modules) sets it, before importing mujoco, to ``egl`` when libEGL is installed, else ``osmesa``
when libOSMesa is installed (a set ``PYOPENGL_PLATFORM`` must agree, because mujoco refuses to
mix the two); with neither it is set to "" and building a CpuRenderer raises a RuntimeError
naming the packages to install. If mujoco was already imported by someone else before
``MUJOCO_GL`` was set (so it bound GLFW, which needs a display), :class:`CpuRenderer` swaps
mujoco's offscreen GL context class to the MUJOCO_GL backend when it is built.
"""

from __future__ import annotations

import ctypes.util
import os

# Choose the headless GL before mujoco is imported (it reads MUJOCO_GL at import time).
# An existing MUJOCO_GL wins; else egl, then osmesa, whichever library is installed and agrees
# with PYOPENGL_PLATFORM if that is set (mujoco's egl/osmesa modules refuse a mismatch).
os.environ.setdefault(
    "MUJOCO_GL",
    next(
        (
            gl
            for gl, lib in (("egl", "EGL"), ("osmesa", "OSMesa"))
            if os.environ.get("PYOPENGL_PLATFORM", gl).strip().lower() == gl
            and ctypes.util.find_library(lib)
        ),
        "",
    ),
)

from agnostos_mjx.render.common import (
    GL_INSTALL_HINT,
    CameraImages,
    camera_names,
    clip_planes,
    gl_backend,
)
from agnostos_mjx.render.cpu import CpuRenderer
from agnostos_mjx.render.threaded import (
    MAX_RENDER_THREADS,
    RENDER_THREADS_ENV,
    ThreadedCpuRenderer,
    cpu_renderer,
    render_threads,
)
from agnostos_mjx.render.warp import FixedCamLight, WarpRenderer

__all__ = [
    "GL_INSTALL_HINT", "MAX_RENDER_THREADS", "RENDER_THREADS_ENV", "CameraImages", "CpuRenderer",
    "FixedCamLight", "ThreadedCpuRenderer", "WarpRenderer", "camera_names", "clip_planes",
    "cpu_renderer", "gl_backend", "render_threads",
]

