"""What each physics backend and each render route offers the layers above: read here,
never a name compared.  A leaf module, so that the backends, the renderers and the
package's face all import it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Capabilities:
    """What a backend offers the layers above, so that they read it here instead of
    comparing its name (adding a backend adds its entry to CAPABILITIES)."""

    # Key actions run as one device program (Episodes.step_on_device), else on the host.
    on_device: bool
    # Batches are padded to one shape: the backend compiles a program per batch shape.
    padded_batch: bool
    # Physics steps per iteration of a device phase's loop (runtime/phase.steps_per_iteration).
    steps_per_iteration: int = 1
    # Its rollouts release the GIL: tasks running at once step on a thread pool.
    threaded: bool = False
    # The renderer that sits next to it (its worlds' state already there), else None.
    renderer: str | None = None
    # Its device programs capture CUDA graphs: Python's collector stays off while they run.
    captures_graphs: bool = False
    # Its worlds split over the local devices (sharding.py).
    sharded: bool = False
    # Per-scene kernels that warmup builds ahead in parallel processes, once per machine.
    kernels: bool = False


# Warp's K-step chunks (one FFI call per K steps); see runtime/phase.steps_per_iteration.
WARP_STEPS_PER_ITERATION = 16
CAPABILITIES: dict[str, Capabilities] = {
    "native": Capabilities(on_device=False, padded_batch=False, threaded=True),
    "jax": Capabilities(on_device=True, padded_batch=True, sharded=True),
    "warp": Capabilities(on_device=True, padded_batch=True,
                         steps_per_iteration=WARP_STEPS_PER_ITERATION, renderer="warp",
                         captures_graphs=True, kernels=True),
}


@dataclass(frozen=True)
class RenderRoute:
    """Where observations are rendered, as the layers above need to know it (adding a
    renderer adds its entry to RENDER_ROUTES)."""

    name: str  # as `--renderer` takes it and results and datasets record it
    label: str  # for the run's log
    # Images come from one device program with the observation's other arrays (the
    # worlds' state goes to the GPU); else from CPU threads, as numpy arrays.
    on_device: bool
    # Loading its modules takes seconds: a run starts that on a thread (render.warp.preload).
    preload: bool = False


RENDER_ROUTES: dict[str, RenderRoute] = {
    "cpu": RenderRoute("cpu", "OpenGL on the CPU", on_device=False),
    "warp": RenderRoute("warp", "MJX-Warp on the GPU", on_device=True, preload=True),
}
