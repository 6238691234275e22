"""close_laptop_lid (unseen, Level 1): push the open laptop lid over until it shuts."""

from __future__ import annotations

import math

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
from agnostos_mjx.tasks.builders.appliances import LAPTOP_HINGE, laptop
from agnostos_mjx.tasks.builders.common import DOWN_ACROSS

# Gripper pointing down, fingers (closed into a fist) along the hinge axis.
FIST = DOWN_ACROSS
# The push in the hinge's (angle from upright towards the keyboard, radius)
# polar coordinates: behind the lid's top edge, then over and down (RLBench's
# 11-point arc of radius 0.24 m about the hinge).
APPROACH = ((-0.5, 0.32), (-0.32, 0.22))
ARC = ((0.35, 0.23), (0.9, 0.245), (1.5, 0.243))
# Model bounding box: holder, base and open lid, x[-0.214, 0.186], y[-0.224, 0.088].
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.2, 0.156), (-0.014, -0.068)


def _polar(angle: float, radius: float) -> tuple[float, float, float]:
    """Root-frame point at `radius` from the hinge, `angle` from upright
    towards -y, in RLBench's waypoint plane x = -0.039."""
    _, y, z = LAPTOP_HINGE
    return (-0.039, y - radius * math.sin(angle), z + radius * math.cos(angle))


class CloseLaptopLid(Task):
    name = "close_laptop_lid"
    split = Split.LEVEL1
    objects = {"lid": "laptop_lid_center", "laptop holder": "laptop_holder",
               "laptop base": "laptop_base"}
    frames = ("laptop_root",)
    joints = ("laptop_lid_joint",)
    notes = ("The holder block (12 kg) and the laptop base (1.35 kg) are dynamic in RLBench and "
             "static here; neither moves when the lid is pushed. The lid has no contact with the "
             "base and rests on its 105-degree limit (see builders.appliances.laptop). The expert "
             "approaches from above behind the lid and pushes along 3 key actions instead of the "
             "11-point arc; like RLBench it closes the empty gripper first and opens it to 0.1 at "
             "the end.")

    def descriptions(self, variation: int) -> list[str]:
        return ["close laptop lid", "close the laptop", "shut the laptop lid"]

    def build(self, scene) -> None:
        laptop(scene, scene.mocap("laptop_root"))

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, FOOTPRINT_HALF, jnp.pi, offset=FOOTPRINT_CENTER)
        return Placement(bodies={"laptop_root": (pos, quat)})

    def success(self, variation):
        return JointMoved(self.joints, 1.79)

    def expert(self, obs, variation):
        quat = frame_quat(obs, "laptop_root", FIST)
        at = lambda p: in_frame(obs, "laptop_root", _polar(*p))  # noqa: E731
        end = _polar(*ARC[-1])
        retreat = (end[0], end[1] - 0.05, end[2])
        return key_actions(
            [(at(APPROACH[0]), quat, 1.0), (at(APPROACH[1]), quat, 0.0)]
            + [(at(p), quat, 0.0) for p in ARC]
            + [(at(ARC[-1]), quat, 0.1), (in_frame(obs, "laptop_root", retreat), quat, 0.1)])


TASK = CloseLaptopLid()
