"""RLBench's kinematic grasp on a free object: closing attaches a graspable
between the fingers without moving it, lifting carries it, opening drops it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.sim.conditions import never
from agnostos_mjx.sim.math3d import euler_xyz_quat
from agnostos_mjx.tasks.base import TABLE_Z, KeyActions, Placement, Split, Task, key_actions
from agnostos_mjx.tasks.builders import panel

DOWN = euler_xyz_quat(np.pi, 0.0, np.pi)
BLOCK_HALF = 0.02


class PickBlock(Task):
    """A test-only task: one free block to pick up."""

    name = "pick_block_test"
    split = Split.SEEN
    objects = {"block": "block"}
    graspables = ("block",)
    graspable_radius = (BLOCK_HALF,)

    def descriptions(self, variation):
        return ["pick up the block"]

    def build(self, scene):
        body = scene.world.add_body(name="block", pos=[0.3, 0.0, TABLE_Z + BLOCK_HALF])
        body.add_freejoint()
        panel(body, (BLOCK_HALF,) * 3, (0, 0, 0), (1.0, 0.0, 0.0)).mass = 0.05

    def sample(self, key, variation):
        xy = jnp.array([0.3, 0.0]) + jax.random.uniform(key, (2,), minval=-0.05, maxval=0.05)
        pos = jnp.concatenate([xy, jnp.array([TABLE_Z + BLOCK_HALF])])
        return Placement(bodies={"block": (pos, jnp.array([1.0, 0.0, 0.0, 0.0]))})

    def success(self, variation):
        return never()  # the tests step by hand and check the grasp themselves

    def expert(self, obs, variation) -> KeyActions:
        block = obs.pos("block")
        up = jnp.array([0.0, 0.0, 0.15])
        return key_actions([(block + up, DOWN, 1.0), (block, DOWN, 0.0), (block + up, DOWN, 0.0),
                            (block + up, DOWN, 1.0)])


@pytest.fixture(scope="module")
def episodes():
    return Episodes(PickBlock(), "native")


def test_close_attaches_lift_carries_open_releases(episodes):
    env = episodes.reset(jax.random.split(jax.random.PRNGKey(0), 2), np.zeros(2, int))
    start = np.asarray(env.obs.pos("block")).copy()
    actions = episodes.expert_actions(env)
    step = lambda env, k: episodes.step(env, jax.tree.map(lambda x: x[:, k], actions))[0]  # noqa
    env = step(env, 0)  # above the block
    env = step(env, 1)  # down, close: attach
    assert env.attached.all(), "closing around the block must attach it"
    assert np.abs(np.asarray(env.obs.pos("block")) - start).max() < 0.01, "attach must not move it"
    env = step(env, 2)  # lift
    lifted = np.asarray(env.obs.pos("block"))
    assert (lifted[:, 2] - start[:, 2] > 0.12).all(), "the attached block follows the gripper"
    env = step(env, 3)  # open: release, the block falls back to the table
    assert not env.attached.any()
    physics = env.physics
    model = episodes.scene.model
    data = mujoco.MjData(model)
    data.qpos[:] = physics.qpos[0]
    data.ctrl[:] = physics.ctrl[0]
    data.mocap_pos[:] = physics.mocap_pos[0]
    data.mocap_quat[:] = physics.mocap_quat[0]
    for _ in range(200):
        mujoco.mj_step(model, data)
    assert data.body("block").xpos[2] < TABLE_Z + 0.05
    assert (env.outcome == Outcome.RUNNING).all()


def test_closing_on_empty_air_attaches_nothing(episodes):
    env = episodes.reset(jax.random.split(jax.random.PRNGKey(1), 1), np.zeros(1, int))
    far = KeyActions(np.array([[0.3, 0.3, 1.2]], np.float32), np.asarray(DOWN, np.float32)[None],
                     np.zeros(1, np.float32), np.ones(1, bool))
    env, _ = episodes.step(env, far)
    assert not env.attached.any()
