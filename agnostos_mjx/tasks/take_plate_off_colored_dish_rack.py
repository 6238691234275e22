"""take_plate_off_colored_dish_rack (unseen, Level 2): lift the plate out of
the black, red or purple section of the rack and put it down on the cyan block."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import AnyOf, Detected, NothingGrasped, all_of
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
from agnostos_mjx.tasks.builders.kitchen import dish_rack, plate
from agnostos_mjx.tasks.builders.primitives import panel

SECTIONS = ("black", "red", "purple")
PILLAR_COLORS = ((0.0, 0.0, 0.0),) * 2 + ((1.0, 0.0, 0.0),) * 2 + ((0.5, 0.0, 1.0),) * 2
# RLBench's success_pos<i>: where the plate stands in each section (z kept).
PLATE_XY = ((0.002, -0.103), (0.002, 0.002), (0.002, 0.097))
PLATE_RADIUS, RACK_TOP = 0.1, 0.015
PLATE_Z = RACK_TOP + PLATE_RADIUS
GRASP_HEIGHT = 0.071  # the grasp point above the plate's centre (RLBench's waypoint1)
TARGET_POS, TARGET_HALF = (0.07, -0.312, 0.05), 0.05
SOURCE_POS, SOURCE_HALF = (0.0, 0.0, 0.06), (0.1, 0.11, 0.05)
GOAL_POS, GOAL_HALF = (0.076, -0.309, 0.11), (0.025, 0.025, 0.025)
# Gripper pointing down, fingers across the plate (along the root's y).
# Footprint in the root frame: rack, plate and cyan block, x[-0.1, 0.12] y[-0.362, 0.15].
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.11, 0.256), (0.01, -0.106)


class TakePlateOffColoredDishRack(Task):
    name = "take_plate_off_colored_dish_rack"
    split = Split.LEVEL2
    num_variations = 3
    objects = {"plate": "plate", "dish rack": "dish_rack", "plate target": "plate_target"}
    probes = tuple(f"plate_probe{i}" for i in range(5))
    frames = ("success_source", "success_target", "take_plate_off_colored_dish_rack", *probes)
    graspables = ("plate",)
    grasp_points = ("plate_grasp_point",)
    graspable_radius = (0.01,)
    notes = ("The plate's shape is tested against the sensor volumes "
             "through five probe points (centre and four rim points, grown by its half "
             "thickness). RLBench lowers the plate into the cyan block with collisions ignored "
             "and lets it lean there; our expert lowers it until it stands on the block's top, "
             "centred over the target volume, and lets go.")

    def descriptions(self, variation: int) -> list[str]:
        c = SECTIONS[variation]
        return [f"take plate off the {c} colored rack", f"remove the dish from the {c} rack",
                f"find the dish placed between the {c} spokes of the dish rack and drop it on "
                "the table",
                f"grasp the plate from the {c} part of the dish rack, lift it up off of the rack, "
                "and leave it on the table top",
                f"move the plate from the {c} rack to the table's surface",
                f"lift the plate up off the {c} colored rack and drop it onto the table from a "
                "considerable height"]

    def build(self, scene) -> None:
        root = scene.mocap("take_plate_off_colored_dish_rack")
        rack = root.add_body(name="dish_rack")
        dish_rack(rack, "dish_rack", pillar_colors=PILLAR_COLORS,
                  base_half=(0.08, 0.15, RACK_TOP / 2))
        plate(scene, "plate", radius=PLATE_RADIUS, grasp_height=GRASP_HEIGHT)
        target = root.add_body(name="plate_target", pos=list(TARGET_POS))
        panel(target, (TARGET_HALF,) * 3, (0, 0, 0), (0.0, 0.85, 1.0))
        sensor_volume(root, "success_source", SOURCE_POS, SOURCE_HALF)
        sensor_volume(root, "success_target", GOAL_POS, GOAL_HALF)

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, FOOTPRINT_HALF, jnp.pi, offset=FOOTPRINT_CENTER)
        xy = jnp.asarray(PLATE_XY)[variation]
        local = jnp.array([xy[0], xy[1], PLATE_Z])
        return Placement(bodies={"take_plate_off_colored_dish_rack": (pos, quat),
                                 "plate": pose_in_root(pos, quat, local)})

    def success(self, variation):
        """Off the rack, on the block, released (RLBench's three conditions)."""
        off = [Detected(p, "success_source", SOURCE_HALF, radius=0.0125, negated=True)
               for p in self.probes]
        on = AnyOf(tuple(Detected(p, "success_target", GOAL_HALF, radius=0.0125)
                         for p in self.probes))
        return all_of([*off, on, NothingGrasped()])

    def expert(self, obs, variation):
        root = "take_plate_off_colored_dish_rack"
        quat = frame_quat(obs, root, DOWN)
        grasp = obs.pos("plate_grasp_point")
        lift = obs.pos(root)[2] + 0.335  # RLBench's waypoint2 height
        # Over the target the plate hangs with its centre above the volume's centre.
        over = in_frame(obs, root, (GOAL_POS[0], GOAL_POS[1], 0.335))
        stand = obs.pos(root)[2] + 2 * TARGET_HALF + PLATE_RADIUS + GRASP_HEIGHT + 0.008
        return key_actions([
            (grasp + jnp.array([0.0, 0.0, 0.068]), quat, 1.0),  # above the top edge
            (grasp, quat, 0.0),  # grip the top edge
            (grasp.at[2].set(lift), quat, 0.0),  # lift out of the rack
            (over, quat, 0.0),  # over the cyan block
            (over.at[2].set(stand), quat, 1.0),  # lower onto the block's top, let go
        ])


TASK = TakePlateOffColoredDishRack()
