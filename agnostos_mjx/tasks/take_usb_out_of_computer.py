"""take_usb_out_of_computer (unseen, Level 2): pull the USB stick out of the
PC's port and let go of it.  RLBench's scene is undocumented: this layout is
our design (see `notes`)."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, NothingGrasped, all_of
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.common import DOWN, pose_in_root, sensor_volume
from agnostos_mjx.tasks.builders.kitchen import HOLDING, desktop_computer, plug

CASE_HALF = (0.15, 0.09, 0.17)
FRONT_X = 0.05  # the case's front face; the stick sticks out towards the root's -x
PORT = (0.0, 0.28)  # (y, z) of the port's mouth
STICK_HALF = (0.0225, 0.009, 0.004)
STICK_POS = (FRONT_X - STICK_HALF[0] - 0.001, PORT[0], PORT[1])  # connector 11 mm in
# The `success` volume covers the plugged-in position around the port.
SUCCESS_HALF = (0.04, 0.02, 0.02)
PULL = 0.10
# Footprint in the root frame: the stick's free end to the case's back.
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.18, 0.09), (0.17, 0.0)


class TakeUsbOutOfComputer(Task):
    name = "take_usb_out_of_computer"
    split = Split.LEVEL2
    objects = {"usb": "usb", "computer": "computer"}
    frames = ("usb_success", "take_usb_out_of_computer")
    graspables = ("usb",)
    grasp_points = ("usb_grasp_point",)
    graspable_radius = (0.008,)
    notes = ("RLBench's scene model is not documented; this layout is our design: a tower PC "
             "(0.30 x 0.18 x 0.34 m) whose front faces the root's -x, a USB stick (45 x 18 x 8 mm, "
             "connector 12 mm deep in a tube port) sticking out of the front 0.28 m above the "
             "table, and a `success` volume around the plugged-in position. The expert follows "
             "the task code's pattern: approach from above (passing over the case, as the root "
             "may face any way), grasp, pull 0.10 m straight out along the port axis, release.")

    def descriptions(self, variation: int) -> list[str]:
        return ["take usb out of computer", "remove the usb stick from its port",
                "retrieve the usb stick", "grasp the usb stick and slide it out of the pc",
                "get a hold of the usb stick and pull it out of the desktop computer"]

    def build(self, scene) -> None:
        root = scene.mocap("take_usb_out_of_computer")
        desktop_computer(root, "computer", front_x=FRONT_X, half=CASE_HALF, port=PORT)
        plug(scene, "usb", body_half=STICK_HALF, pins=[(0.0, 0.0)], pin_half=(0.0060, 0.0023),
             pin_length=0.012, grasp_offset=(-0.004, 0.0, 0.0), rgba=(0.1, 0.25, 0.7), mass=0.008,
             impedance=HOLDING)  # left alone, the stick stays in its port
        sensor_volume(root, "usb_success", (FRONT_X, *PORT), SUCCESS_HALF)

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, FOOTPRINT_HALF, jnp.pi, offset=FOOTPRINT_CENTER)
        return Placement(bodies={"take_usb_out_of_computer": (pos, quat),
                                 "usb": pose_in_root(pos, quat, STICK_POS)})

    def success(self, variation):
        return all_of([Detected("usb", "usb_success", SUCCESS_HALF, radius=0.005, negated=True),
                       NothingGrasped()])

    def expert(self, obs, variation):
        root = "take_usb_out_of_computer"
        quat = frame_quat(obs, root, DOWN)
        grasp = obs.pos("usb_grasp_point")
        out = in_frame(obs, root, (-PULL, 0.0, 0.0)) - obs.pos(root)
        over_case = grasp.at[2].set(obs.pos(root)[2] + 2 * CASE_HALF[2] + 0.12)
        return key_actions([
            (over_case, quat, 1.0),  # above the case's top: no planner to go round it
            (grasp + jnp.array([0.0, 0.0, 0.06]), quat, 1.0),
            (grasp, quat, 0.0),  # close on the stick
            (grasp + out, quat, 0.0),  # slide it out along the port axis
            (grasp + out, quat, 1.0),  # let go
        ])


TASK = TakeUsbOutOfComputer()
