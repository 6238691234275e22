"""Plumbing shared by the command-line tools (eval, data generation, training):
help formatting, logging that coexists with a progress bar, atomic writes and
version stamps."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows defaults, except the uninformative None / False."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


def atomic_write(path: Path, text: str | bytes) -> None:
    """Write via a temporary file and os.replace, so readers never see half a file."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(text.encode("utf-8") if isinstance(text, str) else text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


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
    """A one-line progress bar on stderr: done/total (episodes, demos, ...), rate and ETA.

    On a terminal it redraws in place; otherwise it prints a line at most every
    30 s (and at the end), so logs stay readable."""

    def __init__(self, total: int, enabled: bool = True, stream: TextIO | None = None,
                 unit: str = "episodes") -> None:
        self.total, self.enabled, self.unit = total, enabled and total > 0, unit
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.start = time.monotonic()
        self.done = 0
        self._last = -1e9
        self._shown = False
        self._drawn = -1  # `done` at the last draw

    def line(self) -> str:
        elapsed = time.monotonic() - self.start
        rate = self.done / elapsed if elapsed > 0 else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        width = 24
        filled = int(width * self.done / max(self.total, 1))
        eta_s = "?" if np.isnan(eta) else _hms(eta)
        return (f"[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} {self.unit}"
                f"  {rate:.2f}/s  elapsed {_hms(elapsed)}  ETA {eta_s}")

    def update(self, done: int, force: bool = False) -> None:
        self.done = done
        if not self.enabled:
            return
        now = time.monotonic()
        interval = 0.2 if self.tty else 30.0
        if not force and done < self.total and now - self._last < interval:
            return
        if not self.tty and (done == self._drawn or done == 0):
            return  # a log file gets only lines that say something new
        self._last, self._drawn = now, done
        self._draw()

    def _draw(self) -> None:
        if self.tty:
            self.stream.write("\r\033[K" + self.line())
        else:
            self.stream.write(self.line() + "\n")
        self.stream.flush()
        self._shown = True

    def clear(self) -> None:
        """Erase the bar (before a log line) on a terminal."""
        if self.enabled and self.tty and self._shown:
            self.stream.write("\r\033[K")
            self.stream.flush()

    def redraw(self) -> None:
        if self.enabled and self.tty and self._shown:
            self._draw()

    def close(self) -> None:
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
        if bar is not None:
            bar.clear()
        super().emit(record)
        if bar is not None:
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
    """A Progress bar that log lines (via setup_logging's handler) draw around."""
    bar = Progress(total, enabled=enabled, unit=unit)
    if _HANDLER is not None:
        _HANDLER.progress = bar
    try:
        yield bar
    finally:
        bar.close()
        if _HANDLER is not None:
            _HANDLER.progress = None
