"""put_rubbish_in_bin (unseen, Level 1): drop the paper ball into the bin, not a tomato."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco

from agnostos_mjx.tasks.base import Placement, Split, Task, in_frame, key_actions, place_root
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_body,
    grasp_site,
    pose_in_root,
    sensor_volume,
    yaw_of,
)
from agnostos_mjx.tasks.builders.household import open_container, placed, solid

GREY = (0.6, 0.6, 0.6)
PAPER = (1.0, 1.0, 1.0)
TOMATO = (0.85, 0.12, 0.05)
BIN_XY, BIN_INNER, BIN_HEIGHT = (0.087, -0.280), 0.094, 0.189
RUBBISH_HALF = (0.030, 0.030, 0.0175)
# Item spots in the root frame: the rubbish, tomato1, tomato2 (heights are each item's own).
SPOTS = ((0.086, 0.103), (0.121, 0.252), (0.098, -0.039))
TOMATO_RADIUS = 0.033
# The cylindrical volume (radius 0.07, 0.06 high from the bin floor) as a box.
SUCCESS_CENTER, SUCCESS_HALF = (*BIN_XY, 0.033), (0.07, 0.07, 0.03)
# Model bounding box of bin and items in the root frame: x[-0.015, 0.188], y[-0.382, 0.285].
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.102, 0.334), (0.087, -0.049)


class PutRubbishInBin(Task):
    name = "put_rubbish_in_bin"
    split = Split.LEVEL1
    objects = {"rubbish": "rubbish", "bin": "bin_center"}
    frames = ("bin_root", "success")
    graspables = ("rubbish",)
    graspable_radius = (0.02,)
    notes = (
        "Typo fixed: the fifth description 'chuck way any rubbish on the table rubbish' reads "
        "'chuck away any rubbish on the table'. The crumpled paper ball is a 6 x 6 x 3.5 cm box "
        "(RLBench's 9 cm mesh would not fit between the open fingers of a real grasp); the "
        "bin's cylindrical success volume (r = 0.07 m) is approximated by its 0.14 m square. "
        "The tomatoes are visual decoys, static and non-colliding, as in RLBench."
    )

    def descriptions(self, variation: int) -> list[str]:
        return ["put rubbish in bin", "drop the rubbish into the bin",
                "pick up the rubbish and leave it in the trash can",
                "throw away the trash, leaving any other objects alone",
                "chuck away any rubbish on the table"]

    def build(self, scene) -> None:
        root = scene.mocap("bin_root")
        open_container(root, "bin", (*BIN_XY, 0.0), BIN_INNER, BIN_HEIGHT, GREY)
        grasp_site(root, "bin_center", [*BIN_XY, BIN_HEIGHT / 2])
        sensor_volume(root, "success", SUCCESS_CENTER, SUCCESS_HALF)
        rubbish = free_body(scene, "rubbish")
        solid(rubbish, RUBBISH_HALF, (0, 0, 0), PAPER, 0.42)
        for k, (dx, dy, r) in enumerate(((0.012, 0.01, 0.02), (-0.014, -0.008, 0.018))):
            rubbish.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[r, 0, 0],
                             pos=[dx, dy, 0.006], rgba=[*PAPER, 1.0], contype=0, conaffinity=0,
                             group=1, name=f"rubbish_crumple{k}")
        for k in (1, 2):
            tomato = scene.mocap(f"tomato{k}")
            tomato.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[TOMATO_RADIUS, 0, 0],
                            pos=[0, 0, TOMATO_RADIUS], rgba=[*TOMATO, 1.0], contype=0,
                            conaffinity=0, group=1, name=f"tomato{k}_visual")
            tomato.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[0.004, 0.006, 0],
                            pos=[0, 0, 2 * TOMATO_RADIUS + 0.004], rgba=[0.1, 0.5, 0.1, 1.0],
                            contype=0, conaffinity=0, group=1)

    def sample(self, key, variation) -> Placement:
        k_root, k_swap = jax.random.split(key)
        pos, quat = place_root(k_root, FOOTPRINT_HALF, jnp.pi, offset=FOOTPRINT_CENTER)
        # RLBench's randint(3): 0 swaps the rubbish with tomato2, 2 with tomato1, 1 keeps it.
        spots = jnp.asarray(SPOTS)
        swap = jax.random.randint(k_swap, (), 0, 3)
        partner = jnp.where(swap == 0, 2, jnp.where(swap == 2, 1, 0))
        order = jnp.arange(3).at[0].set(partner).at[partner].set(0)
        xy = spots[order]
        heights = (RUBBISH_HALF[2], 0.0, 0.0)
        bodies = {"bin_root": (pos, quat)}
        for k, name in enumerate(("rubbish", "tomato1", "tomato2")):
            bodies[name] = pose_in_root(pos, quat, jnp.array([xy[k, 0], xy[k, 1], heights[k]]))
        return Placement(bodies=bodies)

    def success(self, variation):
        return placed("rubbish", "success", SUCCESS_HALF, radius=0.01, released=False)

    def expert(self, obs, variation):
        rubbish = obs.pos("rubbish")
        grasp = down_grasp(yaw_of(obs.quat("rubbish")))
        above_bin = in_frame(obs, "bin_root", (*BIN_XY, 0.253))
        return key_actions([
            (rubbish + jnp.array([0.0, 0.0, 0.08]), grasp, 1.0),
            (rubbish + jnp.array([0.0, 0.0, 0.003]), grasp, 0.0),
            (rubbish + jnp.array([0.0, 0.0, 0.234]), grasp, 0.0),
            (above_bin, down_grasp(yaw_of(obs.quat("bin_root"))), 1.0),
        ])


TASK = PutRubbishInBin()
