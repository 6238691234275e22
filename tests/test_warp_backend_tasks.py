"""Every task steps on the warp physics backend (MuJoCo Warp), where warp-lang is installed:
its reset and the expert's first key action (Warp's CPU backend on a machine without a
GPU; CI has no warp-lang and skips).  The scenes over 60 dofs (straighten_rope,
put_groceries_in_cupboard) are the ones MuJoCo Warp once refused."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from agnostos_mjx.tasks import SEEN, UNSEEN_LEVEL1, UNSEEN_LEVEL2


@pytest.mark.slow  # a scene's Warp step is built per task (cached by Warp after the first run)
@pytest.mark.parametrize("name", sorted(SEEN + UNSEEN_LEVEL1 + UNSEEN_LEVEL2))
def test_every_task_steps_on_the_warp_backend(name: str) -> None:
    pytest.importorskip("warp")
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    runner = Episodes(get_task(name), "warp")
    try:
        state = runner.reset(jax.random.split(jax.random.PRNGKey(0), 2), np.zeros(2, np.int32))
        first = jax.tree.map(lambda x: x[:, 0], runner.expert_actions(state))
        after, _ = runner.step(state, first)
    finally:
        runner.close()
    assert (np.asarray(after.sim_steps) > 0).all(), name
    assert np.isfinite(np.asarray(after.physics.qpos)).all(), name
    moved = np.abs(np.asarray(after.physics.qpos) - np.asarray(state.physics.qpos)).max()
    assert moved > 1e-3, name  # the arm went somewhere
