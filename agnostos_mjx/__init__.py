"""agnostos-mjx: the AGNOSTOS cross-task benchmark and X-ICM in MuJoCo / MJX."""

from __future__ import annotations

import os

__version__ = "0.1.0"


def _tune_cpu_xla() -> None:
    """On CPU-only installs, lower XLA's LLVM optimisation level.

    Measured on jaxlib 0.10 (2-core x86): the default level made the small
    unrolled kinematics kernels 100x slower at run time (18 ms vs 0.18 ms per
    forward-kinematics call).  Skipped when a CUDA plugin is installed or the
    user set the flag; AGNOSTOS_XLA_TUNE=0 disables it."""
    import importlib.util

    if os.environ.get("AGNOSTOS_XLA_TUNE", "1") == "0":
        return
    if importlib.util.find_spec("jax_plugins") is not None:  # a GPU plugin is installed
        return
    lower_cpu_optimisation()


def lower_cpu_optimisation() -> None:
    """Add --xla_backend_optimization_level=1 to XLA_FLAGS unless the user set a level.
    Takes effect for a JAX backend started after the call (data.generate's CPU workers
    call it themselves, since a GPU plugin makes the import-time tuning skip)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_backend_optimization_level=1").strip()


_tune_cpu_xla()


def enable_compilation_cache(path: str | None = None) -> str:
    """Turn on JAX's persistent compilation cache (default on at import).

    The directory comes from `path`, else $AGNOSTOS_JAX_CACHE, else
    ~/.cache/agnostos_mjx/jax; set AGNOSTOS_JAX_CACHE=off to disable."""
    import jax

    path = path or os.environ.get("AGNOSTOS_JAX_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "agnostos_mjx", "jax")
    if path == "off":
        return ""
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


enable_compilation_cache()
