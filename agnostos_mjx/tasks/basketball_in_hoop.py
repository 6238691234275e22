"""basketball_in_hoop (unseen, Level 2): pick up the ball and drop it
through the hoop; it must fall through the rim into the volume below."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.common import DOWN, grasp_site, pose_in_root, sensor_volume
from agnostos_mjx.tasks.builders.props import ball, ball_stop, basketball_hoop

ROOT, BALL = "basketball_root", "ball"
BALL_RADIUS, BALL_MASS = 0.03, 0.111
BALL_START = (-0.15, 0.035)
RIM = (0.093, 0.026, 0.25)  # rim centre; RLBench releases the ball 8.5 cm above it
# RLBench's `success` sensor: a 5 cm box on the ground under the rim.
SUCCESS_CENTER, SUCCESS_HALF = (0.095, 0.024, 0.059), (0.025, 0.025, 0.025)


class BasketballInHoop(Task):
    name = "basketball_in_hoop"
    split = Split.LEVEL2
    objects = {"hoop": "basketball_hoop", "ball": BALL}
    frames = (ROOT, "basketball_success")
    graspables = (BALL,)
    graspable_radius = (BALL_RADIUS,)
    notes = ("The hoop is built from boxes and a ring of capsules (rim radius 6 cm, 25 cm up) "
             "after RLBench's collision proxy; its long visual base is left out. X-ICM's 'hoop' "
             "position is the rim centre here (the original averages the visual mesh's points). "
             "The expert retreats upwards after the release so the ball has time to fall "
             "(RLBench waits up to 10 physics steps).")

    def descriptions(self, variation: int) -> list[str]:
        return ["put the ball in the hoop", "play basketball", "shoot the ball through the net",
                "pick up the basketball and put it in the hoop",
                "throw the basketball through the hoop", "place the basket ball through the hoop"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        basketball_hoop(root, "basketball_hoop", rim_center=RIM)
        grasp_site(root, "basketball_hoop", RIM)
        ball_stop(root, BALL_START, BALL_RADIUS)
        sensor_volume(root, "basketball_success", SUCCESS_CENTER, SUCCESS_HALF)
        ball(scene, BALL, BALL_RADIUS, BALL_MASS)

    def sample(self, key, variation) -> Placement:
        # RLBench's `basket_boundary_root` plane, 0.30 x 0.55 m, yaw +-pi/4.
        pos, quat = place_root(key, (0.15, 0.275), jnp.pi / 4)
        return Placement(bodies={ROOT: (pos, quat),
                                 BALL: pose_in_root(pos, quat, (*BALL_START, BALL_RADIUS))})

    def success(self, variation):
        return Detected(BALL, "basketball_success", SUCCESS_HALF, radius=BALL_RADIUS)

    def expert(self, obs, variation):
        quat = frame_quat(obs, ROOT, DOWN)
        grasp = obs.pos(BALL) + jnp.array([0.0, 0.0, 0.012])
        lift = grasp.at[2].set(obs.pos(ROOT)[2] + 0.397)
        over_rim = in_frame(obs, ROOT, (RIM[0], RIM[1], 0.335))
        high = grasp.at[2].set(obs.pos(ROOT)[2] + 0.55)
        return key_actions([
            (high, quat, 1.0),  # via-point above the backboard (RLBench plans around it)
            (grasp + jnp.array([0.0, 0.0, 0.077]), quat, 1.0),  # above the ball
            (grasp, quat, 0.0),  # around the ball, close: attach
            (lift, quat, 0.0),  # lift
            (over_rim, quat, 1.0),  # over the rim, release: the ball drops
            (over_rim + jnp.array([0.0, 0.0, 0.1]), quat, 1.0),  # retreat while it falls
        ])


TASK = BasketballInHoop()
