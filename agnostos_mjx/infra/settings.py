"""The environment variables agnostos-mjx reads, and the JAX set-up of its commands.

Every ``AGNOSTOS_*`` variable the package reads is a `Setting` below, with what it means;
code reads them through these objects.  Where a command-line option exists, the option
wins over the variable.

Importing the package changes nothing in the process.  `configure_jax` is the one place
that sets XLA's flags and JAX's compile cache: every command that runs JAX calls it first
thing in its `main` (and in the worker processes it spawns), as do the tests' conftest and
the notebooks' first cell.  A script of your own that runs JAX calls it before JAX starts
to get the same compiled programs and numbers as the commands.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Setting:
    """One environment variable: its name and a one-line meaning."""

    name: str
    doc: str

    def get(self, environ: Mapping[str, str] | None = None) -> str | None:
        """The value without surrounding spaces; None when unset or empty."""
        value = (os.environ if environ is None else environ).get(self.name, "").strip()
        return value or None

    def _typed(self, cast: type, what: str, environ: Mapping[str, str] | None):
        value = self.get(environ)
        try:
            return None if value is None else cast(value)
        except ValueError:
            raise ValueError(f"{self.name} must be {what}, got {value!r}") from None

    def get_float(self, environ: Mapping[str, str] | None = None) -> float | None:
        return self._typed(float, "a number", environ)

    def get_int(self, environ: Mapping[str, str] | None = None) -> int | None:
        return self._typed(int, "an integer", environ)

    def get_switch(self, default: bool) -> bool:
        """A 0/1 switch; `default` when unset."""
        value = self.get()
        if value is None:
            return default
        if value not in ("0", "1"):
            raise ValueError(f"{self.name} must be 0 or 1, got {value!r}")
        return value == "1"


LLM_URL = Setting(
    "AGNOSTOS_LLM_URL", "X-ICM's LLM: an OpenAI-compatible server URL or vllm:MODEL (--llm-url)")
LLM_MODEL = Setting("AGNOSTOS_LLM_MODEL", "the model name on that LLM server (--llm-model)")
LLM_API_KEY = Setting("AGNOSTOS_LLM_API_KEY", "the LLM server's API key (else OPENAI_API_KEY)")
POLICY_URL = Setting(
    "AGNOSTOS_POLICY_URL", "a served policy's ws:// or http:// address (--policy-url)")
GPU_MEM_FRACTION = Setting(
    "AGNOSTOS_GPU_MEM_FRACTION",
    "the share of the GPU's memory JAX preallocates, 0 for none (--gpu-mem-fraction)")
RENDER_THREADS = Setting(
    "AGNOSTOS_RENDER_THREADS", "threads of CPU rendering (default: the usable cores, at most 8)")
CACHE = Setting(
    "AGNOSTOS_CACHE",
    "root of the warm-up's markers and the model's structure (default: ~/.cache/agnostos_mjx)")
JAX_CACHE = Setting(
    "AGNOSTOS_JAX_CACHE",
    "JAX's persistent compile cache directory, or off (default: ~/.cache/agnostos_mjx/jax)")
XLA_TUNE = Setting(
    "AGNOSTOS_XLA_TUNE",
    "0 keeps XLA's default CPU optimisation level (the commands lower it on CPU-only installs)")

SETTINGS: tuple[Setting, ...] = (LLM_URL, LLM_MODEL, LLM_API_KEY, POLICY_URL, GPU_MEM_FRACTION,
                                 RENDER_THREADS, CACHE, JAX_CACHE, XLA_TUNE)

CPU_OPTIMISATION_FLAG = "--xla_backend_optimization_level=1"


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity (taskset, a container's cpuset),
    not every core of the machine as os.cpu_count() says."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):  # no affinity on this platform
        return os.cpu_count() or 1


def _home_cache() -> Path:
    return Path.home() / ".cache" / "agnostos_mjx"


def cache_root() -> Path:
    """The root of agnostos-mjx's own caches (warm-up markers, the model's structure)."""
    value = CACHE.get()
    return Path(value) if value else _home_cache()


def _backend_started() -> bool:
    bridge = sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(bridge, "_backends", None))


def lower_cpu_optimisation() -> None:
    """Add XLA's CPU optimisation level 1 to XLA_FLAGS unless a level is set there already.

    The default level made the small unrolled kinematics kernels about 100x slower at run
    time (docs/performance.md).  The level
    changes floating-point results in the last bits, so every command applies it the same
    way.  XLA reads the flags when JAX starts its backend: this must come before."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level" in flags:
        return
    if _backend_started():
        log.warning("JAX has started already: %s comes too late", CPU_OPTIMISATION_FLAG)
    os.environ["XLA_FLAGS"] = f"{flags} {CPU_OPTIMISATION_FLAG}".strip()


def enable_compilation_cache() -> str | None:
    """Turn on JAX's persistent compilation cache in $AGNOSTOS_JAX_CACHE (default
    ~/.cache/agnostos_mjx/jax); None when it is `off`, else the directory.  Before JAX is
    imported it sets JAX's own environment variables, which JAX reads at import (so the
    launcher of --local-processes never imports JAX); after, JAX's config."""
    path = JAX_CACHE.get() or str(_home_cache() / "jax")
    if path == "off":
        os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)  # e.g. a parent's, inherited
        return None
    os.makedirs(path, exist_ok=True)
    options = {"jax_compilation_cache_dir": path,
               "jax_persistent_cache_min_compile_time_secs": 0,
               "jax_persistent_cache_min_entry_size_bytes": 0}
    if "jax" not in sys.modules:
        os.environ.update({name.upper(): str(value) for name, value in options.items()})
        return path
    import jax

    for name, value in options.items():
        jax.config.update(name, value)
    return path


def gpu_plugin_installed() -> bool:
    """Whether a JAX GPU plugin is installed, found without starting JAX."""
    return importlib.util.find_spec("jax_plugins") is not None


def configure_jax(cpu: bool = False) -> None:
    """Set XLA's flags and JAX's compile cache for this process, before JAX starts.

    XLA's CPU optimisation level is lowered (`lower_cpu_optimisation`) unless
    AGNOSTOS_XLA_TUNE=0, on installs without a GPU plugin, or with `cpu` for a process
    that keeps JAX on the CPU whatever is installed.  Calling it again changes nothing."""
    if XLA_TUNE.get_switch(default=True) and (cpu or not gpu_plugin_installed()):
        lower_cpu_optimisation()
    enable_compilation_cache()


__all__ = ["CACHE", "GPU_MEM_FRACTION", "JAX_CACHE", "LLM_API_KEY", "LLM_MODEL", "LLM_URL",
           "POLICY_URL", "RENDER_THREADS", "SETTINGS", "XLA_TUNE", "Setting", "cache_root",
           "configure_jax", "enable_compilation_cache", "gpu_plugin_installed",
           "lower_cpu_optimisation"]
