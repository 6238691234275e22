"""put_groceries_in_cupboard (seen): pick one of nine groceries and put it in the cupboard."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, NothingGrasped, Select, all_of
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
# The hand seen from above at a top-down grasp (the panda model's collision boxes, in the
# tip frame): the palm, 0.19 m long across the fingers' closing direction and 0.05 m
# along the heading, from 4.5 cm above the tip up; the open finger pads, 0.116 x 0.021 m,
# down to the tip's height.  A grocery taller than the palm's underside must stay clear of
# the palm's footprint, any grocery clear of the pads'.
PALM_HALF, PALM_ABOVE_TIP = (0.025, 0.095), 0.045
PADS_HALF = (0.0105, 0.058)
OPENING = 0.065  # widest side the open fingers (0.08 m apart) close on with some play
CLEARANCE = 0.01  # m: candidates at least this clear of every neighbour count as equal
CAN_YAWS = 12  # grasp headings tried for a can over a half turn (the hand's symmetry)
PRE_GRASP = 0.035  # m, tip above the grasp point before the last straight descent


def _grasp_height(g: Grocery) -> float:
    """Grasp point above the item's centre: near its top, never below the centre."""
    return max(g.size[2] / 2 - GRASP_BELOW_TOP, 0.0)


def _radius(g: Grocery) -> float:
    """Radius of a disc covering the item's footprint (a box's corners, a can's octagon)."""
    if g.round_:
        return g.size[0] / 2 / math.cos(math.pi / 8)
    return math.hypot(g.size[0] / 2, g.size[1] / 2)


def _grasp_yaw_candidates(g_round, g_fits, item_yaw, natural):
    """Gripper headings the chosen item can be grasped with (CAN_YAWS,), and which are
    valid: a box across its thin side, or across its long side where that fits between
    the open fingers; a can at any heading.  Each is the heading equivalent under the
    hand's half-turn symmetry nearest the natural yaw (least wrist twist)."""
    k = jnp.arange(CAN_YAWS)
    can = natural + (k - CAN_YAWS // 2) * (jnp.pi / CAN_YAWS)
    across = nearest_yaw(item_yaw, natural, jnp.pi)
    along = nearest_yaw(item_yaw + jnp.pi / 2, natural, jnp.pi)
    box = jnp.where(k == 0, across, along)
    return (jnp.where(g_round, can, box),
            jnp.where(g_round, True, (k == 0) | ((k == 1) & g_fits)))


def _hand_clearance(yaw, grasp, tip_above_table, others_xy, others_top, others_radius):
    """Smallest gap (m, negative: overlap) between the hand's footprint at a top-down
    grasp with heading `yaw` at `grasp` and the other items' footprint discs: the palm's
    for items reaching above its underside, the finger pads' for the others."""
    d = others_xy - grasp[:2]
    a = jnp.abs(d[:, 0] * jnp.cos(yaw) + d[:, 1] * jnp.sin(yaw))  # along the heading
    b = jnp.abs(-d[:, 0] * jnp.sin(yaw) + d[:, 1] * jnp.cos(yaw))  # along the closing
    tall = others_top > tip_above_table + PALM_ABOVE_TIP
    hx = jnp.where(tall, PALM_HALF[0], PADS_HALF[0])
    hy = jnp.where(tall, PALM_HALF[1], PADS_HALF[1])
    gap = jnp.hypot(jnp.maximum(a - hx, 0.0), jnp.maximum(b - hy, 0.0)) - others_radius
    return gap.min()


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
             "The expert grasps from above (at the heading, among the item's grasp "
             "symmetries, that keeps the 0.19 m palm clear of taller neighbours; via a "
             "pre-grasp just above the item, so the wrist's lag near the folded-elbow "
             "limit settles before the fingers reach it) and slides the item into "
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
        # Height of the grasp point above the item's bottom.
        hold = jnp.asarray([g.size[2] / 2 + _grasp_height(g) for g in GROCERIES])[variation]
        # Boxes are gripped across their thin side (y), or across the long side where it
        # fits, a half turn being the same grasp; cans at any heading.  The palm is 0.19 m
        # long, so next to a taller neighbour (items spawn 0.1 m apart) some headings put
        # it onto that neighbour while the tip is still above the grasp (RLBench's planner
        # would reject such a grasp); take the heading clearest of the others, among those
        # clear by CLEARANCE the one with the least wrist twist.
        pos = jnp.stack([obs.pos(n) for n in NAMES])
        top = pos[:, 2] + jnp.asarray([g.size[2] / 2 for g in GROCERIES]) - TABLE_Z
        radius = jnp.asarray([_radius(g) for g in GROCERIES])
        others = jnp.arange(len(NAMES)) != variation
        natural = natural_yaw(grasp)
        yaws, ok = _grasp_yaw_candidates(
            jnp.asarray([g.round_ for g in GROCERIES])[variation],
            jnp.asarray([g.size[0] <= OPENING for g in GROCERIES])[variation],
            yaw_of(q), natural)
        clear = jax.vmap(lambda y: _hand_clearance(
            y, grasp, grasp[2] - TABLE_Z, pos[:, :2], jnp.where(others, top, -1.0),
            jnp.where(others, radius, -1.0)))(yaws)
        twist = jnp.abs(yaws - natural)
        score = jnp.where(ok, jnp.minimum(clear, CLEARANCE) - 1e-3 * twist, -jnp.inf)
        grasp_yaw = yaws[jnp.argmax(score)]
        inside = in_frame(obs, ROOT, (DEPTH / 2 - 0.01, 0.0, FLOOR + hold + 0.01))
        front = in_frame(obs, ROOT, (-0.06, 0.0, FLOOR + hold + 0.01))
        # Fingers across the opening (along the root's y), hand clear of the sides.
        put_yaw = nearest_yaw(yaw_of(obs.quat(ROOT)), natural_yaw(inside), jnp.pi)
        lift = TABLE_Z + 0.13 + hold  # the item's bottom above the other groceries
        grip, put = down_grasp(grasp_yaw, wrap=False), down_grasp(put_yaw, wrap=False)
        return key_actions([
            (grasp + jnp.array([0.0, 0.0, 0.08]), grip, 1.0),  # above the item
            # Pre-grasp, the pads (0.9 cm below the tip) just above the item's top.  Close
            # to the robot's base the elbow folds to its limit and an 8 cm descent turns the
            # wrist by up to 1.5 rad, faster than its damped joints follow: the hand trails
            # the straight line by 2-3 cm and a pad lands on the item.  Stopping above the
            # item lets that lag settle; the last 3.5 cm turn the wrist little.
            (grasp + jnp.array([0.0, 0.0, PRE_GRASP]), grip, 1.0),
            (grasp, grip, 0.0),  # grasp (RLBench's waypoint1 = the grasp point)
            (grasp.at[2].set(lift), grip, 0.0),  # lift
            (front.at[2].set(lift), put, 0.0),  # in front of the cupboard
            (front, put, 0.0),  # down to the compartment's floor height
            (inside, put, 1.0),  # slide in, release
            (front, put, 1.0),  # retreat
        ])


TASK = PutGroceriesInCupboard()
