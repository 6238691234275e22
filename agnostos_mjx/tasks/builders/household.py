"""Household pieces for the pick-and-place tasks: solid parts with explicit
masses, open containers (bins, umbrella stands, shelves), and their success
test.  Free bodies, sensor volumes, root-frame poses, grasps and spawning
come from `common`.
"""

from __future__ import annotations

import mujoco
import numpy as np

from agnostos_mjx.sim.conditions import Condition, Detected, NothingGrasped, all_of
from agnostos_mjx.sim.math3d import yaw_quat
from agnostos_mjx.sim.world import SceneBuilder
from agnostos_mjx.tasks.builders.common import IDENTITY, grasp_site
from agnostos_mjx.tasks.builders.primitives import panel


# ---- scene pieces -------------------------------------------------------------------------
def held_by_weld_only(scene: SceneBuilder, body: str) -> None:
    """Let the gripper pass through a graspable, so only the grasp weld holds
    it (RLBench parents a grasped object to the gripper).  For long, thin
    objects held near one end: pad friction would otherwise keep them tilted
    against the weld after a jolt."""
    for part in ("hand", "left_finger", "right_finger"):
        scene.exclude(part, body)


def solid(body: mujoco.MjsBody, half, pos, rgba, mass: float, name: str = "",
          quat=IDENTITY) -> mujoco.MjsGeom:
    """A colliding box with an explicit mass (default densities make toy-like
    objects far too heavy or light)."""
    geom = panel(body, half, pos, rgba, name=name, quat=quat)
    geom.mass = mass
    return geom


def open_container(body: mujoco.MjsBody, name: str, pos, inner_radius: float, height: float,
                   rgba, sides: int = 4, wall: float = 0.006,
                   floor: float = 0.006) -> list[mujoco.MjsGeom]:
    """An open-top container (bin, umbrella stand) of `sides` flat walls
    around a regular polygon of inscribed radius `inner_radius`, standing on
    its floor at `pos`; with `floor=0` a bare tube (a toilet roll).  Returns
    the geoms (to set masses on a free body)."""
    x, y, z = pos
    half_side = (inner_radius + wall) * np.tan(np.pi / sides) + 1e-4
    geoms = []
    if floor > 0:
        geoms.append(panel(body, (inner_radius + wall, inner_radius + wall, floor / 2),
                           (x, y, z + floor / 2), rgba, name=f"{name}_floor"))
    for k in range(sides):
        angle = 2 * np.pi * k / sides
        r = inner_radius + wall / 2
        quat = np.asarray(yaw_quat(np.float64(angle)))
        geoms.append(panel(body, (wall / 2, half_side, height / 2),
                           (x + r * np.cos(angle), y + r * np.sin(angle), z + height / 2), rgba,
                           name=f"{name}_wall{k}", quat=tuple(quat)))
    return geoms


def shelf_unit(body: mujoco.MjsBody, name: str, pos, half, shelf_top: float, height: float,
               rgba, board: float = 0.012, wall: float = 0.008) -> None:
    """A shelf unit open at the front (+y) and, above its shelf board (top
    face at `shelf_top`), open at the top: sides, back, bottom and shelf
    boards.  Adds a site `name` at the middle of the shelf board."""
    x, y, z = pos
    hx, hy = half
    panel(body, (hx, hy, board / 2), (x, y, z + board / 2), rgba, name=f"{name}_bottom")
    panel(body, (hx - wall, hy, board / 2), (x, y, z + shelf_top - board / 2), rgba,
          name=f"{name}_shelf")
    for side in (-1, 1):
        panel(body, (wall / 2, hy, height / 2), (x + side * (hx - wall / 2), y, z + height / 2),
              rgba, name=f"{name}_side{(side + 1) // 2}")
    panel(body, (hx, wall / 2, height / 2), (x, y - hy + wall / 2, z + height / 2), rgba,
          name=f"{name}_back")
    grasp_site(body, name, (x, y, z + shelf_top))


# ---- success ------------------------------------------------------------------------------
def placed(obj: str, vol: str, half, radius: float = 0.0, released: bool = True,
           ordered: bool = False) -> Condition:
    """RLBench's DetectedCondition(obj, volume), with NothingGrasped when
    `released` (both at once, or the detection first when `ordered`)."""
    detected = Detected(obj, vol, tuple(half), radius=radius)
    if not released:
        return detected
    return all_of([detected, NothingGrasped()], ordered=ordered)
