"""The jitted key-action step (key_action.py) against the host path (episode.py's
recording path) on MJX-jax at tiny batch: same outcomes, poses within tolerance, and a
world frozen past its own end (issue 13).  MJX compiles on CPU take minutes per task, so
the per-task cases are slow tests; `python -m pytest -m slow tests/test_key_action.py`."""

from __future__ import annotations

import dataclasses
import functools

import jax
import numpy as np
import pytest

from agnostos_mjx.runtime.env import Episodes, SETTLE_STEPS
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.tasks import get_task
from agnostos_mjx.tasks.base import KeyActions

POS_TOL = 0.01  # m: tip and object frames after the episode
STEP_TOL = 3  # physics steps: the success step may move by float32 round-off in the plan


def _keys(n: int):
    return jax.vmap(lambda e: jax.random.fold_in(jax.random.PRNGKey(0), e))(np.arange(n))


def _constructed_actions(ep: Episodes, env) -> list[KeyActions]:
    """The expert's key actions with two constructed cases: world 1 has nothing valid from
    its second action on (NO_ACTION, then frozen), world 2's first target is out of the
    workspace."""
    expert = ep.expert_actions(env)
    steps = []
    for k in range(expert.pos.shape[1]):
        pos, quat, grip, valid = (np.array(x[:, k]) for x in
                                  (expert.pos, expert.quat, expert.gripper, expert.valid))
        if k >= 1:
            valid[1] = False
        if k == 0:
            pos[2] = (0.2, 0.0, 2.5)
        steps.append(KeyActions(pos, quat, grip, valid))
    return steps


@pytest.mark.parametrize("task", ["lamp_on", "phone_on_base"])
def test_device_step_traces_with_the_documented_shapes(task):
    """The device program (with and without grasp welds) traces, at both stop modes, to a
    DeviceEnv of the input's shapes and dtypes: a cheap guard for the default suite (no
    compile, no physics)."""
    from agnostos_mjx.key_action import KeyActionStep, to_device

    ep = Episodes(get_task(task), "jax")
    env = ep.reset(_keys(2), np.zeros(2, np.int32))
    dev = to_device(env)
    expert = ep.expert_actions(env)
    acts = KeyActions(*(jax.numpy.asarray(np.asarray(x)[:, 0]) for x in
                        (expert.pos, expert.quat, expert.gripper, expert.valid)))
    step = KeyActionStep(ep, 2)
    plan = jax.eval_shape(ep._device_plan, dev.data[:, ep._arm_q], acts.pos, acts.quat)
    for stop in (True, False):
        out = jax.eval_shape(functools.partial(step._key_action, stop_at_success=stop),
                             dev, acts, plan)
        shapes = jax.tree.map(lambda x: (x.shape, x.dtype), out)
        assert shapes == jax.tree.map(lambda x: (x.shape, x.dtype), dev)


def _run(ep: Episodes, env, steps: list[KeyActions], record: bool):
    env = dataclasses.replace(env)
    history = []
    for action in steps:
        env, _ = ep.step(env, action, record=record)
        history.append(jax.tree.map(np.asarray, env.physics))
    return env, history


@pytest.mark.slow
@pytest.mark.parametrize("task", ["lamp_on", "phone_on_base", "open_drawer"])
def test_device_step_matches_host_path(task):
    ep = Episodes(get_task(task), "jax")
    b = 3
    env = ep.reset(_keys(b), np.zeros(b, np.int32))
    steps = _constructed_actions(ep, env)
    host, _ = _run(ep, env, steps, record=True)
    dev, history = _run(ep, env, steps, record=False)

    assert Outcome(int(host.outcome[0])) == Outcome.SUCCESS, "the expert world succeeds"
    assert Outcome(int(host.outcome[1])) == Outcome.NO_ACTION
    assert Outcome(int(host.outcome[2])) == Outcome.OUT_OF_WORKSPACE
    np.testing.assert_array_equal(dev.outcome, host.outcome)
    np.testing.assert_array_equal(dev.key_actions, host.key_actions)
    np.testing.assert_array_equal(dev.attached, host.attached)
    assert np.abs(dev.sim_steps - host.sim_steps).max() <= STEP_TOL
    layout = ep.scene.layout
    for name in ("tip", *ep.task.observed_frames):
        key = f"{name}.pos"
        if key in layout.names:
            err = np.abs(np.asarray(dev.obs[key]) - np.asarray(host.obs[key])).max()
            assert err < POS_TOL, f"{task}: {key} differs by {err:.4f} m"

    # Frozen worlds: world 1 never moves after its first key action, world 2 never moves,
    # and every world's clock stops at its own last step.
    for later in history[1:]:
        np.testing.assert_array_equal(later.qpos[1], history[0].qpos[1])
    np.testing.assert_array_equal(history[-1].qpos[2], env.physics.qpos[2].astype(np.float32))
    np.testing.assert_allclose(history[-1].time, (SETTLE_STEPS + dev.sim_steps) * ep.dt, atol=1e-4)
