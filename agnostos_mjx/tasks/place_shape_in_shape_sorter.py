"""place_shape_in_shape_sorter (seen): drop one of five shapes through its hole in the sorter."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, Select
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
    natural_yaw,
    nearest_yaw,
    sensor_volume,
    spawn_many_on_root_plane,
    yaw_of,
)
from agnostos_mjx.tasks.builders.furniture import shape_sorter, sorter_shape

ROOT = "shape_sorter_root"
SORTER_XY = (0.0, -0.15)  # root frame, as in RLBench's (x2 scaled) PerAct model
LID_TOP = 0.143


class Shape(NamedTuple):
    name: str  # body name
    words: str  # as the language says it
    rgba: tuple[float, float, float]
    # Centre relative to the sorter and half sizes: the shape's footprint + 8 mm.
    hole: tuple[float, float, float, float]
    period: float  # yaw symmetry the hole needs (0: any yaw passes)
    half_height: float  # the builder's; centre height when lying on the table


SHAPES = (
    Shape("cube", "cube", (0.0, 0.85, 1.0), (-0.049, 0.049, 0.029, 0.029), jnp.pi / 2, 0.021),
    Shape("cylinder", "cylinder", (1.0, 0.41, 1.0), (-0.050, -0.048, 0.031, 0.031), 0.0,
          0.021),
    Shape("triangular_prism", "triangular prism", (1.0, 0.7, 0.7),
          (0.050, 0.055, 0.031, 0.028), jnp.pi, 0.0195),
    Shape("star", "star", (1.0, 0.99, 0.0), (0.0, 0.001, 0.028, 0.028), 0.0, 0.015),
    Shape("moon", "moon", (0.62, 0.99, 0.60), (0.059, -0.052, 0.030, 0.024), jnp.pi, 0.012),
)
NAMES = tuple(s.name for s in SHAPES)
# RLBench's `boundary` spawn plane (0.421 x 0.301 m at root (0, 0.125)).
BOUNDARY_CENTER, BOUNDARY_HALF = (0.0, 0.125), (0.2105, 0.1505)
FOOTPRINT = (0.03, 0.03)  # shapes' half footprint for spawn overlap tests
VOLUME_HALF = (0.08, 0.08, 0.05)  # RLBench's `success`: 0.16 x 0.16, 0.10 m high
CARRY = 0.25  # carrying height above the table, clear of the 0.143 m high sorter

FINGER_REACH = 0.05  # open fingers' pads from the tip, along the finger axis
PAD_CLEARANCE = 0.045  # pad centre to a neighbour's centre
HAND_REACH = (0.05, 0.075, 0.1)  # points of the hand along the finger axis
SORTER_KEEPOUT = 0.089 + 0.03  # the sorter's half size plus half the hand's width


def _grasp_yaw(pos, yaw, period: float, others, sorter, sorter_yaw):
    """A grasp yaw whose open pads miss the neighbours and whose hand misses
    the sorter, least wrist twist first.  Candidates are quarter turns for
    shapes with a hole orientation (the fingers may hold them either way;
    the drop turns them by the same relative yaw), eighth turns for shapes
    any yaw suits.  If none is clear, the one with the most pad clearance."""
    base = nearest_yaw(yaw, natural_yaw(pos), jnp.pi / 2 if period else 0.0)
    step, ks = (jnp.pi / 2, (0, -1, 1)) if period else (jnp.pi / 4, (0, -1, 1, -2, 2))
    candidates = jnp.stack([base + k * step for k in ks])
    finger = jnp.stack([-jnp.sin(candidates), jnp.cos(candidates)], -1)  # (C, 2)
    pads = pos[:2] + FINGER_REACH * jnp.stack([finger, -finger], 1)  # (C, 2, 2)
    gap = jnp.linalg.norm(pads[:, :, None] - others[None, None], axis=-1).min(axis=(1, 2))
    reach = jnp.asarray(HAND_REACH + tuple(-r for r in HAND_REACH))
    hand = pos[:2] + reach[None, :, None] * finger[:, None]  # (C, R, 2)
    c, s = jnp.cos(sorter_yaw), jnp.sin(sorter_yaw)
    d = hand - sorter[:2]
    local = jnp.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)
    hits_sorter = jnp.all(jnp.abs(local) < SORTER_KEEPOUT, -1).any(-1)
    clear = (gap > PAD_CLEARANCE) & ~hits_sorter
    best = jnp.where(clear.any(), jnp.argmax(clear), jnp.argmax(gap - hits_sorter))
    return candidates[best]


class PlaceShapeInShapeSorter(Task):
    name = "place_shape_in_shape_sorter"
    split = Split.SEEN
    num_variations = 5
    objects = {"cube": "cube", "shape sorter": "shape_sorter"}
    frames = (ROOT, "success") + NAMES[1:]
    graspables = NAMES
    graspable_radius = (0.012,) * 5
    notes = ("Shapes are built from boxes (the prism from three slabs, the cylinder as an "
             "octagonal prism; the star and the moon collide through a small box, like "
             "RLBench's proxies, and show rays and a crescent of boxes); the lid is a "
             "box plate with a rectangular hole per shape, at RLBench's drop points. The shapes "
             "weigh 0.1 kg each instead of RLBench's 0.07-6.6 kg: CoppeliaSim's attach makes "
             "a carried object kinematic, our weld makes the arm carry its mass. The sorter "
             "stands on the table (RLBench's reaches 4.6 cm below it). The expert picks a "
             "grasp yaw whose open fingers miss the neighbouring shapes and whose hand misses "
             "the sorter (RLBench's planner avoids them), carries the shape at 0.25 m and "
             "turns it to match its hole (cube, prism, moon).")

    def descriptions(self, variation: int) -> list[str]:
        s = SHAPES[variation].words
        return [f"put the {s} in the shape sorter", f"pick up the {s} and put it in the sorter",
                f"place the {s} into its slot in the shape sorter",
                f"slot the {s} into the shape sorter"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        holder = root.add_body(name="shape_sorter_frame", pos=[*SORTER_XY, 0.0])
        shape_sorter(holder, "shape_sorter", [s.hole for s in SHAPES], height=LID_TOP)
        sensor_volume(holder, "success", (0.0, 0.0, VOLUME_HALF[2] - 0.001), VOLUME_HALF)
        for s in SHAPES:
            assert sorter_shape(scene, s.name, s.name, s.rgba) == s.half_height

    def sample(self, key, variation) -> Placement:
        k_root, k_shapes = jax.random.split(key)
        pos, quat = place_root(k_root, (0.211, 0.263), jnp.pi, offset=(0.0, 0.0125))
        shapes = spawn_many_on_root_plane(k_shapes, (pos, quat), [FOOTPRINT] * len(SHAPES),
                                          BOUNDARY_CENTER, BOUNDARY_HALF,
                                          heights=[s.half_height for s in SHAPES],
                                          min_distance=0.05)
        return Placement(bodies={ROOT: (pos, quat), **dict(zip(NAMES, shapes))})

    def success(self, variation):
        return Select(tuple(Detected(n, "success", VOLUME_HALF, radius=0.01) for n in NAMES),
                      variation)

    def expert(self, obs, variation):
        shape = jnp.stack([obs.pos(n) for n in NAMES])[variation]
        q = jnp.stack([obs.quat(n) for n in NAMES])[variation]
        shape_yaw, root_yaw = yaw_of(q), yaw_of(obs.quat(ROOT))  # shapes lie flat
        holes = jnp.asarray([[SORTER_XY[0] + s.hole[0], SORTER_XY[1] + s.hole[1]]
                             for s in SHAPES])
        half = jnp.asarray([s.half_height for s in SHAPES])[variation]
        hole = in_frame(obs, ROOT, jnp.concatenate([holes[variation], jnp.zeros(1)]))
        sorter = obs.pos("shape_sorter")
        others = jnp.stack([obs.pos(n)[:2] for n in NAMES])
        others = jnp.where((jnp.arange(len(NAMES)) == variation)[:, None], 1e3, others)
        # Grasp with the least wrist twist while the open fingers miss the
        # neighbours (RLBench spawns them 5 cm apart) and the hand misses the
        # sorter, then turn the shape to line up with its hole (the grasp
        # keeps the relative yaw).
        grasp_yaw, drop_yaw = natural_yaw(shape), natural_yaw(hole)
        for v, s in enumerate(SHAPES):
            g = _grasp_yaw(shape, shape_yaw, s.period, others, sorter, root_yaw)
            d = nearest_yaw(g + root_yaw - shape_yaw, natural_yaw(hole), s.period)
            grasp_yaw = jnp.where(variation == v, g, grasp_yaw)
            drop_yaw = jnp.where(variation == v, d, drop_yaw)
        table = obs.pos(ROOT)[2]

        def at(p, z):  # p at height z above the table
            return p.at[2].set(table + z)

        grip, drop = down_grasp(grasp_yaw, wrap=False), down_grasp(drop_yaw, wrap=False)
        return key_actions([
            (shape + jnp.array([0.0, 0.0, 0.075]), grip, 1.0),  # above (wp0)
            (shape, grip, 0.0),  # grasp (wp1)
            (at(shape, CARRY), grip, 0.0),  # lift (wp2)
            (at(hole, CARRY), drop, 0.0),  # above the hole (wp3)
            (at(hole, LID_TOP + half + 0.012), drop, 1.0),  # at the hole, drop (wp4)
        ])


TASK = PlaceShapeInShapeSorter()
