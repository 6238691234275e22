"""Python's cyclic garbage collector paused for a block, counted across threads.

Two reasons to pause it:

* **CUDA graph capture.** Warp runs MJX steps and renders as Python code inside an XLA FFI
  callback and captures them into a CUDA graph.  A collection there may free an old XLA
  executable (e.g. the previous task's runner); XLA then unloads its CUDA module, which is
  illegal while a stream captures, and the capture fails ("Warp CUDA error 901 ... during
  capture").  The caller waits for the result inside the block, so the callback has
  finished before collection resumes.
* **Importing MJX-Warp.** mujoco_warp builds thousands of Warp kernel objects at import;
  with JAX loaded, every collection also runs JAX's collection callback, which made the
  import up to twice as slow.

The collector is one switch for the whole process, so a pause is counted: it resumes when
the last block (of any thread) ends, and only if it was on when the first one began.
"""

from __future__ import annotations

import contextlib
import gc
import threading
from collections.abc import Iterator

_lock = threading.Lock()
_holders = 0
_resume = False  # whether the collector was on when the first holder paused it


@contextlib.contextmanager
def gc_paused() -> Iterator[None]:
    """No cyclic collection inside the block (module docstring)."""
    global _holders, _resume
    with _lock:
        if _holders == 0:
            _resume = gc.isenabled()
            gc.disable()
        _holders += 1
    try:
        yield
    finally:
        with _lock:
            _holders -= 1
            if _holders == 0 and _resume:
                gc.enable()
