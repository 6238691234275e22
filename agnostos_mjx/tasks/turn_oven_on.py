"""turn_oven_on (unseen, Level 2): turn the oven's left-most knob a quarter turn."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import JointMoved
from agnostos_mjx.sim.math3d import axis_angle_quat, euler_xyz_quat, quat_mul
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.kitchen import oven

KNOB = (0.027, 0.200, 0.491)  # the left-most knob, seen from the front
DECOR_KNOBS = ((0.028, 0.110, 0.490), (0.028, 0.027, 0.489), (0.027, -0.052, 0.490),
               (0.028, -0.123, 0.471), (0.025, -0.186, 0.490), (0.029, -0.257, 0.489))
# Gripper horizontal, pointing into the oven front (root +x), fingers along
# the root's y around the knob's grip bar; then rolled 90 degrees about the
# knob's axis (root -x), anticlockwise as seen from the front.  Of the two
# hand poses that put the fingers along y, this one (camera side up) leaves
# joint 7 room for the roll on the arm's usual IK branch.
FORWARD = quat_mul(axis_angle_quat(jnp.array([0.0, 1.0, 0.0]), -jnp.pi / 2),
                   euler_xyz_quat(jnp.pi, 0.0, 0.0))
TURNED = quat_mul(axis_angle_quat(jnp.array([-1.0, 0.0, 0.0]), jnp.pi / 2), FORWARD)


class TurnOvenOn(Task):
    name = "turn_oven_on"
    split = Split.LEVEL2
    objects = {"oven": "oven_frame", "oven knob": "oven_knob"}
    frames = ("turn_oven_on",)
    joints = ("oven_knob_joint",)
    # RLBench turns the knob by the fingers' grip on it; we attach the closed
    # gripper to the knob (which stays on its hinge), as open_drawer does.
    graspables = ("oven_knob",)
    graspable_radius = (0.01,)
    notes = ("The knob is turned by attaching the closed gripper to it (it stays on its hinge), "
             "not by a friction grip, as open_drawer does with its handle. Meshes become boxes: "
             "one collision box for the cabinet, a visual stove top, the door (closed, hinged at "
             "its bottom, RLBench's q = 90 deg closed convention) and the tray (on its slide) "
             "keep their joints. The expert adds a stand-off 0.15 m in front of the knob "
             "(RLBench's planner went round the oven).")

    def descriptions(self, variation: int) -> list[str]:
        return ["turn on the oven",
                "grip the left most knob on the oven and rotate it anti-clockwise to turn the oven "
                "on", "turn the left most knob on the oven to switch the oven on", "heat up the oven",
                "get the oven hot", "preheat the oven", "get the oven heat going"]

    def build(self, scene) -> None:
        root = scene.mocap("turn_oven_on")
        oven(scene, root, "oven", active_knob=KNOB, decor_knobs=DECOR_KNOBS)

    def sample(self, key, variation) -> Placement:
        # RLBench samples the 0.10 x 0.55 m proxy plane at the root, yaw +-pi/4.
        pos, quat = place_root(key, (0.05, 0.275), jnp.pi / 4, offset=(0.0, -0.025))
        return Placement(bodies={"turn_oven_on": (pos, quat)})

    def success(self, variation):
        return JointMoved(self.joints, 1.5)

    def expert(self, obs, variation):
        forward = frame_quat(obs, "turn_oven_on", FORWARD)
        turned = frame_quat(obs, "turn_oven_on", TURNED)
        knob = obs.pos("oven_knob")
        front = lambda d: in_frame(obs, "oven_knob", (-d, 0.0, 0.0))  # noqa: E731
        return key_actions([
            (front(0.15), forward, 1.0),  # stand-off in front of the oven
            (front(0.025), forward, 1.0),  # RLBench's waypoint0
            (knob, forward, 0.0),  # on the knob, close
            (knob, turned, 0.0),  # roll a quarter turn
        ])


TASK = TurnOvenOn()
