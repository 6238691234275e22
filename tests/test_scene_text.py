"""Scene text and rendering from a live reset."""

import re

import jax
import numpy as np
import pytest

from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.sim.textualise import voxel_to_point
from agnostos_mjx.tasks import get_task
from agnostos_mjx.xicm.scene_text import object_voxels, query_texts


@pytest.fixture(scope="module")
def lamp():
    ep = Episodes(get_task("lamp_on"), "native")
    env = ep.reset(jax.random.split(jax.random.PRNGKey(3), 2), np.zeros(2, int))
    return ep, env


def test_query_text_has_the_original_format(lamp):
    ep, env = lamp
    texts = query_texts(ep.task, env.obs, env.variation)
    pattern = (r"^\['instruction': turn on the light, \{'button': \[\d+, \d+, \d+\], "
               r"'button topPlate': \[\d+, \d+, \d+\], 'lamp': \[\d+, \d+, \d+\]\}\]>$")
    assert all(re.match(pattern, t) for t in texts), texts
    assert texts[0] != texts[1], "different scenes must give different text"


def test_object_voxels_decode_near_true_positions(lamp):
    ep, env = lamp
    for world, objects in enumerate(object_voxels(ep.task, env.obs)):
        for name, voxel in objects.items():
            true = np.asarray(env.obs.pos(ep.task.objects[name]))[world]
            assert np.all(np.abs(np.asarray(voxel_to_point(np.array(voxel))) - true) <= 0.0051)


def test_render_front_camera_differs_between_scenes(lamp):
    ep, env = lamp
    try:
        frames = ep.render(env, "front", 64, 64)
    except RuntimeError as err:  # no headless GL on this machine
        pytest.skip(str(err))
    assert frames.shape == (2, 64, 64, 3) and frames.dtype == np.uint8
    assert np.abs(frames[0].astype(int) - frames[1].astype(int)).mean() > 1.0


def test_xicm_integer_actions_execute(lamp):
    from agnostos_mjx.runtime.outcome import Outcome
    from agnostos_mjx.sim.textualise import xicm_actions

    ep, env = lamp
    ints = np.array([[57, 49, 87, 0, 39, 0, 1], [57, 49, 87, 0, 99, 0, 1]])  # second: bad bin
    actions = xicm_actions(ints)
    assert actions.valid.tolist() == [True, False]
    env = ep.reset(jax.random.split(jax.random.PRNGKey(5), 2), np.zeros(2, int))
    env, _ = ep.step(env, actions)
    assert env.outcome[1] == Outcome.NO_ACTION and env.outcome[0] == Outcome.RUNNING
    tip = np.asarray(env.obs["tip.pos"])[0]
    assert np.linalg.norm(tip - np.array([0.275, -0.005, 1.475])) < 0.01
