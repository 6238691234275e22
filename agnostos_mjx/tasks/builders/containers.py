"""Containers and what goes in or on them: jars and lids, nesting cups, bulb
holders, light bulbs and a lamp socket, a safe with shelves, mugs and a mug
tree.  Plus what only the container tasks share: a root placement for a yaw
range off zero, a success test whose target object or volume the variation
picks, and a distractor colour draw (spawning, grasp sites, sensor volumes
and down grasps: see `common`).

Conventions: a piece's body origin is the centre of its bounding box (as
RLBench's shape positions are), so the layout numbers of the spec carry over.
Round parts are a visual cylinder with inscribed boxes for contact
(MJX-jax has no box-cylinder collisions).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from agnostos_mjx.sim.conditions import AnyOf, Condition, Detected
from agnostos_mjx.sim.math3d import quat_mul, quat_rotate, yaw_quat
from agnostos_mjx.sim.world import OBJECT_COLLISION
from agnostos_mjx.tasks.base import TABLE_Z, WORKSPACE_CENTER, WORKSPACE_HALF
from agnostos_mjx.tasks.builders.articulated import hinged_door
from agnostos_mjx.tasks.builders.common import grasp_site, sensor_volume
from agnostos_mjx.tasks.builders.primitives import WHITE, disc, panel, rod

G = mujoco.mjtGeom
INVISIBLE = (0.0, 0.0, 0.0, 0.0)


# ---- sampling and conditions ----------------------------------------------------------------
def place_root_between(key: jax.Array, half_extents: tuple[float, float], yaw_min: float,
                       yaw_max: float, offset=(0.0, 0.0), tries: int = 64,
                       ) -> tuple[jnp.ndarray, jnp.ndarray]:
    """`place_root` for a yaw range not centred on zero (RLBench's
    base_rotation_bounds, e.g. 0..pi/2): the first of `tries` candidates whose
    yawed footprint (centred at `offset` in the root frame) fits the workspace."""
    k_xy, k_yaw = jax.random.split(key)
    center = jnp.asarray(WORKSPACE_CENTER)
    half = jnp.asarray(WORKSPACE_HALF)
    xy = center + jax.random.uniform(k_xy, (tries, 2), minval=-half, maxval=half)
    yaw = jax.random.uniform(k_yaw, (tries,), minval=yaw_min, maxval=yaw_max)
    c, s = jnp.abs(jnp.cos(yaw)), jnp.abs(jnp.sin(yaw))
    reach = jnp.stack([c * half_extents[0] + s * half_extents[1],
                       s * half_extents[0] + c * half_extents[1]], -1)
    first = jnp.argmax(jnp.all(jnp.abs(xy - center) <= half - reach, -1))
    quat = yaw_quat(yaw[first])
    origin = jnp.concatenate([xy[first], jnp.array([TABLE_Z])])
    return origin - quat_rotate(quat, jnp.array([*offset, 0.0])), quat


def detected_one_of(pairs: Sequence[tuple[str, str]], index, half_extents, radius: float,
                    ) -> Condition:
    """DetectedCondition(object, volume) for the pair number `index` (traced,
    e.g. from the variation): the other pairs get a negative probe radius,
    which no distance satisfies, so one static condition tree serves every
    variation."""
    index = jnp.asarray(index)
    return AnyOf(tuple(
        Detected(obj, vol, tuple(half_extents), radius=jnp.where(index == k, radius, -1.0))
        for k, (obj, vol) in enumerate(pairs)))


def other_color(key: jax.Array, target: jnp.ndarray, count: int) -> jnp.ndarray:
    """A colour index drawn uniformly from the `count` colours except `target`."""
    pick = jax.random.randint(key, (), 0, count - 1)
    return pick + (pick >= target)


# ---- jars ----------------------------------------------------------------------------------
JAR_HALF_HEIGHT = 0.055
LID_HALF_HEIGHT = 0.0105


def jar(body: mujoco.MjsBody, name: str, *, radius: float = 0.045, neck_radius: float = 0.036,
        neck_height: float = 0.02, rgba=(1.0, 0.0, 0.0)) -> None:
    """A closed jar 0.11 m tall: a body and a narrower threaded neck whose top
    (at +JAR_HALF_HEIGHT) the lid rests on.  Geoms named `<name>_body` and
    `<name>_neck` take the variation colour."""
    h = JAR_HALF_HEIGHT
    body_half = h - neck_height / 2
    disc(body, radius, body_half, (0, 0, -h + body_half), rgba, name=f"{name}_body")
    disc(body, neck_radius, neck_height / 2, (0, 0, h - neck_height / 2), rgba,
         name=f"{name}_neck")
    for r, half, z in ((radius, body_half, -h + body_half),
                       (neck_radius, neck_height / 2, h - neck_height / 2)):
        s = r / np.sqrt(2.0)
        panel(body, (s, s, half), (0, 0, z)).rgba = list(INVISIBLE)


def jar_lid(body: mujoco.MjsBody, name: str, *, radius: float = 0.037, mass: float = 1.0,
            rgba=WHITE) -> None:
    """A screw lid 0.021 m thick, origin at its centre (a free graspable)."""
    disc(body, radius, LID_HALF_HEIGHT, (0, 0, 0), rgba, name=f"{name}_visual")
    s = radius / np.sqrt(2.0)
    box = panel(body, (s, s, LID_HALF_HEIGHT), (0, 0, 0))
    box.rgba = list(INVISIBLE)
    box.mass = mass


# ---- light bulbs ---------------------------------------------------------------------------
HOLDER_HALF = (0.05, 0.05, 0.0325)
HOLDER_FLOOR = 0.018  # floor top above the holder's bottom
BULB_HALF_HEIGHT = 0.053
BULB_GLASS_Z = 0.017  # glass centre above the bulb's centre
BULB_BASE_Z = -0.0355  # screw-base centre
SOCKET_FLOOR, SOCKET_WALL_TOP = 0.29, 0.32  # lamp socket, heights above the lamp's foot
SOCKET_INNER = 0.014


def open_box_geoms(name: str) -> list[str]:
    """The geoms of `open_box(..., name, ...)`, e.g. to colour them."""
    return [f"{name}_floor"] + [f"{name}_wall{k}" for k in range(4)]


def open_box(body: mujoco.MjsBody, name: str, half, *, floor: float, wall: float,
             rgba) -> None:
    """A box open at the top, origin at its centre, with a floor `floor` thick
    and walls `wall` thick (a bulb holder, a casing).  Geoms as `open_box_geoms`."""
    hx, hy, hz = half
    names = open_box_geoms(name)
    panel(body, (hx, hy, floor / 2), (0, 0, -hz + floor / 2), rgba, name=names[0])
    wall_half = hz - floor / 2
    z = -hz + floor + wall_half
    for k, (sx, sy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
        size = (wall / 2, hy, wall_half) if sx else (hx - wall, wall / 2, wall_half)
        pos = (sx * (hx - wall / 2), sy * (hy - wall / 2), z)
        panel(body, size, pos, rgba, name=names[1 + k])


def bulb_holder(body: mujoco.MjsBody, name: str, rgba=(1.0, 0.0, 0.0)) -> None:
    """A square casing 0.10 x 0.10 x 0.065 m whose floor carries a bulb
    standing upright; its geoms (`open_box_geoms(name)`) take the variation colour."""
    open_box(body, name, HOLDER_HALF, floor=HOLDER_FLOOR, wall=0.008, rgba=rgba)


def light_bulb(body: mujoco.MjsBody, name: str, glass: str, *, mass: float = 1.0) -> None:
    """A light bulb 0.106 m tall standing on its screw base (a free graspable):
    a capsule screw base and a glass sphere.  Adds sites `glass` at the glass
    centre (where it is grasped) and `<name>_base` at the screw base (what
    the lamp's socket sensor detects)."""
    body.add_geom(type=G.mjGEOM_SPHERE, size=[0.034, 0, 0], pos=[0, 0, BULB_GLASS_Z],
                  rgba=[1.0, 1.0, 1.0, 1.0], mass=mass, contype=OBJECT_COLLISION[0],
                  conaffinity=OBJECT_COLLISION[1], group=2, name=f"{glass}_glass")
    body.add_geom(type=G.mjGEOM_CAPSULE, size=[0.011, 0.0065, 0], pos=[0, 0, BULB_BASE_Z],
                  rgba=[0.6, 0.6, 0.6, 1.0], mass=0.01, contype=OBJECT_COLLISION[0],
                  conaffinity=OBJECT_COLLISION[1], group=2)
    disc(body, 0.015, 0.006, (0, 0, BULB_BASE_Z + 0.018), (0.6, 0.6, 0.6))
    grasp_site(body, glass, (0, 0, BULB_GLASS_Z))
    grasp_site(body, f"{name}_base", (0, 0, BULB_BASE_Z))


def lamp_with_socket(parent: mujoco.MjsBody, name: str, socket: str, pos) -> mujoco.MjsBody:
    """A bare table lamp 0.32 m tall whose socket, a cup 28 mm wide inside
    (floor at SOCKET_FLOOR), takes a bulb's screw base.  Returns the socket
    body `socket`, whose origin is at the socket floor's centre."""
    x, y = pos
    base = parent.add_body(name=name, pos=[x, y, 0.137])
    disc(base, 0.047, 0.01, (0, 0, -0.127), (0.85, 0.85, 1.0))
    disc(base, 0.012, 0.127, (0, 0, 0.01), (0.85, 0.85, 1.0))
    panel(base, (0.033, 0.033, 0.137), (0, 0, 0)).rgba = list(INVISIBLE)
    body = parent.add_body(name=socket, pos=[x, y, SOCKET_FLOOR])
    dark = (0.1, 0.1, 0.1)
    disc(body, 0.025, 0.0245, (0, 0, 0.0105), dark)
    panel(body, (0.017, 0.017, 0.007), (0, 0, -0.007), dark)  # floor
    wall_half = (SOCKET_WALL_TOP - SOCKET_FLOOR) / 2
    for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        size = (0.002, SOCKET_INNER + 0.004, wall_half) if sx else (SOCKET_INNER, 0.002, wall_half)
        panel(body, size, (sx * (SOCKET_INNER + 0.002), sy * (SOCKET_INNER + 0.002), wall_half),
              dark).rgba = list(INVISIBLE)
    return body


# ---- cups ----------------------------------------------------------------------------------
CUP_HALF_HEIGHT = 0.07
CUP_SIDES = 12


def cup_geoms(name: str, sides: int = CUP_SIDES) -> list[str]:
    """The geoms of `cup(..., name, ...)`, e.g. to colour them."""
    return [f"{name}_bottom"] + [f"{name}_side{k}" for k in range(sides)]


def cup_radius(z: float, bottom_radius: float = 0.032, top_radius: float = 0.047) -> float:
    """Outer radius of a cup at height `z` above its bottom."""
    return bottom_radius + (top_radius - bottom_radius) * z / (2 * CUP_HALF_HEIGHT)


def cup(body: mujoco.MjsBody, name: str, *, bottom_radius: float = 0.032,
        top_radius: float = 0.047, wall: float = 0.003, sides: int = CUP_SIDES,
        mass: float = 0.0532, rgba=WHITE, half_height: float = CUP_HALF_HEIGHT) -> None:
    """A tapered, open plastic cup 0.14 m tall (a free object), origin at its
    centre: a bottom plate and `sides` tilted wall panels, so that cups of the
    same yaw nest inside each other.  Geoms as `cup_geoms(name)`."""
    h = half_height
    tilt = np.arctan2(top_radius - bottom_radius, 2 * h)
    mid = (top_radius + bottom_radius) / 2 - wall / 2 * np.cos(tilt)
    half_width = mid * np.tan(np.pi / sides)
    half_len = h / np.cos(tilt)
    names = cup_geoms(name, sides)
    inner = (bottom_radius - wall) / np.sqrt(2.0)
    plate = panel(body, (inner, inner, wall / 2), (0, 0, -h + wall / 2), rgba, name=names[0])
    plate.mass = mass / (sides + 1)
    for k in range(sides):
        theta = 2 * np.pi * k / sides
        lean = np.array([np.cos(tilt / 2), 0.0, np.sin(tilt / 2), 0.0])  # about local y
        quat = np.asarray(quat_mul(np.asarray(yaw_quat(np.float64(theta))), lean))
        pos = (mid * np.cos(theta), mid * np.sin(theta), 0.0)
        geom = panel(body, (wall / 2, half_width, half_len), pos, rgba, name=names[1 + k],
                     quat=tuple(quat))
        geom.mass = mass / (sides + 1)


# ---- safe ----------------------------------------------------------------------------------
SAFE_HALF = (0.155, 0.118, 0.2475)  # width (x), depth (y, open front at +y), height
SAFE_WALL = 0.015
SAFE_SHELVES = (0.02, 0.165, 0.32)  # shelf top surfaces above the safe's bottom
MONEY_HALF = (0.0265, 0.0625, 0.016)


def safe(scene, parent: mujoco.MjsBody, name: str, pos, yaw: float, *,
         door_angle: float = 2.9, rgba=(0.8, 0.8, 0.8)) -> mujoco.MjsBody:
    """A safe 0.31 x 0.236 x 0.495 m open at its front (+y), with a floor and
    two shelves (tops at SAFE_SHELVES) and its door swung open on a passive
    hinge at the front right edge (`<name>_joint`, held by friction).  Returns
    the static body, origin at the safe's centre."""
    hx, hy, hz = SAFE_HALF
    t = SAFE_WALL
    body = parent.add_body(name=name, pos=list(pos),
                           quat=list(np.asarray(yaw_quat(np.float64(yaw)))))
    floor_half = (SAFE_SHELVES[0] / 2)
    panel(body, (hx, hy, floor_half), (0, 0, -hz + floor_half), rgba)  # floor
    panel(body, (hx, hy, t / 2), (0, 0, hz - t / 2), rgba)  # roof
    panel(body, (hx, t / 2, hz), (0, -hy + t / 2, 0), rgba)  # back
    for sx in (-1, 1):
        panel(body, (t / 2, hy, hz), (sx * (hx - t / 2), 0, 0), rgba)
    for top in SAFE_SHELVES[1:]:
        panel(body, (hx - t, hy - t / 2, 0.005), (0, t / 2, -hz + top - 0.005), rgba)
    hinged_door(scene, body, f"{name}_door", hinge_pos=(hx, hy, 0.0), axis=(0, 0, -1),
                panel_half=(0.145, 0.005, 0.2255), panel_offset=(-0.145, 0.005, 0.0),
                limits=(-np.pi, np.pi), initial=door_angle, friction_torque=5.0, rgba=rgba)
    scene.exclude(name, f"{name}_door")
    return body


def money_stack(body: mujoco.MjsBody, name: str, *, mass: float = 0.5) -> None:
    """A banded stack of bank notes 0.053 x 0.125 x 0.032 m (a free graspable)."""
    panel(body, MONEY_HALF, (0, 0, 0), (0.8, 0.86, 0.75), name=f"{name}_notes").mass = mass
    panel(body, (MONEY_HALF[0] + 0.0005, 0.01, MONEY_HALF[2] + 0.0005), (0, 0, 0),
          (0.77, 0.81, 0.9), collide=False, name=f"{name}_band")


# ---- mugs and a mug tree -------------------------------------------------------------------
MUG_RADIUS = 0.033
MUG_HALF_HEIGHT = 0.0415
HANDLE_RADIUS = 0.004
# The handle is a loop of three capsules in the mug's x-z plane on its +x
# side; its hole (30 mm out from the wall, 42 mm tall) is open along the
# mug's y axis and takes a 13 mm spoke with room for the expert's error.
HANDLE_OUTER_X = MUG_RADIUS + 0.030 + HANDLE_RADIUS
HANDLE_TOP_Z, HANDLE_BOTTOM_Z = 0.030, -0.020
MUG_HOLE = (MUG_RADIUS + 0.015, 0.0, (HANDLE_TOP_Z + HANDLE_BOTTOM_Z) / 2)
# Where the expert grasps: the wall opposite the handle, 20 mm below the rim.
MUG_GRASP = (-(MUG_RADIUS - 0.0015), 0.0, MUG_HALF_HEIGHT - 0.02)
# Mug tree (origin at the foot of the post): four spokes 95 mm long, 13 mm
# thick, tilted SPOKE_TILT up, their centres 0.0508 m out from the post's
# axis, in RLBench's order and heights.
SPOKE_TILT = np.deg2rad(20.0)
SPOKE_HALF_LENGTH, SPOKE_RADIUS, SPOKE_OFFSET = 0.0475, 0.0065, 0.0508
SPOKE_YAWS = tuple(np.deg2rad(a) for a in (189.8, 99.8, 9.8, 279.8))
SPOKE_HEIGHTS = (0.210, 0.149, 0.210, 0.149)
TREE_HEIGHT, TREE_BASE_RADIUS, POST_RADIUS = 0.316, 0.09, 0.015


def mug(body: mujoco.MjsBody, name: str, *, mass: float = 0.3, rgba=WHITE) -> None:
    """An open mug 0.083 m tall and 0.066 m wide with a handle loop on its +x
    side, origin at the centre of its body.  Adds sites `<name>_hole` (the
    handle's hole, what the spoke sensors detect) and `<name>_grasp`."""
    cup(body, name, bottom_radius=MUG_RADIUS, top_radius=MUG_RADIUS, half_height=MUG_HALF_HEIGHT,
        mass=mass, rgba=rgba)
    inner = MUG_RADIUS - 0.002
    for start, end in (((inner, 0, HANDLE_TOP_Z), (HANDLE_OUTER_X, 0, HANDLE_TOP_Z)),
                       ((HANDLE_OUTER_X, 0, HANDLE_TOP_Z), (HANDLE_OUTER_X, 0, HANDLE_BOTTOM_Z)),
                       ((HANDLE_OUTER_X, 0, HANDLE_BOTTOM_Z), (inner, 0, HANDLE_BOTTOM_Z))):
        rod(body, start, end, HANDLE_RADIUS, rgba, collide=True).mass = 0.01
    for site, pos in ((f"{name}_hole", MUG_HOLE), (f"{name}_grasp", MUG_GRASP)):
        grasp_site(body, site, pos)


def spoke_frame(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Centre and unit axis (pointing out and up) of spoke `k` in the tree's frame."""
    yaw = SPOKE_YAWS[k]
    axis = np.array([np.cos(SPOKE_TILT) * np.cos(yaw), np.cos(SPOKE_TILT) * np.sin(yaw),
                     np.sin(SPOKE_TILT)])
    centre = np.array([SPOKE_OFFSET * np.cos(yaw), SPOKE_OFFSET * np.sin(yaw), SPOKE_HEIGHTS[k]])
    return centre, axis


def z_to(axis: np.ndarray) -> np.ndarray:
    """Quaternion (wxyz) turning +z onto the unit vector `axis`."""
    z = np.array([0.0, 0.0, 1.0])
    half = (z + axis) / np.linalg.norm(z + axis)
    return np.array([float(z @ half), *np.cross(z, half)])


def mug_tree(parent: mujoco.MjsBody, name: str, pos, spoke_names: Sequence[str],
             sensor_half, rgba=(0.5, 0.85, 1.0)) -> mujoco.MjsBody:
    """A static mug tree 0.316 m tall: a round foot, a post and four capsule
    spokes (SPOKE_YAWS, SPOKE_HEIGHTS).  Each spoke gets a box site named
    `spoke_names[k]` on its centre, z along the spoke, of half size
    `sensor_half` (the spoke's success sensor).  Returns the tree's body,
    origin at the foot of the post."""
    tree = parent.add_body(name=name, pos=list(pos))
    disc(tree, TREE_BASE_RADIUS, 0.01, (0, 0, 0.01), rgba)
    s = TREE_BASE_RADIUS / np.sqrt(2.0)
    panel(tree, (s, s, 0.01), (0, 0, 0.01)).rgba = list(INVISIBLE)
    post_half = (TREE_HEIGHT - 0.02) / 2
    disc(tree, POST_RADIUS, post_half, (0, 0, 0.02 + post_half), rgba)
    s = POST_RADIUS / np.sqrt(2.0)
    panel(tree, (s, s, post_half), (0, 0, 0.02 + post_half)).rgba = list(INVISIBLE)
    for k, spoke in enumerate(spoke_names):
        centre, axis = spoke_frame(k)
        rod(tree, centre - SPOKE_HALF_LENGTH * axis, centre + SPOKE_HALF_LENGTH * axis,
            SPOKE_RADIUS, rgba, collide=True)
        sensor_volume(tree, spoke, centre, sensor_half, quat=z_to(axis))
    return tree


def hung_mug_pose(k: int, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose (tree frame) of an upright mug of yaw `yaw` whose handle's top bar
    rests on spoke `k`, the spoke through the middle of the hole (a static
    mug; `yaw` should turn the mug's y axis along the spoke)."""
    centre, axis = spoke_frame(k)
    rest_on = HANDLE_TOP_Z - HANDLE_RADIUS - SPOKE_RADIUS - MUG_HOLE[2]  # spoke below hole centre
    hole = centre + np.array([0.0, 0.0, -rest_on])
    quat = np.asarray(yaw_quat(np.float64(yaw)))
    return hole - np.asarray(quat_rotate(quat, np.asarray(MUG_HOLE))), quat


__all__ = [
    "BULB_HALF_HEIGHT", "CUP_HALF_HEIGHT", "HOLDER_HALF", "JAR_HALF_HEIGHT", "LID_HALF_HEIGHT",
    "MONEY_HALF", "MUG_GRASP", "MUG_HALF_HEIGHT", "MUG_HOLE", "MUG_RADIUS", "SAFE_HALF",
    "SAFE_SHELVES", "bulb_holder", "cup", "cup_geoms", "cup_radius", "detected_one_of",
    "hung_mug_pose", "jar", "jar_lid", "lamp_with_socket", "light_bulb", "money_stack", "mug",
    "mug_tree", "open_box", "open_box_geoms", "other_color", "place_root_between", "safe",
    "spoke_frame", "z_to",
]
