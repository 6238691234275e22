"""Free-moving props of the Level-2 tasks: a buzz-wire game with its ring
wand, a basketball hoop and ball, a rope of capsule links, a spatula, and a
watering can with a plant pot.

Every prop is made of boxes, capsules and spheres (the contact pairs MJX-jax
supports); round things that need a cylinder look get a visual disc.  Dynamic
props are free bodies parented to the world: their task samples their pose
every episode, so the builders place them at an arbitrary spot (free
bodies, point markers and sensor volumes: see `common`).
"""

from __future__ import annotations

import mujoco
import numpy as np

from agnostos_mjx.sim.world import OBJECT_COLLISION, SceneBuilder
from agnostos_mjx.tasks.builders.common import free_body, grasp_site
from agnostos_mjx.tasks.builders.primitives import WHITE, panel, rod

G = mujoco.mjtGeom
GREY = (0.6, 0.6, 0.6)
ORANGE = (1.0, 0.5, 0.0)


def capsule(body: mujoco.MjsBody, start, end, radius: float, rgba, mass: float = 0.0,
            name: str = "") -> mujoco.MjsGeom:
    """A colliding capsule; `mass` 0 keeps the density default."""
    geom = rod(body, start, end, radius, rgba, collide=True, name=name)
    geom.group = 2
    if mass:
        geom.mass = mass
    return geom


# ---- beat_the_buzz ---------------------------------------------------------------------------
def buzz_wire(parent: mujoco.MjsBody, name: str, *, wire_z: float = 0.295,
              half_span: float = 0.16, wire_radius: float = 0.003) -> None:
    """The buzz-wire stand (RLBench's `Cuboid`): a base plate, two posts and a
    straight metal wire along the parent's y axis at height `wire_z`."""
    panel(parent, (0.05, half_span + 0.016, 0.005), (0, 0, 0.005), (0.85, 0.85, 1.0),
          name=f"{name}_base")
    for sy in (-1, 1):
        panel(parent, (0.006, 0.006, wire_z / 2), (0, sy * half_span, wire_z / 2 + 0.005),
              (0.85, 0.85, 1.0), name=f"{name}_post{'ab'[sy > 0]}")
    capsule(parent, (0, -half_span, wire_z), (0, half_span, wire_z), wire_radius, GREY,
            name=f"{name}_wire")


def ring_wand(scene: SceneBuilder, name: str, *, ring_radius: float = 0.0385,
              tube_radius: float = 0.0055, handle_end=(-0.10, 0.0, -0.236),
              segments: int = 16, mass: float = 0.03) -> mujoco.MjsBody:
    """The buzz-wire wand: a ring (a polygon of capsules) in the body's x-z
    plane around its origin, and a straight handle from the ring's bottom to
    `handle_end`.  The wand is gravity compensated: RLBench's model saves it
    hovering with the ring centred on the wire, as if hung on a holder, and
    the kinematic grasp carries it from there."""
    body = free_body(scene, name, damping=0.02, gravcomp=1.0)
    angles = np.linspace(0.0, 2 * np.pi, segments + 1)
    points = [(ring_radius * np.cos(a), 0.0, ring_radius * np.sin(a)) for a in angles]
    for i in range(segments):
        capsule(body, points[i], points[i + 1], tube_radius, GREY, mass=mass / (2 * segments))
    capsule(body, (0.0, 0.0, -ring_radius), handle_end, tube_radius, ORANGE, mass=mass / 2,
            name=f"{name}_handle")
    return body


# ---- basketball_in_hoop ----------------------------------------------------------------------
def basketball_hoop(parent: mujoco.MjsBody, name: str, *, rim_center, rim_radius: float = 0.06,
                    tube_radius: float = 0.005, segments: int = 16) -> None:
    """A hoop on a pole: base plate and pole behind the rim (along +x), a
    backboard and a horizontal ring of capsules, with a visual net."""
    cx, cy, cz = rim_center
    board_x = cx + rim_radius + 0.04
    panel(parent, (0.05, 0.08, 0.01), (board_x + 0.05, cy, 0.01), WHITE, name=f"{name}_base")
    panel(parent, (0.012, 0.012, (cz + 0.1) / 2), (board_x + 0.03, cy, (cz + 0.1) / 2), GREY,
          name=f"{name}_pole")
    panel(parent, (0.006, 0.21, 0.13), (board_x, cy, cz + 0.1), WHITE, name=f"{name}_board")
    panel(parent, (0.02, 0.008, 0.004), (board_x - 0.02, cy, cz), ORANGE, name=f"{name}_bracket")
    angles = np.linspace(0.0, 2 * np.pi, segments + 1)
    points = [(cx + rim_radius * np.cos(a), cy + rim_radius * np.sin(a), cz) for a in angles]
    for i in range(segments):
        capsule(parent, points[i], points[i + 1], tube_radius, ORANGE)
    for a in angles[:-1:2]:  # the net: visual strings
        top = (cx + rim_radius * np.cos(a), cy + rim_radius * np.sin(a), cz)
        bottom = (cx + 0.7 * rim_radius * np.cos(a), cy + 0.7 * rim_radius * np.sin(a), cz - 0.1)
        rod(parent, top, bottom, 0.0015, WHITE)


def ball_stop(parent: mujoco.MjsBody, center, ball_radius: float) -> None:
    """RLBench's invisible `ball_stop`: a low collar that keeps a ball from
    rolling away from where it rests on the table."""
    x, y = center
    gap = 0.6 * ball_radius + 0.004  # the collar touches the ball below its equator
    for dx, dy in ((gap, 0.0), (-gap, 0.0), (0.0, gap), (0.0, -gap)):
        geom = panel(parent, (0.004 + abs(dy) * 0.5, 0.004 + abs(dx) * 0.5, 0.005),
                     (x + dx + np.sign(dx) * 0.004, y + dy + np.sign(dy) * 0.004, 0.005))
        geom.rgba[3] = 0.0


def ball(scene: SceneBuilder, name: str, radius: float, mass: float, rgba=WHITE) -> mujoco.MjsBody:
    """A free sphere that rolls (torsional and rolling friction keep it from
    spinning forever)."""
    body = free_body(scene, name)
    contype, conaffinity = OBJECT_COLLISION
    body.add_geom(name=f"{name}_geom", type=G.mjGEOM_SPHERE, size=[radius, 0, 0],
                  rgba=[*rgba, 1.0], mass=mass, contype=contype, conaffinity=conaffinity,
                  group=2, condim=6, friction=[1.0, 0.005, 0.0005])
    return body


# ---- scoop_with_spatula ----------------------------------------------------------------------
def spatula(scene: SceneBuilder, name: str, *, blade_half=(0.06, 0.065, 0.0015),
            blade_pitch: float = 0.09, blade_center=(0.0, -0.154, -0.029),
            handle_half=(0.007, 0.05, 0.005), mass: float = 0.069,
            rgba=(0.71, 0.72, 0.70)) -> mujoco.MjsBody:
    """A spatula whose body origin is the middle of its handle (where it is
    grasped): a box handle along +y, a neck sloping down to a thin blade
    toward -y whose front edge is its lowest point (a ramp for what it
    scoops).  It is gravity compensated and does not touch the table (it
    hovers where RLBench's model rests it): the front edge may run a hair
    below the table top and so slide under objects resting there."""
    body = free_body(scene, name, damping=0.05, gravcomp=1.0)
    scene.exclude(name, "world")
    handle = panel(body, handle_half, (0.0, 0.0, 0.0), rgba, name=f"{name}_handle")
    bx, by, bz = blade_center
    quat = (np.cos(blade_pitch / 2), np.sin(blade_pitch / 2), 0.0, 0.0)  # front edge down
    blade = panel(body, blade_half, blade_center, rgba, name=f"{name}_blade", quat=quat)
    back = (bx, by + blade_half[1] * np.cos(blade_pitch), bz + blade_half[1] * np.sin(blade_pitch))
    neck = capsule(body, back, (0.0, -handle_half[1], 0.0), 0.004, rgba, name=f"{name}_neck")
    for geom, share in ((handle, 0.3), (blade, 0.5), (neck, 0.2)):
        geom.mass = share * mass
    return body


# ---- straighten_rope -------------------------------------------------------------------------
# Rope links collide with the table (contype 4), the robot (1) and other
# objects (2), but not with each other, which keeps the contact count small.
ROPE_COLLISION = (2, 5)


def rope(scene: SceneBuilder, name: str, points, *, radius: float = 0.005,
         masses=None, rgba=(1.0, 0.25, 0.25), damping: float = 0.002,
         armature: float = 1e-5) -> list[str]:
    """A rope lying on the table along the 2-D polyline `points` (metres, in
    the frame the sampler later places the first link in): one capsule link
    per segment, each a child of the previous one on a ball joint at their
    shared point, the first on a free joint.  Link frames have x along the
    segment and z up.  Returns the link body names from first to last."""
    pts = np.asarray(points, float)
    masses = masses if masses is not None else [0.025] * (len(pts) - 1)
    names, parent, parent_pose = [], scene.world, (np.zeros(3), 0.0)
    for i, (a, b) in enumerate(zip(pts[:-1], pts[1:])):
        d = b - a
        half, yaw = np.linalg.norm(d) / 2, np.arctan2(d[1], d[0])
        center = np.array([*(a + b) / 2, radius])
        link = f"{name}_{i}"
        # Pose relative to the parent link (the first link's pose is sampled).
        p_center, p_yaw = parent_pose
        c, s = np.cos(-p_yaw), np.sin(-p_yaw)
        rel = center - p_center
        rel = (c * rel[0] - s * rel[1], s * rel[0] + c * rel[1], rel[2])
        dyaw = yaw - p_yaw
        body = parent.add_body(name=link, pos=list(rel) if i else [0, 0, 0],
                               quat=[np.cos(dyaw / 2), 0, 0, np.sin(dyaw / 2)] if i else [1, 0, 0, 0])
        if i == 0:
            body.add_freejoint(name=f"{link}_free")
        else:
            body.add_joint(name=f"{link}_ball", type=mujoco.mjtJoint.mjJNT_BALL, pos=[-half, 0, 0],
                           damping=damping, armature=armature)
        shade = 0.75 if i == len(pts) - 2 else 1.0  # the last link (the head) darker
        body.add_geom(name=f"{link}_geom", type=G.mjGEOM_CAPSULE, size=[radius, half - radius, 0],
                      quat=[np.sqrt(0.5), 0, np.sqrt(0.5), 0], rgba=[*np.multiply(rgba, shade), 1],
                      mass=masses[i], contype=ROPE_COLLISION[0], conaffinity=ROPE_COLLISION[1],
                      group=2, friction=[0.6, 0.005, 0.0001])
        names.append(link)
        parent, parent_pose = body, (center, yaw)
    return names


# ---- water_plants ----------------------------------------------------------------------------
def watering_can(scene: SceneBuilder, name: str, *, half=(0.045, 0.035), height: float = 0.09,
                 wall: float = 0.004, handle_rise: float = 0.065, mass: float = 0.3,
                 rgba=(0.2, 0.45, 0.75)) -> mujoco.MjsBody:
    """A watering can (origin at the bottom centre, spout toward +x): a box
    with the front half of its top open (the mouth), a bar handle along x
    high enough above the lid for the fingers to close around it from the
    side, and a visual spout.  Sites: `<name>_handle` (the bar's middle),
    `<name>_lip` (the front wall's top edge, where tilted contents leave) and
    `<name>_head` (the spout's tip)."""
    body = free_body(scene, name)
    hx, hy = half
    parts = [
        ((hx, hy, wall / 2), (0, 0, wall / 2)),  # floor
        ((wall / 2, hy, height / 2), (-hx + wall / 2, 0, height / 2)),  # back
        ((wall / 2, hy, height / 2), (hx - wall / 2, 0, height / 2)),  # front
        ((hx, wall / 2, height / 2), (0, hy - wall / 2, height / 2)),  # sides
        ((hx, wall / 2, height / 2), (0, -hy + wall / 2, height / 2)),
        ((hx / 2, hy, wall / 2), (-hx / 2, 0, height - wall / 2)),  # lid over the back half
    ]
    # The handle spans the lid (the back half), clear of the lip where the
    # contents leave.
    bar_z, bar_x = height + handle_rise, -hx / 2
    parts += [((hx / 2, 0.006, 0.006), (bar_x, 0, bar_z))]  # handle bar
    parts += [((0.004, 0.004, handle_rise / 2), (x, 0, height + handle_rise / 2))
              for x in (-hx + 0.004, -0.004)]  # handle posts
    geoms = [panel(body, h, p, rgba) for h, p in parts]
    for geom in geoms:
        geom.mass = mass / len(geoms)
    tip = (hx + 0.08, 0.0, height)
    rod(body, (hx, 0.0, 0.02), tip, 0.006, rgba)  # spout (visual)
    grasp_site(body, f"{name}_handle", (bar_x, 0, bar_z))
    grasp_site(body, f"{name}_lip", (hx, 0, height))
    grasp_site(body, f"{name}_head", tip)
    return body


def water_drops(scene: SceneBuilder, name: str, count: int, *, radius: float = 0.004,
                mass: float = 0.001, rgba=(0.1, 0.1, 0.9)) -> list[str]:
    """`count` free spheres (RLBench's water drops); their task places them
    inside the can.  Returns their body names."""
    return [ball(scene, f"{name}{i}", radius, mass, rgba).name for i in range(count)]


def plant_pot(parent: mujoco.MjsBody, name: str, center, *, half: float = 0.085,
              height: float = 0.09, soil: float = 0.06, wall: float = 0.006) -> None:
    """A square pot with soil inside and a visual plant; `<name>_soil` is a
    site on the soil's surface."""
    x, y = center
    terracotta, earth, leaf = (0.72, 0.36, 0.22), (0.3, 0.2, 0.1), (0.2, 0.6, 0.2)
    panel(parent, (half, half, soil / 2), (x, y, soil / 2), earth, name=f"{name}_soil")
    for sx, sy, hx, hy in ((1, 0, wall / 2, half), (-1, 0, wall / 2, half),
                           (0, 1, half, wall / 2), (0, -1, half, wall / 2)):
        panel(parent, (hx, hy, height / 2),
              (x + sx * (half - wall / 2), y + sy * (half - wall / 2), height / 2), terracotta)
    rod(parent, (x, y, soil), (x, y, soil + 0.12), 0.004, leaf)
    for dx, dy, dz in ((0.03, 0.0, 0.08), (-0.025, 0.02, 0.1), (0.0, -0.03, 0.12)):
        parent.add_geom(type=G.mjGEOM_ELLIPSOID, size=[0.025, 0.012, 0.004],
                        pos=[x + dx, y + dy, soil + dz], rgba=[*leaf, 1.0], contype=0,
                        conaffinity=0, group=1)
    grasp_site(parent, f"{name}_soil", (x, y, soil))
