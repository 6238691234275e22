"""take_lid_off_saucepan (unseen, Level 2): lift the lid off the pan by its knob."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, Grasped, all_of
from agnostos_mjx.tasks.base import Placement, Split, Task, key_actions, place_root
from agnostos_mjx.tasks.builders.common import DOWN, pose_in_root, sensor_volume
from agnostos_mjx.tasks.builders.kitchen import LID_HALF_THICKNESS, saucepan

# RLBench's `success` volume: 0.1 x 0.1 m, 0.05 m high, from 0.216 m above the
# table over the knob's start (the knob starts at 0.101 m).
SUCCESS_HALF = (0.05, 0.05, 0.025)
KNOB_XY = (-0.026, 0.030)  # the lid's and pot's centre
POT_HEIGHT = 0.072
LID_POS = (*KNOB_XY, POT_HEIGHT + LID_HALF_THICKNESS)  # resting on the rim
# Model bounding box in the root frame: x[-0.142, 0.089], y[-0.304, 0.145].
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.116, 0.225), (-0.027, -0.080)


class TakeLidOffSaucepan(Task):
    name = "take_lid_off_saucepan"
    split = Split.LEVEL2
    objects = {"saucepan": "saucepan", "saucepan lid": "saucepan_lid"}
    frames = ("saucepan_success",)
    graspables = ("saucepan_lid",)
    grasp_points = ("saucepan_lid_grasp_point",)
    graspable_radius = (0.01,)
    notes = ("RLBench's lid is a knob and a lid body joined by a force sensor; here one free "
             "body with the knob's centre as its grasp point. Round parts collide through "
             "inscribed boxes (an eight-sided pot wall, a star-shaped lid).")

    def descriptions(self, variation: int) -> list[str]:
        return ["take lid off the saucepan", "using the handle, lift the lid off of the pan",
                "remove the lid from the pan", "grip the saucepan's lid and remove it from the pan",
                "leave the pan open", "uncover the saucepan"]

    def build(self, scene) -> None:
        root = scene.mocap("take_lid_off_saucepan")
        saucepan(scene, root, "saucepan", center=KNOB_XY, height=POT_HEIGHT)
        sensor_volume(root, "saucepan_success", (*KNOB_XY, 0.216 + SUCCESS_HALF[2]), SUCCESS_HALF)

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, FOOTPRINT_HALF, jnp.pi, offset=FOOTPRINT_CENTER)
        return Placement(bodies={"take_lid_off_saucepan": (pos, quat),
                                 "saucepan_lid": pose_in_root(pos, quat, LID_POS)})

    def success(self, variation):
        # Knob held and lifted into the volume (RLBench's ConditionSet, unordered).
        return all_of([Grasped(0), Detected("saucepan_lid_grasp_point", "saucepan_success",
                                            SUCCESS_HALF, radius=0.01)])

    def expert(self, obs, variation):
        """Above the knob, down onto it and close, lift to 0.217 m (RLBench's waypoints)."""
        knob = obs.pos("saucepan_lid_grasp_point")
        up = lambda dz: knob + jnp.array([0.0, 0.0, dz])  # noqa: E731
        return key_actions([(up(0.041), DOWN, 1.0), (up(-0.005), DOWN, 0.0),
                            (up(0.116), DOWN, 0.0)])


TASK = TakeLidOffSaucepan()
