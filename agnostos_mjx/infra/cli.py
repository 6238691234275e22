"""Plumbing shared by the command-line tools (eval, data generation, training):
help formatting, logging that coexists with a progress bar, atomic writes and
version stamps."""

from __future__ import annotations

import argparse
import atexit
import contextlib
import logging
import os
import platform
import select
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import numpy as np


class HelpFormatter(argparse.RawDescriptionHelpFormatter,
                    argparse.ArgumentDefaultsHelpFormatter):
    """Shows defaults, except the uninformative None / False, and the description (a
    module's docstring: its example commands, its lists) with its own line breaks."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


def prog(module: str) -> str:
    """The command's name in argparse's usage and error lines, as the user typed it: the
    console script (``agnostos-eval``, pyproject's [project.scripts]) that ran `module`,
    else ``python -m <module>`` (sys.argv[0] is then the module's file)."""
    from importlib import metadata

    name = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    if name and not name.endswith(".py"):
        scripts = metadata.entry_points(group="console_scripts", name=name)
        if any(script.module == module for script in scripts):
            return name
    return f"python -m {module}"


def atomic_write(path: Path, text: str | bytes) -> None:
    """Write via a temporary file and os.replace, so readers never see half a file."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(text.encode("utf-8") if isinstance(text, str) else text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def process_age_s() -> float | None:
    """Seconds since this process started (interpreter start-up included), from Linux's
    /proc at its clock-tick resolution; None where there is no /proc."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    return max(uptime - start_ticks / os.sysconf("SC_CLK_TCK"), 0.0)


def versions() -> dict[str, Any]:
    from importlib import metadata

    import jax

    import agnostos_mjx

    out: dict[str, Any] = {"agnostos_mjx": agnostos_mjx.__version__,
                           "python": platform.python_version(), "platform": platform.platform()}
    for dist in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy", "warp-lang"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    out["jax_devices"] = [str(d) for d in jax.devices()]
    return out


# ---------------------------------------------------------------------------------------
class Progress:
    """A one-line progress bar on stderr: done/total (episodes, demos, ...), what runs
    now, rate and ETA.

    `partial` is finished work inside unfinished items (a batch's key-action rounds),
    so the bar and the ETA move before the first item ends.  On a terminal it redraws
    in place; otherwise it prints its first line at once, then a line at most every
    30 s when something changed (and at the end), so logs stay readable."""

    def __init__(self, total: int, enabled: bool = True, stream: TextIO | None = None,
                 unit: str = "episodes") -> None:
        self.total, self.enabled, self.unit = total, enabled and total > 0, unit
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.start = time.monotonic()
        self.done = 0
        self.partial = 0.0
        self.detail = ""
        self._last = -1e9
        self._shown = False
        self._drawn: tuple | None = None  # (done, detail) at the last draw
        self.lock = threading.RLock()  # the heartbeat thread draws too

    @property
    def work(self) -> float:
        """Items done, counting finished parts of unfinished ones."""
        return min(self.done + self.partial, float(self.total))

    def line(self) -> str:
        elapsed = time.monotonic() - self.start
        rate = self.work / elapsed if elapsed > 0 else 0.0
        eta = (self.total - self.work) / rate if rate > 0 else float("nan")
        width = 24
        filled = int(width * self.work / max(self.total, 1))
        eta_s = "?" if np.isnan(eta) else _hms(eta)
        detail = f"  {self.detail}" if self.detail else ""
        return (f"[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} {self.unit}"
                f"{detail}  {rate:.2f}/s  elapsed {_hms(elapsed)}  ETA {eta_s}")

    def update(self, done: int, force: bool = False, *, partial: float = 0.0,
               detail: str | None = None) -> None:
        self.done, self.partial = done, max(partial, 0.0)
        if detail is not None:
            self.detail = detail
        if not self.enabled:
            return
        now = time.monotonic()
        first = not self._shown
        if not first and not force and done < self.total and now - self._last < self.interval:
            return
        if not self.tty and self._drawn == (done, self.detail):
            return  # a log file gets only lines that say something new
        self._drawn = (done, self.detail)
        self._draw()

    @property
    def interval(self) -> float:
        return 0.2 if self.tty else 30.0

    def heartbeat(self) -> None:
        """Redraw (elapsed time and ETA) when nothing was drawn for a while: one step of a
        run (a batch's demo selection on a CPU) can take minutes."""
        with self.lock:
            if self.enabled and self._shown and \
                    time.monotonic() - self._last >= max(self.interval, 1.0):
                self._draw()

    def _draw(self) -> None:
        with self.lock:
            if self.tty:
                self.stream.write("\r\033[K" + self.line())
            else:
                self.stream.write(self.line() + "\n")
            self.stream.flush()
            self._shown = True
            self._last = time.monotonic()

    def clear(self) -> None:
        """Erase the bar (before a log line) on a terminal."""
        with self.lock:
            if self.enabled and self.tty and self._shown:
                self.stream.write("\r\033[K")
                self.stream.flush()

    def redraw(self) -> None:
        with self.lock:
            if self.enabled and self.tty and self._shown:
                self._draw()

    def close(self) -> None:
        with self.lock:
            if self.enabled and self._shown and self.tty:
                self.stream.write("\n")
                self.stream.flush()
            self.enabled = False


def _hms(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


class _BarAwareHandler(logging.StreamHandler):
    """Log lines that erase and redraw the progress bar around themselves."""

    progress: Progress | None = None

    def emit(self, record: logging.LogRecord) -> None:
        bar = self.progress
        if bar is None:
            super().emit(record)
            return
        with bar.lock:
            bar.clear()
            super().emit(record)
            bar.redraw()


_HANDLER: _BarAwareHandler | None = None


def setup_logging(quiet: bool) -> None:
    """INFO for this package (WARNING with --quiet); other libraries stay at WARNING.
    Leaves logging alone where the caller (pytest, an application) configured it."""
    global _HANDLER
    root = logging.getLogger()
    if not root.handlers:
        _HANDLER = _BarAwareHandler(sys.stderr)
        _HANDLER.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s",
                                                "%H:%M:%S"))
        root.addHandler(_HANDLER)
        root.setLevel(logging.WARNING)
    logging.getLogger("agnostos_mjx").setLevel(logging.WARNING if quiet else logging.INFO)


@contextlib.contextmanager
def progress_bar(total: int, enabled: bool = True, unit: str = "episodes"):
    """A Progress bar that log lines (via setup_logging's handler) draw around, redrawn
    by a heartbeat thread while the caller is busy."""
    bar = Progress(total, enabled=enabled, unit=unit)
    if _HANDLER is not None:
        _HANDLER.progress = bar
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(1.0):
            bar.heartbeat()

    threading.Thread(target=beat, name="progress-heartbeat", daemon=True).start()
    try:
        yield bar
    finally:
        stop.set()
        bar.close()
        if _HANDLER is not None:
            _HANDLER.progress = None


# ---------------------------------------------------------------------------------------
def check_writable_dir(path: Path) -> str | None:
    """Why files cannot be written under directory `path` (None if they can), found by
    creating and removing a probe in it or its nearest existing ancestor: nothing is
    left behind, so a run can check its output folder before it creates it."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        return f"{path} exists and is not a folder"
    base = path
    while not base.exists():
        if base.parent == base:
            break
        base = base.parent
    if not base.is_dir():
        return f"cannot create {path}: {base} is not a folder"
    try:
        probe = tempfile.mkdtemp(prefix=".write-probe-", dir=base)
        os.rmdir(probe)
    except OSError as err:
        where = "" if base == path else f"cannot create {path}: "
        return f"{where}cannot write to {base} ({err.strerror or err})"
    return None


def remove_empty_dirs(path: Path) -> None:
    """Remove `path` and the folders under it if none of them holds a file (what a run
    that failed before its first result leaves behind); anything with files stays."""
    path = Path(path)
    if not path.is_dir():
        return
    for root, _, _ in sorted(os.walk(path), key=lambda w: -len(w[0])):
        with contextlib.suppress(OSError):
            os.rmdir(root)  # fails, as it should, where files remain


def hard_exit(code: int) -> None:
    """Flush stdout/stderr and end the process now, skipping interpreter teardown: after
    Ctrl-C, teardown can block for minutes joining threads that run native code (XLA)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def quick_exit(code: int) -> None:
    """End the process after its exit handlers (``atexit``: logging's flush, a policy's own
    cleanup) but without the interpreter's teardown of every module (JAX's and Warp's
    included), which a waiting launcher would pay for (docs/performance.md)."""
    atexit._run_exitfuncs()  # what a normal exit runs first
    hard_exit(code)


class InterruptGuard:
    """Bounds how long Ctrl-C takes.

    The first SIGINT raises KeyboardInterrupt in the main thread as usual, so the
    caller can say where the results are; if the main thread is stuck in native code
    (Python only delivers the exception between bytecodes), a watcher thread prints
    `message` itself and exits after `grace_s`.  A second SIGINT exits at once.  The
    watcher learns of signals through `signal.set_wakeup_fd`, which the interpreter's
    C-level handler writes to immediately, whatever the main thread is doing."""

    def __init__(self, grace_s: float = 3.0, stream: TextIO | None = None) -> None:
        self.grace_s, self.stream = grace_s, stream or sys.stderr
        self.message: str | Callable[[], str] = ""
        self._said = threading.Lock()
        self._announced = False
        self._read_fd = self._write_fd = -1
        self._old_fd = -1

    def announce(self) -> None:
        """Print `message` once (from whichever thread gets there first)."""
        with self._said:
            if self._announced or not self.message:
                return
            self._announced = True
        with contextlib.suppress(Exception):
            text = self.message() if callable(self.message) else self.message
            self.stream.write(text.rstrip("\n") + "\n")
            self.stream.flush()

    def __enter__(self) -> InterruptGuard:
        self._read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._write_fd, False)
        self._old_fd = signal.set_wakeup_fd(self._write_fd, warn_on_full_buffer=False)
        threading.Thread(target=self._watch, name="interrupt-guard", daemon=True).start()
        return self

    def __exit__(self, *exc: object) -> None:
        signal.set_wakeup_fd(self._old_fd)
        os.close(self._write_fd)  # ends the watcher (EOF)

    def _watch(self) -> None:
        deadline: float | None = None
        while True:
            timeout = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            ready, _, _ = select.select([self._read_fd], [], [], timeout)
            if not ready:  # the grace period ran out: the main thread is stuck
                self.announce()
                hard_exit(130)
            data = os.read(self._read_fd, 64)
            if not data:
                return
            for _ in range(data.count(signal.SIGINT)):
                if deadline is not None:
                    self.announce()
                    hard_exit(130)
                deadline = time.monotonic() + self.grace_s
