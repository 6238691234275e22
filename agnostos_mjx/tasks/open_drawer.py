"""open_drawer (seen): pull the bottom, middle or top drawer of a chest open."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import JointMoved
from agnostos_mjx.sim.math3d import euler_xyz_quat
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders import drawer_chest

LEVELS = ("bottom", "middle", "top")
CHEST_TOP = 0.466
# Gripper horizontal, approaching the handle along the chest's -y, fingers
# closing vertically around the bar.
GRASP = euler_xyz_quat(jnp.pi / 2, 0.0, 0.0)


class OpenDrawer(Task):
    name = "open_drawer"
    split = Split.SEEN
    num_variations = 3
    objects = {"drawer": "drawer_bottom"}  # X-ICM names only the bottom drawer
    frames = tuple(f"drawer_handle_{lv}" for lv in LEVELS) + ("drawer_root",)
    joints = tuple(f"drawer_joint_{lv}" for lv in LEVELS)
    # RLBench pulls the drawer by pinching its handle with friction; we attach
    # the closed gripper to the drawer instead (the drawer stays on its rail),
    # so success reflects the plan rather than contact tuning.
    graspables = tuple(f"drawer_{lv}" for lv in LEVELS)
    grasp_points = tuple(f"drawer_handle_{lv}" for lv in LEVELS)
    graspable_radius = (0.01, 0.01, 0.01)

    def descriptions(self, variation: int) -> list[str]:
        opt = LEVELS[variation]
        return [f"open the {opt} drawer", f"grip the {opt} handle and pull the {opt} drawer open",
                f"slide the {opt} drawer open"]

    def build(self, scene) -> None:
        root = scene.mocap("drawer_root")
        drawer_chest(scene, root, "drawer")

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, (0.191, 0.205), jnp.pi / 8, offset=(0.0, 0.012))
        return Placement(bodies={"drawer_root": (pos, quat)})

    def success(self, variation):
        return JointMoved(self.joints, 0.15, index=variation)

    def expert(self, obs, variation):
        handles = jnp.stack([obs.pos(f"drawer_handle_{lv}") for lv in LEVELS])
        handle = handles[variation]
        quat = frame_quat(obs, "drawer_root", GRASP)
        out = in_frame(obs, "drawer_root", (0.0, 1.0, 0.0)) - obs.pos("drawer_root")
        # RLBench plans a collision-free path to the pre-grasp; our controller
        # moves in straight lines, so the expert first passes over the chest,
        # then descends in front of it and approaches.
        stand_off = handle + 0.18 * out
        over = stand_off.at[2].set(obs.pos("drawer_root")[2] + CHEST_TOP + 0.12)
        return key_actions([
            (over, quat, 1.0),  # above the chest's front
            (stand_off, quat, 1.0),  # stand-off in front of the handle
            (handle + 0.087 * out, quat, 1.0),  # pre-grasp in front of the handle
            (handle, quat, 0.0),  # at the handle, close the gripper
            (handle + 0.237 * out, quat, 0.0),  # pull straight out
        ])


TASK = OpenDrawer()
