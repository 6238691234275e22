"""put_groceries_in_cupboard (seen): pick one of nine groceries and put it in the cupboard."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from agnostos_mjx.conditions import Detected, NothingGrasped, Select, all_of
from agnostos_mjx.tasks.base import (
    TABLE_Z,
    Placement,
    Split,
    Task,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    grasp_site,
    natural_yaw,
    nearest_yaw,
    sensor_volume,
    spawn_many_on_root_plane,
    yaw_of,
)
from agnostos_mjx.tasks.builders.furniture import cupboard, grocery


class Grocery(NamedTuple):
    name: str  # body name (RLBench's, spaces as underscores)
    words: str  # as the language says it
    size: tuple[float, float, float]  # full size; cans: (diameter, diameter, height)
    rgba: tuple[float, float, float]
    round_: bool = False


GROCERIES = (
    Grocery("crackers", "crackers", (0.075, 0.03, 0.10), (0.85, 0.2, 0.1)),
    Grocery("chocolate_jello", "chocolate jello", (0.05, 0.035, 0.045), (0.45, 0.25, 0.1)),
    Grocery("strawberry_jello", "strawberry jello", (0.055, 0.04, 0.045), (0.95, 0.4, 0.5)),
    Grocery("soup", "soup", (0.05, 0.05, 0.07), (0.8, 0.1, 0.1), True),
    Grocery("tuna", "tuna", (0.06, 0.06, 0.035), (0.2, 0.4, 0.7), True),
    Grocery("spam", "spam", (0.06, 0.035, 0.05), (0.2, 0.3, 0.6)),
    Grocery("coffee", "coffee", (0.06, 0.06, 0.08), (0.15, 0.2, 0.4), True),
    Grocery("mustard", "mustard", (0.055, 0.035, 0.10), (1.0, 0.85, 0.1)),
    Grocery("sugar", "sugar", (0.06, 0.03, 0.09), (0.95, 0.95, 0.8)),
)
NAMES = tuple(g.name for g in GROCERIES)
ROOT = "cupboard_root"  # RLBench's `boundary_root` proxy
FLOOR, CLEAR = 0.015, 0.2375  # the cupboard builder's bottom compartment (floor, clear height)
DEPTH, WIDTH = 0.20, 0.36
VOLUME_HALF = (DEPTH / 2 - 0.015, WIDTH / 2 - 0.015, CLEAR / 2)
GRASP_BELOW_TOP = 0.02  # the tip 2 cm below the top: the pads hold the top 6 cm
# Groceries spawn in front of the opening (root frame), 0.14 m clear of it.
SPAWN_CENTER, SPAWN_HALF = (-0.31, 0.0), (0.17, 0.30)
# Root footprint for placement: the cupboard and the near part of the spawn area
# (the whole scene does not fit our inferred workspace; see notes).
ROOT_CENTER, ROOT_HALF = (-0.08, 0.0), (0.20, 0.25)


def _grasp_height(g: Grocery) -> float:
    """Grasp point above the item's centre: near its top, never below the centre."""
    return max(g.size[2] / 2 - GRASP_BELOW_TOP, 0.0)


class PutGroceriesInCupboard(Task):
    name = "put_groceries_in_cupboard"
    split = Split.SEEN
    num_variations = 9
    objects = {"cupboard": "cupboard", "cracker": "crackers"}
    frames = (ROOT, "success") + NAMES[1:]
    graspables = NAMES
    grasp_points = tuple(f"{n}_grasp_point" for n in NAMES)
    graspable_radius = (0.012,) * 9
    notes = ("RLBench's scene model is not documented: this layout is designed (unverified). A "
             "white open cupboard (0.20 x 0.36 x 0.50 m, open towards the root's -x) with a "
             "bottom compartment (the `success` volume) and a shelf; nine upright groceries "
             "built from boxes and octagonal cans in YCB-like colours, about half YCB size. "
             "RLBench's code samples the groceries over the whole `workspace` (min distance "
             "0.1 m, any yaw); we sample them (same distance, any yaw) on a 0.34 x 0.60 m area "
             "in front of the opening, since a straight-line controller cannot route around "
             "the cupboard. The root is placed with yaw +-1 rad using a footprint of the "
             "cupboard and the near part of that area; unreachable scenes are resampled. "
             "The expert grasps from above and slides the item into "
             "the bottom compartment at its floor height; only the hand and fingers collide "
             "(the arm is visual), so the forearm may show through the shelf.")

    def descriptions(self, variation: int) -> list[str]:
        g = GROCERIES[variation].words
        return [f"put the {g} in the cupboard", f"pick up the {g} and place it in the cupboard",
                f"move the {g} to the bottom shelf", f"put away the {g} in the cupboard"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        floor, clear = cupboard(root, "cupboard", depth=DEPTH, width=WIDTH)
        assert (floor, round(clear, 6)) == (FLOOR, CLEAR)
        sensor_volume(root, "success", (DEPTH / 2, 0.0, FLOOR + CLEAR / 2), VOLUME_HALF)
        for g in GROCERIES:
            body = grocery(scene, g.name, g.size, g.rgba, g.round_)
            grasp_site(body, f"{g.name}_grasp_point", (0.0, 0.0, _grasp_height(g)))

    def sample(self, key, variation) -> Placement:
        k_root, k_items = jax.random.split(key)
        pos, quat = place_root(k_root, ROOT_HALF, 1.0, offset=ROOT_CENTER)
        items = spawn_many_on_root_plane(
            k_items, (pos, quat), [(g.size[0] / 2, g.size[1] / 2) for g in GROCERIES],
            SPAWN_CENTER, SPAWN_HALF, heights=[g.size[2] / 2 for g in GROCERIES],
            min_distance=0.1, tries=256)
        return Placement(bodies={ROOT: (pos, quat), **dict(zip(NAMES, items))})

    def success(self, variation):
        inside = tuple(Detected(n, "success", VOLUME_HALF, radius=0.01) for n in NAMES)
        return all_of([Select(inside, variation), NothingGrasped()])

    def expert(self, obs, variation):
        grasp = jnp.stack([obs.pos(f"{n}_grasp_point") for n in NAMES])[variation]
        q = jnp.stack([obs.quat(n) for n in NAMES])[variation]
        # Boxes are gripped across their thin side (y), a half turn being the
        # same grasp; cans in any yaw.  Choose the least wrist twist.
        boxed = ~jnp.asarray([g.round_ for g in GROCERIES])[variation]
        grasp_yaw = jnp.where(boxed, nearest_yaw(yaw_of(q), natural_yaw(grasp), jnp.pi),
                              natural_yaw(grasp))
        # Height of the grasp point above the item's bottom.
        hold = jnp.asarray([g.size[2] / 2 + _grasp_height(g) for g in GROCERIES])[variation]
        inside = in_frame(obs, ROOT, (DEPTH / 2 - 0.01, 0.0, FLOOR + hold + 0.01))
        front = in_frame(obs, ROOT, (-0.06, 0.0, FLOOR + hold + 0.01))
        # Fingers across the opening (along the root's y), hand clear of the sides.
        put_yaw = nearest_yaw(yaw_of(obs.quat(ROOT)), natural_yaw(inside), jnp.pi)
        lift = TABLE_Z + 0.13 + hold  # the item's bottom above the other groceries
        grip, put = down_grasp(grasp_yaw, wrap=False), down_grasp(put_yaw, wrap=False)
        return key_actions([
            (grasp + jnp.array([0.0, 0.0, 0.08]), grip, 1.0),  # above the item
            (grasp, grip, 0.0),  # grasp (wp1 = the grasp point)
            (grasp.at[2].set(lift), grip, 0.0),  # lift
            (front.at[2].set(lift), put, 0.0),  # in front of the cupboard
            (front, put, 0.0),  # down to the compartment's floor height
            (inside, put, 1.0),  # slide in, release
            (front, put, 1.0),  # retreat
        ])


TASK = PutGroceriesInCupboard()
