"""put_knife_on_chopping_board (unseen, Level 1): pull the knife out of its
block and lay it on the chopping board."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco

from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_body,
    grasp_site,
    pose_in_root,
    sensor_volume,
    spawn_on_root_plane,
)
from agnostos_mjx.tasks.builders.household import held_by_weld_only, placed, solid
from agnostos_mjx.tasks.builders.primitives import WHITE, panel

WOOD_DARK = (0.5, 0.21, 0.0)
STEEL = (0.92, 0.92, 0.92)
BOARD_HALF, BOARD_CENTER = (0.204, 0.100, 0.0075), (0.0, -0.101)
SUCCESS_CENTER, SUCCESS_HALF = (-0.075, -0.101, 0.023), (0.125, 0.100, 0.010)
# Knife block: 0.08 x 0.06 x 0.156 m; its slot, 0.022 x 0.03 m, sits 0.025 m
# towards the block's +x, as the knife does in RLBench's model.
BLOCK_HALF, BLOCK_TOP, SLOT_X, SLOT_HALF, SLOT_FLOOR = (0.04, 0.03), 0.156, 0.025, (0.011, 0.015), 0.015
KNIFE_HALF_LENGTH, KNIFE_CENTER_Z = 0.108, SLOT_FLOOR + 0.108
# Grasp point on the handle above the knife's centre, 0.035 m below its end as
# RLBench's wp1 (any higher and the handle end hits the palm).
HANDLE_Z = 0.073
# RLBench's spawn plane for the block, in the root frame.
BOUNDARY_CENTER, BOUNDARY_HALF = (0.0, 0.15), (0.25, 0.125)
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.25, 0.238), (0.0, 0.037)
# The knife lies along the approach axis once the gripper is pitched level;
# its centre is then this far ahead of the grasp point.
CENTER_AHEAD = HANDLE_Z
RELEASE_HEIGHT, CARRY_Z = 0.06, 0.40  # above the volume's centre; above the block
ROBOT_BASE_XY, HEADING_OFFSET = (-0.268, -0.006), 0.6


class PutKnifeOnChoppingBoard(Task):
    name = "put_knife_on_chopping_board"
    split = Split.LEVEL1
    objects = {"knife": "knife", "chopping board": "chopping_board"}
    frames = ("board_root", "knife_block", "success")
    graspables = ("knife",)
    grasp_points = ("knife_handle",)
    graspable_radius = (0.01,)
    notes = (
        "Knife (round handle + thin blade) and knife block (boxes around a slot) are primitive "
        "stand-ins for RLBench's meshes. The hand and fingers do not collide with the knife: "
        "RLBench parents the grasped knife to the gripper, and here pad friction on the thin "
        "handle would otherwise hold it tilted against the grasp weld after a jolt. RLBench "
        "plans a collision-free path from the block to the board; the expert instead lifts the "
        "knife clear of the block, pitches the gripper level high above the board (the knife "
        "then points away from the robot, 35 degrees off the radial line, where level poses "
        "are reachable), lowers it and lets go 6 cm above the success volume's centre."
    )

    def descriptions(self, variation: int) -> list[str]:
        return ["put the knife on the chopping board",
                "slide the knife out of the knife block and put it down on the chopping board",
                "place the knife on the chopping board",
                "pick up the knife and leave it on the chopping board",
                "move the knife from the holder to the chopping board"]

    def build(self, scene) -> None:
        root = scene.mocap("board_root")
        panel(root, BOARD_HALF, (*BOARD_CENTER, BOARD_HALF[2]), WHITE)
        grasp_site(root, "chopping_board", [*BOARD_CENTER, 2 * BOARD_HALF[2]])
        sensor_volume(root, "success", SUCCESS_CENTER, SUCCESS_HALF)
        block = scene.mocap("knife_block")
        hx, hy = BLOCK_HALF
        sx, sy = SLOT_HALF
        left = (SLOT_X - sx + hx) / 2  # the solid part beside the slot, towards -x
        panel(block, ((SLOT_X - sx + hx) / 2, hy, BLOCK_TOP / 2), (left - hx, 0, BLOCK_TOP / 2),
              WOOD_DARK)
        right = hx - SLOT_X - sx
        panel(block, (right / 2, hy, BLOCK_TOP / 2), (hx - right / 2, 0, BLOCK_TOP / 2), WOOD_DARK)
        for side in (-1, 1):
            panel(block, (sx, (hy - sy) / 2, BLOCK_TOP / 2),
                  (SLOT_X, side * (hy + sy) / 2, BLOCK_TOP / 2), WOOD_DARK)
        panel(block, (sx, sy, SLOT_FLOOR / 2), (SLOT_X, 0, SLOT_FLOOR / 2), WOOD_DARK)
        knife = free_body(scene, "knife")
        handle = 0.1
        handle_z = KNIFE_HALF_LENGTH - handle / 2
        knife.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[0.008, handle / 2 - 0.008, 0],
                       pos=[0, 0, handle_z], rgba=[0.1, 0.1, 0.1, 1.0], mass=0.06)
        solid(knife, (0.0015, 0.011, KNIFE_HALF_LENGTH - handle / 2),
              (0, 0, -handle / 2), STEEL, 0.04)
        held_by_weld_only(scene, "knife")
        grasp_site(knife, "knife_handle", [0, 0, HANDLE_Z])

    def sample(self, key, variation) -> Placement:
        k_root, k_block = jax.random.split(key)
        pos, quat = place_root(k_root, FOOTPRINT_HALF, jnp.pi, offset=FOOTPRINT_CENTER)
        block = spawn_on_root_plane(k_block, (pos, quat), BLOCK_HALF, BOUNDARY_CENTER,
                                    BOUNDARY_HALF)
        knife = pose_in_root(*block, jnp.array([SLOT_X, 0.0, KNIFE_CENTER_Z]))
        return Placement(bodies={"board_root": (pos, quat), "knife_block": block, "knife": knife})

    def success(self, variation):
        return placed("knife", "success", SUCCESS_HALF, radius=0.005, ordered=True)

    def expert(self, obs, variation):
        # The round handle can be gripped at any yaw: grip it so that, once the
        # gripper is pitched level, the knife points away from the robot (35
        # degrees off the radial line, where level poses are far from the
        # wrist singularity) with its centre on the volume.
        center = in_frame(obs, "board_root", SUCCESS_CENTER)
        away = center[:2] - jnp.asarray(ROBOT_BASE_XY)
        heading = jnp.arctan2(away[1], away[0]) + HEADING_OFFSET
        ahead = jnp.array([jnp.cos(heading), jnp.sin(heading), 0.0])
        grip = down_grasp(heading)
        level = down_grasp(heading, pitch=jnp.pi / 2)
        release = (center - CENTER_AHEAD * ahead).at[2].set(center[2] + RELEASE_HEIGHT)
        handle = obs.pos("knife_handle")
        return key_actions([
            (handle + jnp.array([0.0, 0.0, 0.075]), grip, 1.0),
            (handle, grip, 0.0),
            (handle.at[2].set(obs.pos("knife_block")[2] + CARRY_Z), grip, 0.0),
            (release + jnp.array([0.0, 0.0, CARRY_Z - 0.15]), level, 0.0),
            (release, level, 1.0),
        ])


TASK = PutKnifeOnChoppingBoard()
