"""unplug_charger (unseen, Level 2): pull the charger out of the wall socket."""

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
from agnostos_mjx.tasks.builders.common import DOWN, pose_in_root, sensor_volume
from agnostos_mjx.tasks.builders.kitchen import DARK, plug, wall_socket

# Gripper pointing down, fingers across the charger (along the root's y).
CHARGER_HALF = (0.0345, 0.025, 0.0125)
CHARGER_POS = (0.0865, -0.022, 0.219)  # body centre, 2 mm off the socket; pins 2.3 cm in
HOLES = ((-0.034, 0.219), (-0.009, 0.219))
SOCKET_FRONT = 0.123
# RLBench's `charger_success`: 0.05 m cube about 0.13 m in front of the wall.
SUCCESS_HALF = (0.025, 0.025, 0.025)
SUCCESS_POS = (-0.031, -0.036, 0.195 + 0.025)
GRASP_X = -0.0235  # grasp point in the charger frame: its rear half (RLBench: 3 mm from the end)
PULL = 0.117  # straight back along the root's -x, as RLBench's waypoint1
# Footprint in the root frame: the wall (y +-0.2) back to the success volume.
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.117, 0.2), (0.057, 0.0)


class UnplugCharger(Task):
    name = "unplug_charger"
    split = Split.LEVEL2
    objects = {"charger": "charger", "plug": "unplug_charger_socket"}  # RLBench's names
    frames = ("charger_success", "unplug_charger")
    graspables = ("charger",)
    grasp_points = ("charger_grasp_point",)
    graspable_radius = (0.01,)
    notes = ("The charger is dark to match the language (\"the black charger\"); RLBench's "
             "visual mesh is grey. Its two pins sit in two square tubes and hold it by contact. "
             "The expert grasps the charger centred across its width and 1 cm further in than "
             "RLBench's waypoint (3 mm from the rear end, off-centre by 1.4 cm), which leaves "
             "the open fingers 1 mm of clearance here. The wall and the socket plate are visual "
             "only, as in RLBench; the holes' tubes collide.")

    def descriptions(self, variation: int) -> list[str]:
        return ["unplug charger", "take the charger out of the wall",
                "grip the black charger and pull it out of its socket",
                "slide the plug out from the wall", "remove the charger from the mains",
                "get the charger from the wall plug"]

    def build(self, scene) -> None:
        root = scene.mocap("unplug_charger")
        wall_socket(root, "unplug_charger", face_x=SOCKET_FRONT, plate_center=(-0.022, 0.217),
                    holes=HOLES)
        plug(scene, "charger", body_half=CHARGER_HALF,
             pins=[(y - CHARGER_POS[1], z - CHARGER_POS[2]) for y, z in HOLES],
             pin_half=(0.0031, 0.0031), pin_length=0.025, grasp_offset=(GRASP_X, 0.0, 0.0),
             rgba=DARK, mass=0.006)
        sensor_volume(root, "charger_success", SUCCESS_POS, SUCCESS_HALF)

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, FOOTPRINT_HALF, jnp.pi / 4, offset=FOOTPRINT_CENTER)
        return Placement(bodies={"unplug_charger": (pos, quat),
                                 "charger": pose_in_root(pos, quat, CHARGER_POS)})

    def success(self, variation):
        return Detected("charger", "charger_success", SUCCESS_HALF, radius=0.01)

    def expert(self, obs, variation):
        """Down onto the charger's rear half and close, pull straight back."""
        quat = frame_quat(obs, "unplug_charger", DOWN)
        grasp = obs.pos("charger_grasp_point")
        back = in_frame(obs, "unplug_charger", (-PULL, 0.0, 0.0)) - obs.pos("unplug_charger")
        return key_actions([(grasp + jnp.array([0.0, 0.0, 0.08]), quat, 1.0),
                            (grasp, quat, 0.0), (grasp + back, quat, 0.0)])


TASK = UnplugCharger()
