"""phone_on_base (unseen, Level 1): put the handset back into its base's cradle."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.tasks.base import Placement, Split, Task, in_frame, key_actions, place_root
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_body,
    grasp_site,
    pose_in_root,
    sensor_volume,
    yaw_of,
)
from agnostos_mjx.tasks.builders.household import placed, solid
from agnostos_mjx.tasks.builders.primitives import WHITE, panel

BASE_RGBA = (1.0, 0.27, 0.0)
# The base: a 0.282 x 0.204 m slab, a raised keypad block and a lip that
# together leave a 0.072 m wide cradle along x at y = 0.066 (root frame).
SLAB_TOP, RIM_TOP = 0.035, 0.062
PHONE_START = (0.002, 0.237, 0.036)
SUCCESS_CENTER, SUCCESS_HALF = (0.001, 0.066, 0.064), (0.075, 0.025, 0.025)
# RLBench's grasp point on the handset (0.027 m off its centre), and where
# the expert lets go of it above the cradle.
GRASP_OFFSET = (0.027, 0.003, 0.014)
RELEASE = (0.028, 0.065, 0.111)
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.141, 0.185), (0.0, 0.083)


class PhoneOnBase(Task):
    name = "phone_on_base"
    split = Split.LEVEL1
    objects = {"phone": "phone", "phone case": "phone_case_center"}
    frames = ("phone_case", "success")
    graspables = ("phone",)
    graspable_radius = (0.02,)
    notes = (
        "Typo fixed: 'put the hone on the hub' reads 'put the phone on the hub'. The base and the "
        "handset are built from boxes (an old-style handset: two 0.066 m high ends joined by a "
        "lower grip bar); the cradle is a 0.072 m wide groove around RLBench's success volume."
    )

    def descriptions(self, variation: int) -> list[str]:
        return ["put the phone on the base", "put the phone on the stand",
                "put the phone on the hub", "grasp the phone and put it on the base",
                "place the phone on the base", "put the phone back on the base"]

    def build(self, scene) -> None:
        base = scene.mocap("phone_case")
        panel(base, (0.141, 0.102, SLAB_TOP / 2), (0, 0, SLAB_TOP / 2), BASE_RGBA)
        rim = (RIM_TOP - SLAB_TOP) / 2
        panel(base, (0.141, 0.066, rim), (0, -0.036, SLAB_TOP + rim), BASE_RGBA)  # keypad block
        panel(base, (0.141, 0.004, rim), (0, 0.106, SLAB_TOP + rim), BASE_RGBA)  # lip
        grasp_site(base, "phone_case_center", [0, 0, 0.037])
        sensor_volume(base, "success", SUCCESS_CENTER, SUCCESS_HALF)
        phone = free_body(scene, "phone")
        for sx in (-1, 1):  # earpiece and mouthpiece
            solid(phone, (0.025, 0.03, 0.033), (sx * 0.109, 0, -0.003), WHITE, 0.09)
        solid(phone, (0.085, 0.022, 0.015), (0, 0, 0.015), WHITE, 0.091)  # grip bar

    def sample(self, key, variation) -> Placement:
        # No spawn boundaries: the root turns with any yaw, the handset lies beside the base.
        pos, quat = place_root(key, FOOTPRINT_HALF, jnp.pi, offset=FOOTPRINT_CENTER)
        return Placement(bodies={"phone_case": (pos, quat),
                                 "phone": pose_in_root(pos, quat, PHONE_START)})

    def success(self, variation):
        return placed("phone", "success", SUCCESS_HALF)

    def expert(self, obs, variation):
        grip = down_grasp(yaw_of(obs.quat("phone")))
        place = down_grasp(yaw_of(obs.quat("phone_case")))
        grasp = in_frame(obs, "phone", GRASP_OFFSET)
        up = jnp.array([0.0, 0.0, 0.075])
        release = in_frame(obs, "phone_case", RELEASE)
        return key_actions([
            (grasp + up, grip, 1.0),
            (grasp, grip, 0.0),
            (grasp + up, grip, 0.0),
            (release + jnp.array([0.0, 0.0, 0.047]), place, 0.0),
            (release, place, 1.0),
        ])


TASK = PhoneOnBase()
