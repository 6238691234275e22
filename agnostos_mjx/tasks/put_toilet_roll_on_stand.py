"""put_toilet_roll_on_stand (unseen, Level 1): take the roll off its box and
slide it onto the stand's spindle."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from agnostos_mjx.sim.math3d import euler_xyz_quat
from agnostos_mjx.tasks.base import Placement, Split, Task, in_frame, key_actions, place_root
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_body,
    grasp_site,
    pose_in_root,
    sensor_volume,
    spawn_on_root_plane,
    yaw_of,
)
from agnostos_mjx.tasks.builders.household import open_container, placed, solid
from agnostos_mjx.tasks.builders.primitives import WHITE, disc, panel

LIGHT_GREY = (0.87, 0.87, 0.87)
BOX_HALF = 0.05
# The roll: an octagonal tube (hole radius 0.02 m, outer 0.032 m, 0.07 m
# long) lying on the box with its axis along the box's x, 0.025 m off centre.
ROLL_INNER, ROLL_WALL, ROLL_HALF_LENGTH = 0.02, 0.012, 0.035
ROLL_ON_BOX = (-0.025, 0.0, BOX_HALF + ROLL_INNER + ROLL_WALL + 0.002)
AXIS_ALONG_X = euler_xyz_quat(0.0, jnp.pi / 2, 0.0)
# The stand, in its own frame: a post at -x carrying a spindle along +x at
# SPINDLE_Z; the roll ends up centred on the origin, hanging on the spindle.
POST_X, POST_HALF, POST_TOP = -0.062, 0.012, 0.245
SPINDLE_Z, SPINDLE_HALF = 0.222, (0.05, 0.007, 0.007)
SUCCESS_CENTER, SUCCESS_HALF = (0.0, 0.0, 0.2145), (0.0125, 0.0125, 0.0125)
STAND_HALF, STAND_OFFSET = (0.081, 0.05), (-0.031, 0.0)  # footprint in the stand frame
# RLBench's spawn planes (root frame) for the box and the stand.
ROLL_PLANE, STAND_PLANE, PLANE_HALF = (0.0, 0.125), (0.0, -0.125), (0.2, 0.1)
GRIP_ABOVE = 0.005  # tip above the roll's axis when grasping
LINE_UP_X = SPINDLE_HALF[0] + ROLL_HALF_LENGTH + 0.02  # roll centre in front of the spindle tip
CARRY_Z = 0.35


class PutToiletRollOnStand(Task):
    name = "put_toilet_roll_on_stand"
    split = Split.LEVEL1
    objects = {"toilet roll": "toilet_roll", "holder": "holder", "stand_base": "stand_base"}
    frames = ("roll_root", "toilet_roll_box", "stand", "success")
    graspables = ("toilet_roll",)
    graspable_radius = (0.02,)
    notes = (
        "Stand redesigned around RLBench's success volume: the post stands behind the spindle "
        "(at the spindle's -x end) instead of beside it, so that the fingers, which grip the "
        "roll's outside, clear it. RLBench grasps the roll through its core and slides it on "
        "with collisions ignored; here the expert grasps it from above across its outside, "
        "lines its hole up with the spindle tip and slides it on along the spindle (-x), then "
        "lets go so that it hangs on the spindle. Roll and box are primitive stand-ins (an "
        "octagonal tube, a cube)."
    )

    def descriptions(self, variation: int) -> list[str]:
        return ["put toilet roll on stand", "place the toilet roll on the stand",
                "slide the roll onto its holder"]

    def build(self, scene) -> None:
        scene.mocap("roll_root")  # the task root: the spawn planes are relative to it
        stand = scene.mocap("stand")
        panel(stand, (0.035, 0.035, 0.004), (POST_X, 0, 0.004), LIGHT_GREY)
        disc(stand, 0.05, 0.004, (POST_X, 0, 0.004), LIGHT_GREY)
        grasp_site(stand, "stand_base", [POST_X, 0, POST_TOP / 2])
        panel(stand, (POST_HALF, POST_HALF, POST_TOP / 2), (POST_X, 0, POST_TOP / 2), LIGHT_GREY)
        panel(stand, SPINDLE_HALF, (0, 0, SPINDLE_Z), LIGHT_GREY, name="holder_spindle")
        grasp_site(stand, "holder", [0, 0, SPINDLE_Z])
        sensor_volume(stand, "success", SUCCESS_CENTER, SUCCESS_HALF)
        box = free_body(scene, "toilet_roll_box")
        solid(box, (BOX_HALF,) * 3, (0, 0, 0), (0.85, 0.85, 0.85), 1.0)
        roll = free_body(scene, "toilet_roll")
        for geom in open_container(roll, "toilet_roll", (0, 0, -ROLL_HALF_LENGTH), ROLL_INNER,
                                   2 * ROLL_HALF_LENGTH, WHITE, sides=8, wall=ROLL_WALL, floor=0):
            geom.mass = 0.1 / 8

    def sample(self, key, variation) -> Placement:
        k_root, k_box, k_stand = jax.random.split(key, 3)
        root = place_root(k_root, (0.2, 0.225), jnp.pi)
        box_pos, box_quat = spawn_on_root_plane(k_box, root, (BOX_HALF, BOX_HALF), ROLL_PLANE,
                                                PLANE_HALF)
        box = (box_pos + jnp.array([0.0, 0.0, BOX_HALF]), box_quat)
        return Placement(bodies={
            "roll_root": root,
            "toilet_roll_box": box,
            "toilet_roll": pose_in_root(*box, ROLL_ON_BOX, AXIS_ALONG_X),
            "stand": spawn_on_root_plane(k_stand, root, STAND_HALF, STAND_PLANE, PLANE_HALF,
                                         offset=STAND_OFFSET),
        })

    def success(self, variation):
        return placed("toilet_roll", "success", SUCCESS_HALF, radius=0.005)

    def expert(self, obs, variation):
        grip = down_grasp(yaw_of(obs.quat("toilet_roll_box")))  # fingers across the roll
        place = down_grasp(yaw_of(obs.quat("stand")))
        roll = obs.pos("toilet_roll") + jnp.array([0.0, 0.0, GRIP_ABOVE])
        line_up = in_frame(obs, "stand", (LINE_UP_X, 0.0, SPINDLE_Z + GRIP_ABOVE))
        on = in_frame(obs, "stand", (0.0, 0.0, SPINDLE_Z + GRIP_ABOVE))
        high = obs.pos("roll_root")[2] + CARRY_Z
        return key_actions([
            (roll + jnp.array([0.0, 0.0, 0.08]), grip, 1.0),
            (roll, grip, 0.0),
            (roll.at[2].set(high), grip, 0.0),
            (line_up.at[2].set(high), place, 0.0),
            (line_up, place, 0.0),
            (on, place, 1.0),  # slide onto the spindle, let go
        ])


TASK = PutToiletRollOnStand()
