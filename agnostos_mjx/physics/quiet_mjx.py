"""``mujoco.mjx``, imported without its warp-lang complaint: our one way to import it.

Without warp-lang (every CPU install; it is the ``gpu`` extra) mujoco-mjx's import prints
``Failed to import warp: No module named 'warp'`` and the same for ``mujoco_warp`` to
stdout.  The CPU path never uses Warp, and the Warp backend checks for it itself, so those
two lines only alarm; any other output of the import (e.g. warp installed but failing to
load) still gets through.  The import runs with the garbage collector paused: where warp-lang
is installed it builds mujoco_warp's thousands of kernel objects, and collections (each also
running JAX's callback) made it up to twice as slow (infra.gc_pause).
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import sys

from agnostos_mjx.infra.gc_pause import gc_paused

_NOT_INSTALLED = ("Failed to import warp: No module named 'warp'",
                  "Failed to import mujoco_warp: No module named 'warp'")


def _import_quietly():
    if "mujoco.mjx" in sys.modules:  # imported before: it prints nothing more
        from mujoco import mjx

        return mjx
    # Only without warp-lang is there a complaint to drop; with it, stdout (the whole
    # process's, so a capture would hold other threads' lines) is left alone.
    complains = importlib.util.find_spec("warp") is None
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed) if complains else contextlib.nullcontext(), \
            gc_paused():
        from mujoco import mjx
    sys.stdout.write("".join(line for line in printed.getvalue().splitlines(keepends=True)
                             if line.rstrip("\n") not in _NOT_INSTALLED))
    return mjx


mjx = _import_quietly()

__all__ = ["mjx"]
