"""reach_and_drag (seen): pick up a stick and drag the cube onto the coloured target with it."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.colors import COLORS
from agnostos_mjx.sim.conditions import Detected
from agnostos_mjx.sim.math3d import axis_angle_quat, quat_conj, quat_mul, quat_rotate, yaw_quat
from agnostos_mjx.tasks.base import Placement, Split, Task, key_actions, place_root
from agnostos_mjx.tasks.builders.blocks import flat_patch, rotation_between, stick
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_box,
    pose_in_root,
    sensor_volume,
    yaw_of,
)

ROOT = "reach_and_drag_root"
CUBE_HALF = 0.04
CUBE_XY = (0.106, -0.150)
STICK_HALF_LENGTH, STICK_HALF_WIDTH, GRIP_FROM_END = 0.18, 0.0064, 0.027
# The stick leans from the cube's top edge (its held end) down to the table:
# centre, heading and downward pitch of its +x axis in the root frame.
STICK_CENTRE = (0.145, -0.021, 0.060)
STICK_YAW, STICK_PITCH = 1.192, 0.276
PATCH_HALF = 0.065
TARGET_XY = (-0.137, -0.154)
DISTRACTOR_XY = ((0.088, 0.121), (0.088, -0.379), (0.253, -0.153))
# Dragging: the stick lies level along the root's +y at this height, first
# this far beyond the cube's +x face, then pulled along -x until the cube
# sits on the target's centre.
DRAG_Z, GAP = 0.03, 0.03
ABOVE = 0.1


class ReachAndDrag(Task):
    name = "reach_and_drag"
    split = Split.SEEN
    num_variations = 20
    objects = {"stick": "stick", "cube": "cube"}
    frames = (ROOT, "stick_grasp", "success0", "target0")
    graspables = ("stick",)
    grasp_points = ("stick_grasp",)
    graspable_radius = (0.01,)
    notes = (
        "The fourth description keeps the original's 'use the its other end' verbatim. The "
        "expert lays the held stick level along the root's y axis beside the cube and pulls "
        "it along -x (RLBench tilts the gripper ~32 degrees instead); the orientation is "
        "computed from the stick's pose in the hand. The root is sampled with a 0.3 x 0.3 m "
        "footprint (the original's proxy is not documented); unreachable scenes are "
        "resampled.")

    def descriptions(self, variation: int) -> list[str]:
        c = COLORS[variation][0]
        return [f"use the stick to drag the cube onto the {c} target",
                f"pick up the stick and use it to push or pull the cube onto the {c} target",
                f"drag the block towards the {c} square on the table top",
                "grasping the stick by one end, pick it up and use the its other end to move "
                f"the block onto the {c} target"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        target = root.add_body(name="target0", pos=[*TARGET_XY, 0.0])
        flat_patch(target, "target0", (0.0, 0.0, 0.0), (PATCH_HALF, PATCH_HALF), (1.0, 0.0, 0.0))
        # RLBench's success0: 0.1 x 0.1 m, 1 cm high, centred on the table top.
        sensor_volume(target, "success0", (0.0, 0.0, 0.0), (0.05, 0.05, 0.005))
        for k, (x, y) in enumerate(DISTRACTOR_XY):
            flat_patch(root, f"distractor{k + 1}", (x, y, 0.0), (PATCH_HALF, PATCH_HALF),
                       (1.0, 0.0, 0.0))
        free_box(scene, "cube", (CUBE_HALF,) * 3, (0.85, 0.85, 1.0), mass=0.512)
        stick(scene, "stick", STICK_HALF_LENGTH, STICK_HALF_WIDTH, (0.85, 0.85, 1.0), mass=0.059,
              grip_from_end=GRIP_FROM_END)

    def sample(self, key, variation) -> Placement:
        root_pos, root_quat = place_root(key, (0.15, 0.15), jnp.pi, offset=(0.058, -0.129))
        stick_pos, heading = pose_in_root(root_pos, root_quat, STICK_CENTRE, yaw_quat(STICK_YAW))
        pitch = axis_angle_quat(jnp.array([0.0, 1.0, 0.0]), jnp.float32(STICK_PITCH))
        rgb = jnp.asarray([c for _, c in COLORS], jnp.float32)
        colors = {"target0": rgb[variation]}
        colors |= {f"distractor{k}": rgb[(variation + 4 + k) % len(COLORS)] for k in (1, 2, 3)}
        return Placement(bodies={
            ROOT: (root_pos, root_quat),
            "cube": pose_in_root(root_pos, root_quat, (*CUBE_XY, CUBE_HALF)),
            "stick": (stick_pos, quat_mul(heading, pitch)),
        }, colors=colors)

    def success(self, variation):
        return Detected("cube", "success0", (0.05, 0.05, 0.005), radius=CUBE_HALF)

    def expert(self, obs, variation):
        root_pos, root_quat = obs.pos(ROOT), obs.quat(ROOT)
        grip = obs.pos("stick_grasp")
        along = quat_rotate(obs.quat("stick"), jnp.array([1.0, 0.0, 0.0]))  # held end -> tip
        # Grasp from above, fingers closing across the stick.
        grasp = down_grasp(yaw_of(obs.quat("stick")))
        # Turn the hand so the stick lies level along the root's +y.
        level = quat_rotate(root_quat, jnp.array([0.0, 1.0, 0.0]))
        drag = quat_mul(rotation_between(along, level), grasp)

        def world(x, y, z):
            return root_pos + quat_rotate(root_quat, jnp.stack([x, y, jnp.float32(z)]))

        cube = quat_rotate(quat_conj(root_quat), obs.pos("cube") - root_pos)  # root frame
        held = STICK_HALF_LENGTH - GRIP_FROM_END  # the grip point to the stick's middle
        beside = cube[0] + CUBE_HALF + STICK_HALF_WIDTH + GAP
        done = TARGET_XY[0] + CUBE_HALF + STICK_HALF_WIDTH
        y = cube[1] - held
        return key_actions([
            (grip + jnp.array([0.0, 0.0, 0.05]), grasp, 1.0),  # above the stick's raised end
            (grip, grasp, 0.0),  # grasp it
            (grip + jnp.array([0.0, 0.0, 0.12]), grasp, 0.0),  # lift
            (world(beside, y, DRAG_Z + ABOVE), drag, 0.0),  # level, above the cube's far side
            (world(beside, y, DRAG_Z), drag, 0.0),  # down beside the cube
            (world(jnp.float32(done), y, DRAG_Z), drag, 0.0),  # drag it onto the target
        ])


TASK = ReachAndDrag()
