"""close_microwave (unseen, Level 1): push the open microwave door shut."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import JointMoved
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders import hinged_door, panel
from agnostos_mjx.tasks.builders.common import DOWN_ACROSS

OPEN_ANGLE = 0.6981317  # 40 degrees, as the model saves it
FRAME_RGBA = (0.85, 0.85, 1.0)
# Gripper pointing down, fingers across the push direction.
DOWN = DOWN_ACROSS


class CloseMicrowave(Task):
    name = "close_microwave"
    split = Split.LEVEL1
    objects = {"microwave door": "microwave_door", "microwave frame": "microwave_frame"}
    frames = ("microwave_root",)
    joints = ("microwave_door_joint",)
    notes = ("Success is RLBench's JointCondition(door, 40 deg) from a 40-degree opening: the "
             "door must reach its closed limit (opening it past 80 degrees would also count).")

    def descriptions(self, variation: int) -> list[str]:
        return ["close microwave", "shut the microwave", "close the microwave door",
                "push the microwave door shut"]

    def build(self, scene) -> None:
        root = scene.mocap("microwave_root")
        frame = root.add_body(name="microwave_frame", pos=[0.005, 0.33, 0.16])
        # Five panels, 0.57 x 0.28 x 0.31 m, open towards the root's -y.
        panel(frame, (0.285, 0.138, 0.01), (0, 0, -0.147), FRAME_RGBA)
        panel(frame, (0.285, 0.138, 0.01), (0, 0, 0.148), FRAME_RGBA)
        panel(frame, (0.01, 0.138, 0.157), (-0.275, 0, 0), FRAME_RGBA)
        panel(frame, (0.01, 0.138, 0.157), (0.275, 0, 0), FRAME_RGBA)
        panel(frame, (0.285, 0.01, 0.157), (0, 0.128, 0), FRAME_RGBA)
        panel(frame, (0.06, 0.005, 0.14), (0.2, -0.13, 0), (0.3, 0.3, 0.35), collide=False)
        hinged_door(scene, root, "microwave_door", hinge_pos=(-0.265, 0.182, 0.138),
                    axis=(0, 0, -1), panel_half=(0.228, 0.023, 0.132),
                    panel_offset=(0.228, -0.023, 0.0), limits=(0.0, 1.571),
                    initial=OPEN_ANGLE, friction_torque=2.07, rgba=(0.75, 0.75, 0.85))
        scene.exclude("microwave_frame", "microwave_door")

    def sample(self, key, variation) -> Placement:
        # RLBench places the `boundary_root` proxy (0.48 x 0.225 m) with yaw +-pi/8.
        pos, quat = place_root(key, (0.24, 0.113), jnp.pi / 8, offset=(-0.025, 0.0))
        return Placement(bodies={"microwave_root": (pos, quat)})

    def success(self, variation):
        return JointMoved(self.joints, OPEN_ANGLE)

    def expert(self, obs, variation):
        quat = frame_quat(obs, "microwave_root", DOWN)
        return key_actions([
            (in_frame(obs, "microwave_root", (-0.082, -0.122, 0.228)), quat, 1.0),
            (in_frame(obs, "microwave_root", (0.124, 0.169, 0.26)), quat, 1.0),
        ])


TASK = CloseMicrowave()
