"""Level-2 tasks with delicate physics: language against the spec, and each
task's own mechanics (a failure condition, a falling ball, a scoop, a rope,
water drops).  The expert's success is covered by the generic tests."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.tasks import get_task, is_implemented
from tests.conftest import episodes_for

# (task, variations, variation, index, verbatim string from the spec)
DESCRIPTIONS = [
    ("beat_the_buzz", 1, 0, 0, "beat the buzz"),
    ("beat_the_buzz", 1, 0, 6, "move the ring from end of the pole to the other whilst "
                               "maintaining separation between them"),
    ("basketball_in_hoop", 1, 0, 0, "put the ball in the hoop"),
    ("basketball_in_hoop", 1, 0, 5, "place the basket ball through the hoop"),
    ("scoop_with_spatula", 1, 0, 0, "scoop up the cube and lift it with the spatula"),
    ("scoop_with_spatula", 1, 0, 5, "pick up the block using the spatula"),
    ("straighten_rope", 1, 0, 0, "straighten rope"),
    # the original's typo "is is" is kept: the strings are verbatim, not the instruction
    ("straighten_rope", 1, 0, 3, "pull each end of the rope until is is straight"),
    ("water_plants", 1, 0, 0, "water plant"),
    ("water_plants", 1, 0, 4, "pour water from the watering can into the plant pot"),
]


def _needs(name: str):
    return pytest.mark.skipif(not is_implemented(name), reason=f"{name} not implemented")


def episodes(name: str) -> Episodes:
    return episodes_for(name)


def _reset(name: str, n: int = 2, seed: int = 0):
    ep = episodes(name)
    env = ep.reset(jax.random.split(jax.random.PRNGKey(seed), n), np.zeros(n, int))
    return ep, env, ep.expert_actions(env)


def _step(ep, env, actions, k, **changes):
    """Execute expert key action k, with fields replaced by `changes`."""
    step = jax.tree.map(lambda x: np.array(x[:, k]), actions)._replace(**changes)
    return ep.step(env, step)[0]


@pytest.mark.parametrize("name, count, variation, index, text", DESCRIPTIONS)
def test_descriptions_verbatim(name, count, variation, index, text):
    if not is_implemented(name):
        pytest.skip(f"{name} not implemented")
    task = get_task(name)
    assert task.num_variations == count
    assert task.descriptions(variation)[index] == text


@_needs("beat_the_buzz")
def test_beat_the_buzz_touching_the_wire_fails():
    """Sliding the ring 3 cm low brings it onto the wire: the failure
    condition ends the episode; the expert's slide keeps clear of it."""
    ep, env, actions = _reset("beat_the_buzz")
    for k in range(3):  # via-point, behind the handle, grasp
        env = _step(ep, env, actions, k)
    assert env.attached.all() and (env.outcome == Outcome.RUNNING).all()
    for k in range(3, int(actions.valid[0].sum())):  # the slide, 3 cm low, holding on
        low = np.array(actions.pos[:, k]) - np.array([0.0, 0.0, 0.03])
        env = _step(ep, env, actions, k, pos=low, gripper=np.full(2, 0.14, np.float32))
    assert (env.outcome == Outcome.FAILURE_CONDITION).all()


@_needs("beat_the_buzz")
@pytest.mark.slow
def test_beat_the_buzz_holding_at_the_end_is_not_success():
    """Success needs the wand at the far end *and* released (NothingGrasped)."""
    ep, env, actions = _reset("beat_the_buzz", seed=1)
    last = int(actions.valid[0].sum()) - 1
    for k in range(last):
        env = _step(ep, env, actions, k)
    env = _step(ep, env, actions, last, gripper=np.full(2, 0.14, np.float32))
    assert (env.outcome == Outcome.RUNNING).all()
    env = _step(ep, env, actions, last)
    assert (env.outcome == Outcome.SUCCESS).all()


@_needs("basketball_in_hoop")
@pytest.mark.slow
def test_basketball_dropped_beside_the_hoop_misses():
    """The ball must fall through the rim: released 15 cm to the side of it,
    it lands on the table outside the volume under the rim."""
    ep, env, actions = _reset("basketball_in_hoop")
    for k in range(3):  # via-point, above the ball, grasp
        env = _step(ep, env, actions, k)
    assert env.attached.all()
    env = _step(ep, env, actions, 3)  # lift
    beside = np.array(actions.pos[:, 4]) - 0.15 * _root_axis(env, "basketball_root", 0)
    for k in (4, 5):
        env = _step(ep, env, actions, k, pos=beside + (k - 4) * np.array([0.0, 0.0, 0.1]))
    assert not env.attached.any()
    assert (env.outcome == Outcome.RUNNING).all()
    ball_z = np.asarray(env.obs.pos("ball"))[:, 2]
    assert (ball_z < 0.752 + 0.2).all(), "the released ball falls"


@pytest.mark.slow  # one per mechanism in the default suite; this task's compile in the slow group
@_needs("scoop_with_spatula")
def test_scoop_lifts_the_cube_on_the_blade_and_needs_the_grasp():
    """Pushing slides the blade under the cube (it is not shoved away); lifting
    without holding the spatula (closing beside the handle) is no success."""
    ep, env, actions = _reset("scoop_with_spatula")
    cube0 = np.asarray(env.obs.pos("scoop_cube")).copy()
    for k in range(3):  # above the handle, grasp, push
        env = _step(ep, env, actions, k)
    cube = np.asarray(env.obs.pos("scoop_cube"))
    assert np.linalg.norm(cube[:, :2] - cube0[:, :2], axis=1).max() < 0.06  # blade: 15 cm
    assert (cube[:, 2] > cube0[:, 2] + 0.0005).all(), "the cube sits on the blade"
    env = _step(ep, env, actions, 3)
    assert (env.outcome == Outcome.SUCCESS).all()

    ep, env, actions = _reset("scoop_with_spatula")
    beside = np.array(actions.pos[:, 1]) + np.array([0.0, 0.0, 0.05])
    env = _step(ep, env, actions, 1, pos=beside)  # closes in the air above the handle
    assert not env.attached.any()
    for k in (2, 3):
        env = _step(ep, env, actions, k)
    assert (env.outcome == Outcome.RUNNING).all()


@_needs("straighten_rope")
@pytest.mark.slow
def test_rope_head_alone_is_not_enough_and_the_chain_holds():
    """Dragging only the head onto its patch is no success (both ends must
    be detected); the dragged rope stays one chain of 18 links."""
    ep, env, actions = _reset("straighten_rope")
    for k in range(4, 8):  # the head's four actions only
        env = _step(ep, env, actions, k)
    assert (env.outcome == Outcome.RUNNING).all()
    task = get_task("straighten_rope")
    head = np.asarray(env.obs.pos(task.objects["rope head"]))
    target = np.asarray(env.obs.pos("rope_success_head"))
    assert np.linalg.norm(head[:, :2] - target[:, :2], axis=1).max() < 0.05
    data = mujoco_data(ep, env, 0)
    links = np.array([data.body(f"rope_{i}").xpos for i in range(18)])
    gaps = np.linalg.norm(np.diff(links, axis=0), axis=1)
    assert ((gaps > 0.019) & (gaps < 0.027)).all(), gaps  # links ~0.023 m apart


@_needs("water_plants")
@pytest.mark.slow
def test_water_stays_in_the_can_until_it_is_tilted():
    """Carrying the can upright over the pot releases no drop; the drops
    travel inside the can."""
    ep, env, actions = _reset("water_plants")
    for k in range(4):  # beside the handle, grasp, lift, upright over the pot
        env = _step(ep, env, actions, k)
    assert env.attached.all() and (env.outcome == Outcome.RUNNING).all()
    lip = np.asarray(env.obs.pos("waterer_lip"))
    for i in range(5):
        drop = np.asarray(env.obs.pos(f"water_drop{i}"))
        assert np.linalg.norm(drop - lip, axis=1).max() < 0.13, "the drop is in the can"
        assert (drop[:, 2] > np.asarray(env.obs.pos("plant_pot_soil"))[:, 2] + 0.08).all()


def mujoco_data(ep, env, world: int):
    """An MjData holding one world's state, kinematics computed."""
    from agnostos_mjx.sim.world import posed_data

    return posed_data(ep.scene.model, env.physics, world)


def _root_axis(env, frame: str, axis: int) -> np.ndarray:
    """World direction of a frame's x, y or z axis, per world."""
    from agnostos_mjx.sim.math3d import quat_rotate

    return np.asarray(quat_rotate(np.asarray(env.obs.quat(frame), np.float64), np.eye(3)[axis]))
