"""put_item_in_drawer (seen): open a drawer, then put the block from the chest top in it."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, Select
from agnostos_mjx.sim.math3d import euler_xyz_quat, quat_rotate, yaw_quat
from agnostos_mjx.tasks.base import (
    TABLE_Z,
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    sample_on_plane,
)
from agnostos_mjx.tasks.builders.articulated import drawer_chest
from agnostos_mjx.tasks.builders.common import DOWN_ACROSS, free_box, pose_in_root, sensor_volume

LEVELS = ("bottom", "middle", "top")
ROOT = "put_item_in_drawer_root"
CHEST_OFFSET = (0.025, -0.175)  # chest centre in the task-root frame, as in RLBench
CHEST_TOP = 0.457  # top of drawer_chest's frame with its default sizes
DRAWER_HEIGHT = 0.118  # drawer_chest's default
ITEM_HALF = 0.02
ITEM_LOCAL = (0.050, -0.150, CHEST_TOP + ITEM_HALF)  # on the chest top, root frame
# RLBench's success_<level> sensors: 0.30 x 0.30 m, 0.075 m high from the drawer floor.
VOLUME_HALF = (0.15, 0.15, 0.0375)
# Gripper horizontal, approaching the handle along the chest's -y, fingers
# closing vertically around the bar (as in open_drawer); and pointing down.
HORIZONTAL = euler_xyz_quat(jnp.pi / 2, 0.0, 0.0)
DOWN = DOWN_ACROSS  # fingers along the chest's x
PULL = 0.20  # RLBench's wp3: the drawer is pulled 0.20 m, then released
BACK_OFF = 0.04  # RLBench backs off 0.113 m (wp4); enough to clear the bar, and in reach
# Where the chest centre is drawn (centre, half extents), world frame.
CHEST_REGION = ((0.17, -0.17), (0.08, 0.08))


class PutItemInDrawer(Task):
    name = "put_item_in_drawer"
    split = Split.SEEN
    num_variations = 3
    objects = {"item": "item", "drawer": "drawer_frame"}
    frames = (ROOT,) + tuple(f"drawer_handle_{lv}" for lv in LEVELS) + tuple(
        f"success_{lv}" for lv in LEVELS)
    joints = tuple(f"drawer_joint_{lv}" for lv in LEVELS)
    # The drawers are pulled through the attach, as in open_drawer; the item is
    # RLBench's registered graspable.
    graspables = tuple(f"drawer_{lv}" for lv in LEVELS) + ("item",)
    grasp_points = tuple(f"drawer_handle_{lv}" for lv in LEVELS) + ("item",)
    graspable_radius = (0.01, 0.01, 0.01, ITEM_HALF)
    notes = ("The drawer handle is held by the kinematic attach (RLBench pinches it with "
             "friction). The chest centre is drawn from a 0.16 x 0.16 m region on the robot's "
             "right, yaw +-pi/8, instead of the whole workspace: there the Panda can pull the "
             "drawers out along +y and reach over the 0.46 m high chest top (most "
             "whole-workspace placements were out of reach). The expert backs off 0.04 m "
             "instead of 0.113 m, skips RLBench's high safe points (out of reach pointing "
             "down) and adds via-points in front of and above the chest, because our "
             "controller has no collision-aware planner.")

    def descriptions(self, variation: int) -> list[str]:
        o = LEVELS[variation]
        return [f"put the item in the {o} drawer", f"put the block away in the {o} drawer",
                f"open the {o} drawer and place the block inside of it",
                f"leave the block in the {o} drawer"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        chest = root.add_body(name="drawer_frame", pos=[*CHEST_OFFSET, 0.0])
        drawer_chest(scene, chest, "drawer")
        for lv in LEVELS:
            handle_z = scene.spec.site(f"drawer_handle_{lv}").pos[2]
            floor_top = handle_z - DRAWER_HEIGHT / 2 + 0.010
            sensor_volume(scene.spec.body(f"drawer_{lv}"), f"success_{lv}",
                          (0.0, 0.0, floor_top + VOLUME_HALF[2]), VOLUME_HALF)
        free_box(scene, "item", (ITEM_HALF,) * 3, (0.85, 0.85, 1.0), 0.064)

    def sample(self, key, variation) -> Placement:
        # The chest must stand where the Panda can pull its drawers out along
        # +y and reach over its 0.46 m high top: RLBench's whole-workspace
        # placement leaves most scenes out of reach here, so the chest centre
        # is drawn from a smaller region on the robot's right (see notes).
        xy, yaw = sample_on_plane(key, (0.0, 0.0), jnp.pi / 8, plane_center=CHEST_REGION[0],
                                  plane_half=CHEST_REGION[1])
        quat = yaw_quat(yaw)
        pos = jnp.concatenate([xy, jnp.array([TABLE_Z])]) - quat_rotate(
            quat, jnp.array([*CHEST_OFFSET, 0.0]))
        return Placement(bodies={ROOT: (pos, quat), "item": pose_in_root(pos, quat, ITEM_LOCAL)})

    def success(self, variation):
        return Select(tuple(Detected("item", f"success_{lv}", VOLUME_HALF, radius=ITEM_HALF)
                            for lv in LEVELS), variation)

    def expert(self, obs, variation):
        handle = jnp.stack([obs.pos(f"drawer_handle_{lv}") for lv in LEVELS])[variation]
        out = in_frame(obs, ROOT, (0.0, 1.0, 0.0)) - obs.pos(ROOT)
        up = jnp.array([0.0, 0.0, 1.0])
        side = frame_quat(obs, ROOT, HORIZONTAL)
        down = frame_quat(obs, ROOT, DOWN)
        item = obs.pos("item")
        # RLBench passes high safe points (wp0/wp5/wp9) with a planner; pointing
        # straight down they are out of the Panda's reach here, so we carry at
        # a lower height just clear of the item on the chest top.
        carry = obs.pos(ROOT)[2] + CHEST_TOP + 0.09
        # RLBench plans collision-free paths; we pass above the chest front first.
        over = (handle + 0.18 * out).at[2].set(carry)
        pulled = handle + PULL * out
        backed = pulled + BACK_OFF * out
        drop = pulled - 0.076 * out + 0.038 * up  # RLBench's wp10, from the pulled handle
        return key_actions([
            (over, side, 1.0),  # above the chest front, turned horizontal
            (handle + 0.18 * out, side, 1.0),  # stand-off in front of the handle
            (handle + 0.087 * out, side, 1.0),  # pre-grasp (wp1)
            (handle, side, 0.0),  # grasp the handle (wp2)
            (pulled, side, 1.0),  # pull, release (wp3)
            (backed, side, 1.0),  # back off (wp4)
            (backed + 0.18 * up, side, 1.0),  # up until the hand clears the drawer front
            ((handle + 0.07 * out).at[2].set(carry), down, 1.0),  # up over the chest front
            (item.at[2].set(carry), down, 1.0),  # above the item (wp6)
            (item, down, 0.0),  # grasp (wp7)
            (item.at[2].set(carry), down, 0.0),  # lift (wp8)
            (drop.at[2].set(carry), down, 0.0),  # above the opened drawer
            (drop, down, 1.0),  # release into the drawer (wp10)
        ])


TASK = PutItemInDrawer()
