"""Reusable scene pieces built from primitive geoms.  Tasks compose these;
none copies another.  One module per family of pieces (primitives,
articulated parts, ...); `common` holds the small helpers every family and
task shares (free bodies, ...); this package re-exports the common ones.

Collision geoms avoid cylinders (MJX-jax lacks box-cylinder contacts): round
parts get a cylinder for looks and an inscribed box for contact.
"""

from agnostos_mjx.tasks.builders.articulated import drawer_chest, hinged_door, push_button
from agnostos_mjx.tasks.builders.common import (
    DOWN,
    down_grasp,
    free_body,
    free_box,
    grasp_site,
    natural_yaw,
    nearest_yaw,
    pose_in_root,
    sensor_volume,
    spawn_many_on_root_plane,
    spawn_on_root_plane,
    square_yaw,
    yaw_of,
)
from agnostos_mjx.tasks.builders.primitives import WHITE, WOOD, disc, panel, rod

__all__ = ["DOWN", "WHITE", "WOOD", "disc", "down_grasp", "drawer_chest", "free_body", "free_box",
           "grasp_site", "hinged_door", "natural_yaw", "nearest_yaw", "panel", "pose_in_root",
           "push_button", "rod", "sensor_volume", "spawn_many_on_root_plane", "spawn_on_root_plane",
           "square_yaw", "yaw_of"]
