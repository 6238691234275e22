"""sweep_to_dustpan_of_size (seen): sweep five bits of dirt into the tall or the short dustpan."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, all_of
from agnostos_mjx.sim.math3d import euler_xyz_quat, quat_mul, quat_rotate
from agnostos_mjx.tasks.base import Placement, Split, Task, key_actions, place_root
from agnostos_mjx.tasks.builders.blocks import broom
from agnostos_mjx.tasks.builders.common import free_box, pose_in_root, sensor_volume
from agnostos_mjx.tasks.builders.primitives import panel, rod

ROOT = "sweep_to_dustpan_of_size_root"
SIZES = ("tall", "short")
DIRT = tuple(f"dirt{k}" for k in range(5))
DIRT_XY = ((0.05, -0.05), (0.025, 0.0), (0.0, -0.05), (0.05, 0.0), (0.0, -0.075))
DIRT_HALF = 0.005
DIRT_RGB = (0.46, 0.31, 0.31)
# Success volumes (centre xy, half extents incl. height) per size, from the model.
VOLUMES = (((0.0, -0.275), (0.125, 0.075, 0.025)), ((0.041, 0.187), (0.075, 0.045, 0.015)))
# Broom: head 0.26 m wide (along the root's x), handle leaning 26 degrees
# towards +y against a static holder; grasped 0.325 m up the handle.
HEAD_HALF = (0.13, 0.02, 0.03)
LEAN, GRIP_HEIGHT = 0.454, 0.325
BROOM_XY = (-0.171, 0.096)
HOLDER_XY, HOLDER_HALF = (-0.175, 0.376), (0.05, 0.05, 0.25)
# The gripper points along the root's +y, fingers closing along x, the hand
# upright (tip x axis up, as the downward grasp pitched forward): upside down,
# the wrist (joint 7) sits near its limit and sweeps swing the arm away.
SIDEWAYS = quat_mul(euler_xyz_quat(-jnp.pi / 2, 0.0, 0.0), euler_xyz_quat(0.0, 0.0, -jnp.pi / 2))
# Sweeps of the head's underside centre (start y, end y) along the root's y
# at x = HEAD_X: tall towards -y, short towards +y.
HEAD_X = 0.025
SWEEPS = ((0.08, -0.275), (-0.125, 0.162))
SWEEP_Z, HOVER_Z = 0.003, 0.03
# Short strokes: one long fast stroke lets the arm lag and lift the head over the dirt.
SWEEP_STROKES = 4


class SweepToDustpanOfSize(Task):
    name = "sweep_to_dustpan_of_size"
    split = Split.SEEN
    num_variations = 2
    objects = {"dustpan": "dustpan_tall", "broom holder": "broom_holder"}
    frames = (ROOT, "success", "broom_grasp", "broom_head") + DIRT
    graspables = ("broom",)
    grasp_points = ("broom_grasp",)
    graspable_radius = (0.012,)
    notes = (
        "Dustpans are visual boxes (non-respondable in RLBench too). The broom is a level "
        "0.26 m head with a leaning capsule handle; its holder is static here (5 kg dynamic "
        "box in RLBench). Dirt cubes weigh 2 g instead of 0.5 mg (MuJoCo needs sane mass "
        "ratios). One success volume is moved onto the chosen pan with that pan's size. The "
        "expert keeps the grasp orientation while sweeping and runs the head 3 mm above "
        "the table instead of dragging it (ignore_collisions in RLBench), holds the handle "
        "with the hand upright and sweeps in four short strokes (one key action each) "
        "instead of RLBench's single stroke: in one long fast stroke the arm lags and the "
        "head lifts over the dirt.")

    def descriptions(self, variation: int) -> list[str]:
        s = SIZES[variation]
        return [f"sweep dirt to the {s} dustpan", f"sweep the dirt up into the {s} dustpan",
                f"use the broom to brush the dirt into the {s} dustpan",
                f"clean up the dirt with the {s} pan"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        dark, grey = (0.1, 0.1, 0.1), (0.59, 0.59, 0.59)
        tall = root.add_body(name="dustpan_tall", pos=[0.0, -0.301, 0.0])
        panel(tall, (0.137, 0.109, 0.002), (0.0, 0.0, 0.002), dark, collide=False)
        panel(tall, (0.137, 0.004, 0.045), (0.0, -0.105, 0.045), dark, collide=False)
        rod(tall, (0.01, -0.03, 0.086), (0.01, -0.03, 0.68), 0.01, grey)
        short = root.add_body(name="dustpan_short", pos=[0.044, 0.203, 0.0])
        panel(short, (0.082, 0.065, 0.002), (0.0, 0.0, 0.002), dark, collide=False)
        panel(short, (0.082, 0.004, 0.027), (0.0, 0.061, 0.027), dark, collide=False)
        rod(short, (0.006, 0.018, 0.052), (0.006, 0.018, 0.41), 0.006, grey)
        holder = root.add_body(name="broom_holder", pos=[*HOLDER_XY, 0.0])
        panel(holder, HOLDER_HALF, (0.0, 0.0, HOLDER_HALF[2]), (0.35, 0.48, 0.54))
        success = scene.mocap("success_pan")
        sensor_volume(success, "success", (0.0, 0.0, 0.0), VOLUMES[0][1])  # the condition sizes it
        broom(scene, "broom", HEAD_HALF, 0.6, LEAN, GRIP_HEIGHT, (0.46, 0.31, 0.2), mass=0.445)
        for name in DIRT:
            free_box(scene, name, (DIRT_HALF,) * 3, DIRT_RGB, mass=0.002)

    def sample(self, key, variation) -> Placement:
        root_pos, root_quat = place_root(key, (0.15, 0.15), jnp.pi, offset=(-0.025, 0.0))
        centre = jnp.asarray([c for c, _ in VOLUMES])[variation]
        height = jnp.asarray([h[2] for _, h in VOLUMES])[variation]
        bodies = {ROOT: (root_pos, root_quat),
                  "broom": pose_in_root(root_pos, root_quat, (*BROOM_XY, 0.0)),
                  "success_pan": pose_in_root(root_pos, root_quat, (centre[0], centre[1], height))}
        for name, (x, y) in zip(DIRT, DIRT_XY):
            bodies[name] = pose_in_root(root_pos, root_quat, (x, y, DIRT_HALF))
        return Placement(bodies=bodies)

    def success(self, variation):
        half = jnp.asarray([h for _, h in VOLUMES])[variation]
        return all_of([Detected(d, "success", half, DIRT_HALF) for d in DIRT])

    def expert(self, obs, variation):
        root_pos, root_quat = obs.pos(ROOT), obs.quat(ROOT)
        grasp_q = quat_mul(root_quat, SIDEWAYS)
        grip = obs.pos("broom_grasp")
        head_from_grip = obs.pos("broom_head") - grip  # the broom keeps this pose in the hand
        toward = quat_rotate(root_quat, jnp.array([0.0, 1.0, 0.0]))
        up = jnp.array([0.0, 0.0, 1.0])
        start, end = jnp.asarray(SWEEPS)[variation]

        def tip_for_head(y, z):
            head = root_pos + quat_rotate(root_quat, jnp.stack([jnp.float32(HEAD_X), y,
                                                                jnp.float32(z)]))
            return head - head_from_grip

        strokes = [(tip_for_head(start + (end - start) * k / SWEEP_STROKES, SWEEP_Z), grasp_q, 0.0)
                   for k in range(1, SWEEP_STROKES + 1)]  # sweep into the pan
        return key_actions([
            (grip - 0.08 * toward, grasp_q, 1.0),  # in front of the handle
            (grip, grasp_q, 0.0),  # grasp it
            (grip + 0.05 * up, grasp_q, 0.0),  # lift the head off the table
            (tip_for_head(start, HOVER_Z), grasp_q, 0.0),  # over the sweep's start
            (tip_for_head(start, SWEEP_Z), grasp_q, 0.0),  # head down
            *strokes,
        ])


TASK = SweepToDustpanOfSize()
