"""Sharing one GPU with a policy or LLM server: cap JAX's preallocation.

JAX takes 75% of a GPU's memory when its backend starts (XLA_PYTHON_CLIENT_PREALLOCATE,
XLA_PYTHON_CLIENT_MEM_FRACTION), which starves a VLA or an LLM served on the same card.
``--gpu-mem-fraction F`` (or $AGNOSTOS_GPU_MEM_FRACTION) caps our pool at F of the card;
0 turns preallocation off (memory is taken as needed).  When a remote policy or LLM server
URL points at this machine and nothing is set, F = LOCAL_SERVER_FRACTION (0.35: 28 GB of an
80 GB card, ample for MJX-Warp batches of thousands of worlds, leaving 52 GB for the
server, e.g. an openpi server started with XLA_PYTHON_CLIENT_MEM_FRACTION=0.5).
XLA_PYTHON_CLIENT_* variables set by the user are left alone.  The variables are read when
JAX starts its backend, so this must run before the first computation.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterable, Mapping
from urllib.parse import urlparse

from agnostos_mjx.infra.settings import GPU_MEM_FRACTION

log = logging.getLogger(__name__)
LOCAL_SERVER_FRACTION = 0.35
LOCAL_HOSTS = frozenset({"localhost", "127.0.0.1", "::1", "0.0.0.0", "[::1]"})
XLA_VARS = ("XLA_PYTHON_CLIENT_PREALLOCATE", "XLA_PYTHON_CLIENT_MEM_FRACTION")


def is_local(url: str | None) -> bool:
    """Whether a server URL names this machine (vllm: in-process engines count too)."""
    if not url:
        return False
    if url.startswith("vllm:"):
        return True
    host = urlparse(url).hostname or ""
    return host in LOCAL_HOSTS or host.startswith("127.")


def memory_env(fraction: float | None, urls: Iterable[str | None],
               environ: Mapping[str, str]) -> dict[str, str]:
    """The XLA variables to set (empty: keep JAX's defaults or the user's own)."""
    if fraction is None and any(v in environ for v in XLA_VARS):
        return {}
    if fraction is None:
        fraction = GPU_MEM_FRACTION.get_float(environ)
    if fraction is None and any(map(is_local, urls)):
        fraction = LOCAL_SERVER_FRACTION
    if fraction is None:
        return {}
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"GPU memory fraction must be in [0, 1], got {fraction}")
    if fraction == 0.0:
        return {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    return {"XLA_PYTHON_CLIENT_PREALLOCATE": "true",
            "XLA_PYTHON_CLIENT_MEM_FRACTION": f"{fraction:.3g}"}


def backend_started() -> bool:
    """Whether JAX has already created its backends (then the variables come too late)."""
    bridge = sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(bridge, "_backends", None))


def _late_on_gpu() -> bool:
    """JAX started already on a GPU: a limit set now has no effect (on a CPU none is due)."""
    if not backend_started():
        return False
    import jax

    return jax.default_backend() == "gpu"


def apply_memory_limit(fraction: float | None, urls: Iterable[str | None] = ()) -> dict[str, str]:
    """Set the variables of `memory_env` in os.environ; returns what was set."""
    env = memory_env(fraction, list(urls), os.environ)
    if env and _late_on_gpu():
        log.warning("JAX has started already; the GPU memory limit %s has no effect", env)
    os.environ.update(env)
    if env:
        log.info("GPU memory: %s", ", ".join(f"{k}={v}" for k, v in env.items()))
    return env
