"""Build the Warp kernels of a run's scenes ahead of time, many at once.

Warp builds a module's kernels the first time one of them launches, one module after the
other: on a fresh machine the first scene's step waits about two minutes before it runs, each further
scene size more (docs/performance.md), and every process of a run built what it met.  The modules a
step launches do not depend on the data, so a *dry run* finds them without building any:
the K-step call's function runs once per scene with `wp.launch` recording the kernel's
module instead of launching it (and `capture_while` / `capture_if` taking each branch once).
Then `part` of `parts` processes each build their share of the modules found (the same
list in every process).  Threads barely help where processes do
(docs/performance.md).
Built modules land in Warp's kernel cache on disk, where every later process of the run, or
of a later run, finds them.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterable, Iterator
from typing import Any

import mujoco
import warp as wp

from agnostos_mjx.physics import warp_chunk

log = logging.getLogger(__name__)


@contextlib.contextmanager
def launches_recorded(modules: dict[str, Any]) -> Iterator[None]:
    """Within the block Warp launches nothing: each launch adds its kernel's module to
    `modules` (by name), and graph-conditional blocks run their bodies once (no launch
    sets the conditions).  Array copies and allocations still happen."""
    saved = wp.launch, wp.launch_tiled, wp.capture_while, wp.capture_if

    def record(kernel: Any, *args: Any, **kwargs: Any) -> None:
        modules.setdefault(kernel.module.name, kernel.module)

    def body_once(condition: Any, while_body: Any, *args: Any, **kwargs: Any) -> None:
        while_body(*args, **kwargs)

    def both_branches(condition: Any, on_true: Any = None, on_false: Any = None,
                      *args: Any, **kwargs: Any) -> None:
        for branch in (on_true, on_false):
            if branch is not None:
                branch(*args, **kwargs)

    wp.launch = wp.launch_tiled = record
    wp.capture_while, wp.capture_if = body_once, both_branches
    try:
        yield
    finally:
        wp.launch, wp.launch_tiled, wp.capture_while, wp.capture_if = saved


def _dry_arguments(fn: Any, shapes: dict[str, tuple[int, ...]]) -> list[Any]:
    """Zero arrays for `fn`'s annotated arguments, shaped as `shapes` says."""
    return [wp.zeros(shapes[name], dtype=annotation.dtype)
            for name, annotation in fn.__annotations__.items() if name != "return"]


def scene_modules(model: mujoco.MjModel, batch: int, naconmax: int, njmax: int,
                  modules: dict[str, Any] | None = None) -> dict[str, Any]:
    """The Warp modules the K-step call and the poses call launch for `model` at these
    sizes (found by a dry run on the current Warp device), added to `modules`."""
    modules = {} if modules is None else modules
    b, nq, nv = batch, model.nq, model.nv
    mocap, weld = max(model.nmocap, 1), max(model.neq, 1)
    mw, dw = warp_chunk.workspace(model, batch, naconmax, njmax)
    steps = warp_chunk.steps_function(model, mw, dw, batch)
    poses = warp_chunk.poses_function(model, mw, dw)
    step_shapes = {"qpos": (b, nq), "qvel": (b, nv), "time": (b,), "warmstart": (b, nv),
                   "ctrl": (1, b, max(model.nu, 1)), "mocap_pos": (b, mocap),
                   "mocap_quat": (b, mocap), "eq_active": (b, weld), "eq_data": (b, weld),
                   "qpos_rows": (1, b, nq), "qvel_rows": (1, b, nv), "time_rows": (1, b),
                   "sensor_rows": (1, b, max(model.nsensordata, 1)), "warmstart_out": (b, nv)}
    pose_shapes = {"qpos": (b, nq), "mocap_pos": (b, mocap), "mocap_quat": (b, mocap),
                   "xpos": (b, model.nbody), "xquat": (b, model.nbody)}
    with launches_recorded(modules):
        steps(*_dry_arguments(steps, step_shapes))
        poses(*_dry_arguments(poses, pose_shapes))
    return modules


def share(modules: dict[str, Any], part: int, parts: int) -> list[Any]:
    """Part `part` of `parts` of the modules, balanced by their kernel counts (the largest
    first, each to the lightest part); the same split in every process."""
    if not 0 <= part < parts:
        raise ValueError(f"part must be in [0, {parts}), got {part}")
    ordered = sorted(modules.values(), key=lambda m: (-len(m.kernels), m.name))
    loads, mine = [0] * parts, []
    for module in ordered:
        lightest = loads.index(min(loads))
        loads[lightest] += max(len(module.kernels), 1)
        if lightest == part:
            mine.append(module)
    return mine


def build_scenes(models: Iterable[mujoco.MjModel], batch: int, naconmax: int, njmax: int,
                 part: int = 0, parts: int = 1) -> dict[str, float | int]:
    """Build (or load from Warp's kernel cache) this part's share of the modules the runs
    of `models` at this batch will launch.  Returns what it did: modules, seconds."""
    t0 = time.perf_counter()
    modules: dict[str, Any] = {}
    for model in models:
        if warp_chunk.supported(model) is None:
            scene_modules(model, batch, naconmax, njmax, modules)
    t1 = time.perf_counter()
    mine = share(modules, part, parts)
    wp.force_load(device=wp.get_device(), modules=mine, max_workers=0)
    t2 = time.perf_counter()
    log.info("warp: %d kernel modules found in %.1f s; %d of them built or loaded in %.1f s",
             len(modules), t1 - t0, len(mine), t2 - t1)
    return {"modules": len(modules), "built": len(mine), "part": part, "parts": parts,
            "find_s": round(t1 - t0, 2), "build_s": round(t2 - t1, 2)}


__all__ = ["build_scenes", "launches_recorded", "scene_modules", "share"]
