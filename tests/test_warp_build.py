"""Warp's kernels built ahead of time (physics/warp_build.py) and the K-step call's FFI names.

Where warp-lang is installed (on this CPU Warp builds CPU kernels; slow the first time)."""

from __future__ import annotations

import mujoco
import pytest

from tests.test_k_steps import SCENE


@pytest.mark.slow
def test_dry_run_finds_every_module_a_real_step_loads() -> None:
    """The dry run launches nothing, yet names every module the real K-step and poses calls
    then load, so building those ahead of time leaves nothing to build during a run."""
    wp = pytest.importorskip("warp")
    import jax.numpy as jnp

    from agnostos_mjx.physics import warp_build
    from agnostos_mjx.physics.base import StepData
    from agnostos_mjx.physics.warp_chunk import WarpChunk
    from tests.test_k_steps import GOALS, _state

    model = mujoco.MjModel.from_xml_string(SCENE)
    b = len(GOALS)
    found = warp_build.scene_modules(model, b, 64 * b, 64)
    assert "mujoco.mjx.third_party.mujoco_warp._src.solver" in found
    assert "agnostos_mjx.physics.warp_chunk" in found
    shares = [warp_build.share(found, i, 3) for i in range(3)]
    assert sorted(m.name for part in shares for m in part) == sorted(found)  # a partition
    assert all(shares)
    with pytest.raises(ValueError, match="part must be"):
        warp_build.share(found, 3, 3)
    built = [warp_build.build_scenes([model], b, 64 * b, 64, part=i, parts=3) for i in range(3)]
    assert [x["built"] for x in built] == [len(part) for part in shares]
    assert all(x["modules"] == len(found) for x in built)

    loaded: set[str] = set()
    module_type = type(next(iter(found.values())))
    real_load = module_type.load

    def load(self, *args, **kwargs):
        loaded.add(self.name)
        return real_load(self, *args, **kwargs)

    module_type.load = load
    try:
        chunk = WarpChunk(model, b, 64 * b, 64)
        d = StepData.start(_state(model, b, True).physics, model.nsensordata)
        last, _ = chunk(d, jnp.zeros((3, b, model.nu), jnp.float32))
        chunk.poses(last)
    finally:
        module_type.load = real_load
    assert "mujoco.mjx.third_party.mujoco_warp._src.solver" in loaded
    assert loaded <= set(found), f"not found by the dry run: {sorted(loaded - set(found))}"
    assert wp.launch is not None and wp.launch.__name__ == "launch"  # restored


@pytest.mark.slow
def test_ffi_names_do_not_depend_on_the_order_scenes_are_made() -> None:
    """Each scene's K-step call gets an FFI name of its own (the model's digest and sizes,
    counter 0), so a key-action program is the same XLA program in every process and JAX's
    persistent cache serves it; one shared name took a per-process counter instead."""
    pytest.importorskip("warp")
    from agnostos_mjx.physics.warp_chunk import WarpChunk, model_digest

    first = mujoco.MjModel.from_xml_string(SCENE)
    second = mujoco.MjModel.from_xml_string(SCENE.replace('timestep="0.01"', 'timestep="0.02"'))
    assert model_digest(first) != model_digest(second)
    assert model_digest(first) == model_digest(mujoco.MjModel.from_xml_string(SCENE))
    for model in (second, first):
        chunk = WarpChunk(model, 3, 64 * 3, 64, graph_mode="NONE")
        assert chunk._call.name == f"agnostos_steps_{model_digest(model)}_3_192_64_NONE_0"
        assert chunk._poses.name == f"agnostos_poses_{model_digest(model)}_3_192_64_NONE_0"


@pytest.mark.slow
def test_warmup_builds_the_tasks_kernels() -> None:
    """warmup's first step on warp: every kernel module of the tasks' scenes, at the run's
    sizes (the backend's contacts and constraints per world), through the dry run."""
    pytest.importorskip("warp")
    from agnostos_mjx import warmup

    one = warmup.build_kernels(["lamp_on"], batch=2)
    both = warmup.build_kernels(["lamp_on", "put_books_on_bookshelf"], batch=2, part=1, parts=2)
    assert 0 < one["modules"] < both["modules"]  # the bookshelf's bigger scene adds modules
    assert one["built"] == one["modules"] and 0 < both["built"] < both["modules"]
    assert both["wall_s"] >= both["build_s"]


@pytest.mark.slow
def test_warmup_command_builds_kernels_in_processes(capsys) -> None:
    """The command's kernel step: --kernel-jobs processes, each its share, one result."""
    pytest.importorskip("warp")
    from agnostos_mjx import warmup

    args = warmup.parse_args(["--tasks", "lamp_on", "--backend", "warp", "--batch", "2",
                              "--kernel-jobs", "2"])  # the command's own flags, as it has them
    result = warmup.build_kernels_in_parallel(args)
    assert result.get("parts") == 2 and result["modules"] > 0, result


def test_warp_model_leaves_dense_jacobians_to_auto_only_above_warps_limit() -> None:
    """MuJoCo Warp refuses a dense Jacobian above 60 dofs: the rope's and the groceries'
    scenes get MuJoCo's auto (sparse there), every other scene stays the very same model."""
    import mujoco

    from agnostos_mjx.physics.base import WARP_DENSE_MAX_NV, for_warp
    from agnostos_mjx.sim.world import build_scene
    from agnostos_mjx.tasks import get_task

    rope = build_scene(get_task("straighten_rope")).model
    assert rope.nv > WARP_DENSE_MAX_NV and rope.opt.jacobian == mujoco.mjtJacobian.mjJAC_DENSE
    warp_rope = for_warp(rope)
    assert warp_rope.opt.jacobian == mujoco.mjtJacobian.mjJAC_AUTO
    assert rope.opt.jacobian == mujoco.mjtJacobian.mjJAC_DENSE  # the CPU's model untouched
    lamp = build_scene(get_task("lamp_on")).model
    assert lamp.nv <= WARP_DENSE_MAX_NV and for_warp(lamp) is lamp
