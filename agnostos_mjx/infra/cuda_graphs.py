"""Programs whose loops run as CUDA graphs on a GPU.

XLA runs a `while` loop on a GPU from the host: each iteration launches the body's kernels
and copies the loop's predicate back, and the waiting thread spins meanwhile. Compiled with
GPU_GRAPH_OPTIONS, the loop (conditional nodes included) is one CUDA graph: no host round
trip per iteration and no spinning thread (the IK planner's CPU time per plan fell by far;
docs/performance.md). The kernels are the same, so the numbers are too. The selection's
program (its DDIM steps a `scan`) ran no faster with them, so it stays a plain jit.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax

GPU_GRAPH_OPTIONS = {
    "xla_gpu_enable_command_buffer": "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL"}


def graph_jit(fn: Callable, **jit_kwargs: Any) -> Callable:
    """`jax.jit(fn, **jit_kwargs)`, compiled with GPU_GRAPH_OPTIONS where JAX's default
    backend is a GPU. The backend is read at each call (wrapping starts no backend); the
    wrapper's `programs` holds the jitted function per backend, its `lower` lowers for
    the current one (ahead-of-time compiles: agnostos_mjx.warmup)."""
    programs: dict[str, Callable] = {}

    def program() -> Callable:
        backend = jax.default_backend()
        if backend not in programs:
            options = GPU_GRAPH_OPTIONS if backend == "gpu" else None
            programs[backend] = jax.jit(fn, compiler_options=options, **jit_kwargs)
        return programs[backend]

    @functools.wraps(fn)
    def call(*args: Any, **kwargs: Any) -> Any:
        return program()(*args, **kwargs)

    call.programs = programs  # type: ignore[attr-defined]
    call.lower = lambda *args, **kwargs: program().lower(*args, **kwargs)  # type: ignore[attr-defined]
    return call
