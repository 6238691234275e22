"""Primitive pieces every builder uses: boxes (panels), discs and rods.

Collision geoms avoid cylinders (MJX-jax lacks box-cylinder contacts): round
parts get a cylinder for looks and an inscribed box for contact.
"""

from __future__ import annotations

import mujoco

from agnostos_mjx.sim.world import OBJECT_COLLISION, VISUAL_ONLY

G = mujoco.mjtGeom
WHITE = (0.85, 0.85, 0.85)
WOOD = (0.72, 0.62, 0.48)


def panel(body: mujoco.MjsBody, half, pos, rgba=WHITE, collide: bool = True, name: str = "",
          quat=(1.0, 0.0, 0.0, 0.0)) -> mujoco.MjsGeom:
    """A box; collides with the robot and other objects unless `collide` is False."""
    contype, conaffinity = OBJECT_COLLISION if collide else VISUAL_ONLY
    return body.add_geom(name=name, type=G.mjGEOM_BOX, size=list(half), pos=list(pos),
                         quat=list(quat), rgba=[*rgba, 1.0], contype=contype,
                         conaffinity=conaffinity, group=2 if collide else 1)


def disc(body: mujoco.MjsBody, radius: float, half_height: float, pos, rgba,
         name: str = "") -> mujoco.MjsGeom:
    """A visual-only cylinder (collision comes from an inscribed box)."""
    return body.add_geom(name=name, type=G.mjGEOM_CYLINDER, size=[radius, half_height, 0],
                         pos=list(pos), rgba=[*rgba, 1.0], contype=0, conaffinity=0, group=1)


def rod(body: mujoco.MjsBody, start, end, radius: float, rgba, collide: bool = False,
        name: str = "") -> mujoco.MjsGeom:
    contype, conaffinity = OBJECT_COLLISION if collide else VISUAL_ONLY
    return body.add_geom(name=name, type=G.mjGEOM_CAPSULE, fromto=[*start, *end],
                         size=[radius, 0, 0], rgba=[*rgba, 1.0], contype=contype,
                         conaffinity=conaffinity, group=1)
