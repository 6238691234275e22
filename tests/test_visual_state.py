"""State-dependent colours (visual_state.py): lamp_on's bulb lights up in geom_rgba, in
rendered frames and in the demo bank's last frames; RLBench's never-firing colour checks
(push_buttons, light_bulb_in, lamp_off) stay unchanged; the mechanism works for buttons."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from agnostos_mjx.evaluation.protocol import episode_keys
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.state import EnvState
from agnostos_mjx.sim.conditions import JointMoved
from agnostos_mjx.sim.visual_state import StateColor, paint
from agnostos_mjx.tasks import get_task
from agnostos_mjx.tasks.push_buttons import PushButtons

SIZE = 96
BLACK, WHITE, RED, GREEN = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)


def _reset(episodes: Episodes, n: int = 2) -> EnvState:
    keys = episode_keys(np.zeros(n, np.int64), np.arange(n))
    return episodes.reset(keys, np.zeros(n, np.int32), stop_at_success=False)


def _pixel(episodes: Episodes, env: EnvState, world: int, geom: str, camera: str = "front"):
    """(row, col) where `geom`'s centre projects in `camera` (pinhole, SIZE x SIZE)."""
    m = episodes.scene.model
    d = mujoco.MjData(m)
    d.qpos[:], d.mocap_pos[:], d.mocap_quat[:] = (env.physics.qpos[world], env.physics.mocap_pos[world],
                                                  env.physics.mocap_quat[world])
    mujoco.mj_kinematics(m, d)
    mujoco.mj_camlight(m, d)
    cam = m.camera(camera).id
    local = d.cam_xmat[cam].reshape(3, 3).T @ (d.geom_xpos[m.geom(geom).id] - d.cam_xpos[cam])
    f = 0.5 * SIZE / np.tan(np.deg2rad(m.cam_fovy[cam]) / 2)
    col = SIZE / 2 + f * local[0] / -local[2]
    row = SIZE / 2 - f * local[1] / -local[2]
    return int(row), int(col)


def test_paint_changes_only_flagged_worlds_and_geoms() -> None:
    rgba = np.zeros((3, 5, 4), np.float32)
    rgba[..., 3] = 0.5
    flags = np.array([[True, False], [False, False], [True, True]])
    out = paint(rgba, flags, [np.array([1, 2]), np.array([4])], [np.ones(3), np.full(3, 0.25)])
    assert np.all(out[0, [1, 2], :3] == 1) and np.all(out[2, [1, 2], :3] == 1)
    assert np.all(out[2, 4, :3] == 0.25) and np.all(out[0, 4] == rgba[0, 4])
    assert np.all(out[1] == rgba[1]) and np.all(out[..., 3] == 0.5)
    assert np.all(rgba[..., :3] == 0)  # pure: the input is not modified


@pytest.fixture(scope="module")
def lamp_on():
    episodes = Episodes(get_task("lamp_on"), "native")
    env = _reset(episodes)
    bulb = episodes.scene.model.geom("bulb").id
    before_rgba = env.geom_rgba.copy()
    before = episodes.render(env, "front", SIZE, SIZE)
    env = episodes.run_expert(env)
    return episodes, env, bulb, before_rgba, before


def test_lamp_on_bulb_lights_in_geom_rgba(lamp_on) -> None:
    episodes, env, bulb, before_rgba, _ = lamp_on
    assert np.all(before_rgba[:, bulb, :3] == BLACK)
    assert np.all(env.outcome == 1)
    assert np.all(env.geom_rgba[:, bulb, :3] == WHITE)
    others = np.arange(env.geom_rgba.shape[1]) != bulb
    assert np.array_equal(env.geom_rgba[:, others], before_rgba[:, others])


def test_lamp_on_bulb_lights_in_rendered_frames(lamp_on) -> None:
    episodes, env, bulb, before_rgba, before = lamp_on
    after = episodes.render(env, "front", SIZE, SIZE)
    # Same final state with the bulb's colour from reset: the difference is the bulb only.
    unlit = episodes.observer._renderers[("frames", SIZE, SIZE)].render(env.physics.qpos, env.physics.mocap_pos,
                                      env.physics.mocap_quat, "front", before_rgba)
    for w in range(len(after)):
        r, c = _pixel(episodes, env, w, "bulb")
        assert before[w, r, c].max() < 60, before[w, r, c]  # black glass, lit by the scene
        assert after[w, r, c].min() > 150, after[w, r, c]
        changed = np.argwhere(np.abs(after[w].astype(int) - unlit[w].astype(int)).max(-1) > 30)
        assert len(changed) > 0
        assert np.abs(changed - [r, c]).max() < SIZE // 8  # all around the bulb


@pytest.mark.parametrize("task", ["lamp_off", "push_buttons", "light_bulb_in"])
def test_rlbench_colour_checks_that_never_fire_stay_unrendered(task) -> None:
    """RLBench compares condition_met() with (True, True), which conditions never return."""
    assert get_task(task).state_colors(np.int32(0)) == ()


class _GreenWhenPressed(PushButtons):
    """push_buttons with the colour change its RLBench code intends."""

    def state_colors(self, variation):
        return tuple(StateColor((f"target_button{k}_top", f"target_button{k}_wrap"), GREEN,
                                JointMoved((j,), 0.001)) for k, j in enumerate(self.joints))


def test_a_declared_button_colour_follows_its_press() -> None:
    episodes = Episodes(_GreenWhenPressed(), "native")
    env = _reset(episodes, 1)  # variation 0 presses button 0 only
    model = episodes.scene.model
    plate = [model.geom(f"target_button{k}_top").id for k in range(3)]
    assert np.all(env.geom_rgba[0, plate, :3] == RED)
    env = episodes.run_expert(env)
    assert env.outcome[0] == 1
    assert np.all(env.geom_rgba[0, plate[0], :3] == GREEN)
    assert np.all(env.geom_rgba[0, plate[1:], :3] == RED)


def test_demo_bank_records_the_lit_bulb(tmp_path, lamp_on) -> None:
    from agnostos_mjx.data.generate import Chunk, GenerateConfig, run_chunk

    episodes = lamp_on[0]
    cfg = GenerateConfig(out=tmp_path, tasks=("lamp_on",), demos=1, seed=0, backend="native",
                         batch=1, image_size=SIZE, quiet=True)
    demos = run_chunk(cfg, Chunk("lamp_on", 0, 1), episodes).demos
    first, last = demos["rgb_front_first"][0], demos["rgb_front_last"][0]
    # The bulb is static in its root's frame, so the reset pose locates it in both frames.
    index, attempt = demos["index"][0], demos["attempt"][0]
    from agnostos_mjx.data.generate import demo_keys

    env = episodes.reset(demo_keys(0, "lamp_on", np.array([index]), np.array([attempt])),
                         np.zeros(1, np.int32), stop_at_success=False)
    r, c = _pixel(episodes, env, 0, "bulb")
    assert first[r, c].max() < 60 and last[r, c].min() > 150
