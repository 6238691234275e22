"""Seeding: PRNG keys decide the initial scene, and the same key replays the
same episode on the native backend."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.sim.observables import Observation
from agnostos_mjx.tasks import get_task, list_tasks
from tests.conftest import episodes_for, task_params

TASKS = list_tasks()


def episodes(name: str) -> Episodes:
    return episodes_for(name)


def run_expert(ep: Episodes, env):
    return ep.run_expert(env)


@pytest.mark.parametrize("name", task_params(TASKS))
def test_different_keys_give_different_scenes(name):
    ep = episodes(name)
    keys = jax.random.split(jax.random.PRNGKey(7), 3)
    env = ep.reset(keys, np.zeros(3, int))
    pos, quat = env.physics.mocap_pos, env.physics.mocap_quat
    for a, b in ((0, 1), (0, 2), (1, 2)):
        moved = np.abs(pos[a] - pos[b]).max()
        turned = np.abs(quat[a] - quat[b]).max()
        assert moved > 1e-3 or turned > 1e-3, f"{name}: worlds {a} and {b} start identical"
    # The observation sees the difference too (first observed object frame).
    frame = get_task(name).observed_frames[0]
    obj = np.asarray(env.obs.pos(frame))
    assert np.abs(obj[0] - obj[1]).max() > 1e-3


@pytest.mark.parametrize("name", task_params(TASKS))
def test_same_key_same_reset(name):
    ep = episodes(name)
    keys = jax.random.split(jax.random.PRNGKey(11), 2)
    variations = np.array([0, get_task(name).num_variations - 1])
    a = ep.reset(keys, variations)
    b = ep.reset(keys, variations)
    for field in ("qpos", "qvel", "ctrl", "mocap_pos", "mocap_quat", "eq_active", "eq_data"):
        np.testing.assert_array_equal(getattr(a.physics, field), getattr(b.physics, field), field)
    np.testing.assert_array_equal(np.asarray(a.obs.data), np.asarray(b.obs.data))
    np.testing.assert_array_equal(a.geom_rgba, b.geom_rgba)


@pytest.mark.parametrize("name", ["push_buttons", "lamp_on"])
def test_same_key_same_expert_episode(name):
    ep = episodes(name)
    task = get_task(name)
    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    variations = np.array([0, task.num_variations - 1])
    first = run_expert(ep, ep.reset(keys, variations))
    second = run_expert(ep, ep.reset(keys, variations))
    assert (first.outcome == Outcome.SUCCESS).all()
    np.testing.assert_array_equal(first.outcome, second.outcome)
    np.testing.assert_array_equal(first.sim_steps, second.sim_steps)
    np.testing.assert_array_equal(first.key_actions, second.key_actions)
    np.testing.assert_array_equal(np.asarray(first.obs.data), np.asarray(second.obs.data))
    np.testing.assert_array_equal(first.physics.qpos, second.physics.qpos)


@pytest.mark.slow  # the slow group runs it in CI
@pytest.mark.parametrize("name", ["push_buttons", "close_jar"])
def test_an_episode_does_not_depend_on_its_batch(name):
    """Each world runs its own timeline (as RLBench runs one episode at a time): an episode
    gives the same result alone as in a batch whose other worlds move for longer. With one
    lockstep duration per batch, a world held still while the others moved, so its
    simulation steps (and, in contact-rich tasks, its outcome) depended on --batch."""
    ep = episodes(name)
    keys = jax.random.split(jax.random.PRNGKey(21), 3)
    variations = np.array([0, 1, 2]) % get_task(name).num_variations
    batch = run_expert(ep, ep.reset(keys, variations))
    assert (batch.outcome == Outcome.SUCCESS).all()
    assert len(set(batch.sim_steps.tolist())) > 1  # the worlds' timelines differ
    for w in range(3):
        alone = run_expert(ep, ep.reset(keys[w:w + 1], variations[w:w + 1]))
        assert alone.outcome[0] == batch.outcome[w]
        assert alone.sim_steps[0] == batch.sim_steps[w], (w, alone.sim_steps, batch.sim_steps)
        # Not bit-equal: batched numpy IK and XLA kernels round differently per batch shape
        # (measured up to 6e-5 after a close_jar episode).
        np.testing.assert_allclose(alone.physics.qpos[0], batch.physics.qpos[w], atol=1e-3)


@pytest.mark.parametrize("name", task_params(TASKS))
def test_out_of_range_variation_raises(name):
    ep = episodes(name)
    n = get_task(name).num_variations
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    with pytest.raises(ValueError, match=name):
        ep.reset(keys, [0, n])
    with pytest.raises(ValueError):
        ep.reset(keys, [-1, 0])


@pytest.mark.parametrize("name", task_params(TASKS))
def test_every_variation_resets_with_success_false(name):
    """All variations exist and reset: one world per variation index."""
    import jax.numpy as jnp

    task = get_task(name)
    ep = episodes(name)
    n = task.num_variations
    variations = np.arange(n)
    env = ep.reset(jax.random.split(jax.random.PRNGKey(3), n), variations, placement_tries=2)
    assert (env.outcome == Outcome.RUNNING).all()
    for v in range(n):
        assert task.descriptions(v), f"{name} v{v} has no description"
    def success_now(data, v):
        obs = Observation(data, env.obs.layout, jnp.zeros(len(task.graspables), bool))
        cond = task.success(v)
        return cond.step(cond.init(obs), obs)[1]

    met = np.asarray(jax.vmap(success_now)(jnp.asarray(env.obs.data), jnp.asarray(variations)))
    assert not met.any(), f"{name}: success holds at reset for variations {np.nonzero(met)[0]}"
