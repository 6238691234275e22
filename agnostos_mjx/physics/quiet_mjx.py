"""``mujoco.mjx``, imported without its warp-lang complaint: our one way to import it.

Without warp-lang (every CPU install; it is the ``gpu`` extra) mujoco-mjx's import prints
``Failed to import warp: No module named 'warp'`` and the same for ``mujoco_warp`` to
stdout.  The CPU path never uses Warp, and the Warp backend checks for it itself, so those
two lines only alarm; any other output of the import (e.g. warp installed but failing to
load) still gets through.  The import runs with the garbage collector paused: where warp-lang
is installed it builds mujoco_warp's thousands of kernel objects, and collections (each also
running JAX's callback) made it up to twice as slow (infra.gc_pause).

MJX-jax's mesh module (convex hulls for its mesh collisions) imports trimesh and
scipy.spatial, a third of the whole import, which MJX-Warp (the renderer, the warp backend)
never uses: it is loaded when first used instead (`_LazyMeshFinder`).
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.machinery
import importlib.util
import io
import sys
import threading
from typing import Any

from agnostos_mjx.infra.gc_pause import gc_paused

MESH_MODULE = "mujoco.mjx._src.mesh"
_NOT_INSTALLED = ("Failed to import warp: No module named 'warp'",
                  "Failed to import mujoco_warp: No module named 'warp'")


class _LazyMeshFinder(importlib.abc.MetaPathFinder):
    """Finds MJX's mesh module with a LazyLoader (the standard library's): the module
    executes on its first attribute access.  MJX's modules bind it as ``from
    mujoco.mjx._src import mesh`` and use it only inside functions (MJX-jax's put_model and
    mesh collisions)."""

    def find_spec(self, name: str, path: Any, target: Any = None) -> Any:
        if name != MESH_MODULE:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is not None and spec.loader is not None:
            spec.loader = importlib.util.LazyLoader(spec.loader)
        return spec


_mesh_lock = threading.Lock()


def load_mesh_module() -> None:
    """Execute MJX's mesh module now, once: MJX-jax's put_model calls this first.  Python
    3.11's LazyLoader is not safe when two threads use a module first at once (MJX-jax
    backends built on tasks' threads), so the first use is made here, under a lock."""
    with _mesh_lock:
        getattr(sys.modules.get(MESH_MODULE), "__file__", None)


def _import_quietly():
    if "mujoco.mjx" in sys.modules:  # imported before: it prints nothing more
        from mujoco import mjx

        return mjx
    # Only without warp-lang is there a complaint to drop; with it, stdout (the whole
    # process's, so a capture would hold other threads' lines) is left alone.
    complains = importlib.util.find_spec("warp") is None
    printed = io.StringIO()
    finder = _LazyMeshFinder()
    sys.meta_path.insert(0, finder)
    try:
        with contextlib.redirect_stdout(printed) if complains else contextlib.nullcontext(), \
                gc_paused():
            from mujoco import mjx
    finally:
        sys.meta_path.remove(finder)
    sys.stdout.write("".join(line for line in printed.getvalue().splitlines(keepends=True)
                             if line.rstrip("\n") not in _NOT_INSTALLED))
    return mjx


mjx = _import_quietly()

__all__ = ["mjx"]
