"""Household pieces of the Level-2 tasks: saucepan with lid, dish rack and
plate, oven with knobs, wall socket with charger, desktop computer with USB
stick.

Objects the gripper carries are free bodies in the world (MuJoCo free joints
cannot hang under a mocap root): a builder creates them at the origin, the
task declares their resting pose in its root frame and its sampler places them
with `common.pose_in_root` next to the root it draws.  Static parts hang
under the root.  Sensor volumes are `common.sensor_volume` sites.
"""

from __future__ import annotations

import mujoco
import numpy as np

from agnostos_mjx.sim.world import SceneBuilder
from agnostos_mjx.tasks.builders.common import free_body, grasp_site
from agnostos_mjx.tasks.builders.primitives import WHITE, disc, panel, rod

STEEL = (0.75, 0.75, 0.75)
GREY = (0.6, 0.6, 0.6)
DARK = (0.15, 0.15, 0.15)


def hidden(geom: mujoco.MjsGeom, mass: float | None = None) -> mujoco.MjsGeom:
    """Make a collision proxy invisible (a visual geom shows the shape)."""
    geom.rgba = [0.0, 0.0, 0.0, 0.0]
    if mass is not None:
        geom.mass = mass
    return geom


# solimp (dmin, dmax) of `stiff` contacts, and of harder ones for a pin that must stay in its
# port under its own weight for a whole episode: at STIFF a USB stick left alone crept out of
# its port and fell within 6,000 physics steps; at HOLDING it moves under a millimetre in
# 10,000 physics steps (a dmax of 0.999 made the contacts unstable when a gripper pushed it).
STIFF = (0.95, 0.99)
HOLDING = (0.99, 0.99)


def stiff(geom: mujoco.MjsGeom, impedance: tuple[float, float] = STIFF) -> mujoco.MjsGeom:
    """Hard contacts for a tight fit: the default soft contacts let a pin sink
    millimetres into its hole's walls, enough to tilt a plug out."""
    geom.solref = [0.01, 1.0]
    geom.solimp = [*impedance, 0.001, 0.5, 2.0]
    return geom


def _ring(body: mujoco.MjsBody, center, radius: float, half_thickness: float, z: tuple[float, float],
          rgba, sides: int = 8) -> None:
    """A vertical polygonal wall (collision) around `center`, z from z[0] to z[1]."""
    half_len = radius * np.tan(np.pi / sides) + half_thickness
    zc, hz = (z[0] + z[1]) / 2, (z[1] - z[0]) / 2
    for k in range(sides):
        a = 2 * np.pi * k / sides
        pos = (center[0] + radius * np.cos(a), center[1] + radius * np.sin(a), zc)
        quat = (np.cos(a / 2), 0.0, 0.0, np.sin(a / 2))
        hidden(panel(body, (half_thickness, half_len, hz), pos, rgba, quat=quat))


# ---- saucepan ------------------------------------------------------------------------------
LID_HALF_THICKNESS = 0.009


def saucepan(scene: SceneBuilder, parent: mujoco.MjsBody, name: str, *, center=(0.0, 0.0),
             radius: float = 0.112, height: float = 0.072, handle_length: float = 0.2,
             knob_radius: float = 0.03) -> tuple[str, str]:
    """A pot with a long handle along the root's -y, and a free lid
    `<name>_lid` with a knob, to be placed on the rim at (*center, height +
    LID_HALF_THICKNESS) in the root frame.  A site `<name>_lid_grasp_point`
    marks the knob's centre.  Returns (lid body, knob site)."""
    cx, cy = center
    lid_name = f"{name}_lid"
    pot = parent.add_body(name=name, pos=[0.0, 0.0, 0.0])
    disc(pot, radius, height / 2, (cx, cy, height / 2), STEEL, name=f"{name}_visual")
    disc(pot, radius - 0.006, 0.001, (cx, cy, height + 0.0005), DARK)  # the dark inside
    hidden(panel(pot, (radius * 0.7, radius * 0.7, 0.003), (cx, cy, 0.003), STEEL))
    _ring(pot, (cx, cy), radius - 0.004, 0.003, (0.0, height), STEEL)
    # Handle: a bar rising slightly away from the pot.
    y0, y1 = cy - radius, cy - radius - handle_length
    rod(pot, (cx, y0, height - 0.015), (cx, y1, height + 0.01), 0.011, DARK)
    mid = (cx, (y0 + y1) / 2, height - 0.002)
    tilt = np.arctan2(0.025, handle_length) / 2
    hidden(panel(pot, (0.008, handle_length / 2, 0.008), mid, DARK,
                 quat=(np.cos(tilt), -np.sin(tilt), 0.0, 0.0)))

    lid = free_body(scene, lid_name)
    lid_half = LID_HALF_THICKNESS
    disc(lid, radius + 0.003, lid_half, (0, 0, 0), WHITE, name=f"{lid_name}_visual")
    # Collision: two crossed squares (an eight-pointed star) whose points rest on the rim.
    square = (radius + 0.001) / np.sqrt(2.0)
    for a in (0.0, np.pi / 4):
        hidden(panel(lid, (square, square, lid_half), (0, 0, 0), WHITE,
                     quat=(np.cos(a / 2), 0.0, 0.0, np.sin(a / 2))), mass=0.028)
    knob_z = lid_half + 0.01
    disc(lid, knob_radius, 0.01, (0, 0, knob_z), WHITE, name=f"{lid_name}_knob")
    side = knob_radius / np.sqrt(2.0)
    hidden(panel(lid, (side, side, 0.01), (0, 0, knob_z), WHITE), mass=0.057)
    grasp_site(lid, f"{lid_name}_grasp_point", (0, 0, knob_z))
    return lid_name, f"{lid_name}_grasp_point"


# ---- plugs and sockets (charger in a wall socket, USB stick in a computer) -----------------
def socket_tube(parent: mujoco.MjsBody, front, inner_half: tuple[float, float], depth: float,
                wall: float = 0.0015, rgba=GREY, impedance: tuple[float, float] = STIFF) -> None:
    """A rectangular hole running along the root's +x from the point `front`
    (its mouth): four thin walls that hold a plugged pin by contact."""
    x, y, z = front
    hy, hz = inner_half
    xc, hx = x + depth / 2, depth / 2
    for s in (-1, 1):
        stiff(hidden(panel(parent, (hx, wall, hz + 2 * wall), (xc, y + s * (hy + wall), z),
                           rgba)), impedance)
        stiff(hidden(panel(parent, (hx, hy, wall), (xc, y, z + s * (hz + wall)), rgba)), impedance)
    parent.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.0005, hy + wall, hz + wall],
                    pos=[x - 0.0005, y, z], rgba=[*DARK, 1.0], contype=0, conaffinity=0, group=1)


def plug(scene: SceneBuilder, name: str, *, body_half, pins, pin_half: tuple[float, float],
         pin_length: float, grasp_offset=(0.0, 0.0, 0.0), rgba=GREY, pin_rgba=STEEL,
         mass: float = 0.01, impedance: tuple[float, float] = STIFF) -> str:
    """A free plug: a box body (origin at its centre) with pins sticking out
    of its +x face at (y, z) offsets `pins`, and a site `<name>_grasp_point`
    where the gripper should hold it; `impedance`: its pins' contacts (`stiff`).
    Returns the site name."""
    body = free_body(scene, name)
    panel(body, body_half, (0, 0, 0), rgba, name=f"{name}_visual").mass = mass
    x = body_half[0] + pin_length / 2
    for i, (y, z) in enumerate(pins):
        stiff(panel(body, (pin_length / 2, *pin_half), (x, y, z), pin_rgba,
                    name=f"{name}_pin{i}"), impedance).mass = 0.1 * mass
    grasp_site(body, f"{name}_grasp_point", grasp_offset)
    return f"{name}_grasp_point"


def wall_socket(parent: mujoco.MjsBody, name: str, *, face_x: float, plate_center, holes,
                hole_half=(0.0032, 0.0032), depth: float = 0.05, wall_center=(0.0, 0.2),
                wall_half=(0.2, 0.2)) -> str:
    """A wall facing the root's -x with a square socket plate whose front is
    at `face_x`, centred at (y, z) `plate_center`, with holes at (y, z)
    `holes`.  Returns a site `<name>_socket` at the plate's front centre."""
    wall_x = face_x + 0.019
    # Visual only, as RLBench's wall plane: the holes' tubes run through it.
    panel(parent, (0.004, *wall_half), (wall_x + 0.004, *wall_center), WHITE, collide=False,
          name=f"{name}_wall")
    cy, cz = plate_center
    panel(parent, (0.009, 0.074, 0.074), (face_x + 0.009, cy, cz), (0.95, 0.95, 0.95),
          collide=False, name=f"{name}_plate")
    for y, z in holes:
        socket_tube(parent, (face_x, y, z), hole_half, depth)
    grasp_site(parent, f"{name}_socket", (face_x, cy, cz))
    return f"{name}_socket"


def desktop_computer(parent: mujoco.MjsBody, name: str, *, front_x: float, half=(0.15, 0.09, 0.18),
                     port=(0.0, 0.3), port_half=(0.0062, 0.0024), port_depth: float = 0.02,
                     rgba=(0.22, 0.22, 0.25)) -> str:
    """A tower PC on the table whose front (at `front_x`) faces the root's -x,
    with one USB port at (y, z) `port` that holds a plugged stick (`HOLDING` contacts).
    The case collides from `port_depth` behind its front so the port's tube fits in the
    bezel.  Returns a site `<name>_port` at the port's mouth."""
    hx, hy, hz = half
    case = parent.add_body(name=name, pos=[front_x + hx, 0.0, hz])
    depth = port_depth + 0.002
    panel(case, (hx - depth / 2, hy, hz), (depth / 2, 0, 0), rgba, name=f"{name}_case")
    panel(case, (depth / 2, hy, hz), (-hx + depth / 2, 0, 0), (0.3, 0.3, 0.33), collide=False,
          name=f"{name}_bezel")
    # Drive bay and power button on the bezel (visual).
    panel(case, (0.001, hy * 0.8, 0.02), (-hx - 0.001, 0, hz * 0.6), DARK, collide=False)
    button = case.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.008, 0.001, 0],
                           pos=[-hx - 0.001, 0, hz * 0.35], quat=[0.7071068, 0, 0.7071068, 0],
                           rgba=[0.6, 0.8, 1.0, 1.0], contype=0, conaffinity=0, group=1)
    button.name = f"{name}_power"
    y, z = port
    socket_tube(case, (-hx, y, z - hz), port_half, port_depth, wall=0.002, impedance=HOLDING)
    grasp_site(case, f"{name}_port", (-hx, y, z - hz))
    return f"{name}_port"


# ---- dish rack and plate --------------------------------------------------------------------
def dish_rack(parent: mujoco.MjsBody, name: str, *, pillar_colors, spacing: float = 0.05,
              rod_x: float = 0.08, rod_height: float = 0.15, base_half=(0.08, 0.15, 0.0075)) -> None:
    """A flat base with rows of vertical rod pairs across it: row k stands at
    y = (k - (n-1)/2) * spacing with rods at x = +-rod_x, coloured
    `pillar_colors[k]`; plates stand upright between two rows."""
    panel(parent, base_half, (0, 0, base_half[2]), (0.65, 0.65, 0.65), name=f"{name}_base")
    n = len(pillar_colors)
    for k, rgba in enumerate(pillar_colors):
        y = (k - (n - 1) / 2) * spacing
        for x in (-rod_x, rod_x):
            rod(parent, (x, y, 0.005), (x, y, rod_height - 0.005), 0.005, rgba, collide=True,
                name=f"{name}_pillar{k}_{'a' if x < 0 else 'b'}")


def plate(scene: SceneBuilder, name: str, *, radius: float = 0.1, half_thickness: float = 0.0125,
          mass: float = 0.25, grasp_height: float = 0.071) -> tuple[str, ...]:
    """A free plate standing upright: its face in the body's x-z plane.  It
    collides as two squares turned 22.5 and 67.5 degrees, an eight-pointed
    star whose hull is an octagon with a flat bottom at the disc's lowest
    point (so it stands on the rack like the disc would).  Sites: `<name>_grasp_point` on the
    top edge where the gripper holds it, and probe points (centre and four
    rim points) standing in for its shape in sensor-volume tests.  Returns
    the probe site names."""
    body = free_body(scene, name)
    body.add_geom(name=f"{name}_visual", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                  size=[radius, half_thickness, 0], quat=[0.7071068, 0.7071068, 0, 0],
                  rgba=[0.99, 0.99, 0.99, 1.0], contype=0, conaffinity=0, group=1)
    half = radius / np.cos(np.pi / 8) / np.sqrt(2.0)
    for a in (np.pi / 8, 3 * np.pi / 8):
        hidden(panel(body, (half, half_thickness, half), (0, 0, 0), WHITE,
                     quat=(np.cos(a / 2), 0.0, np.sin(a / 2), 0.0)), mass=mass / 2)
    grasp_site(body, f"{name}_grasp_point", (0, 0, grasp_height))
    probes = [(0.0, 0.0)] + [(0.9 * radius * np.cos(a), 0.9 * radius * np.sin(a))
                             for a in np.arange(4) * np.pi / 2]
    names = []
    for i, (x, z) in enumerate(probes):
        grasp_site(body, f"{name}_probe{i}", (x, 0, z))
        names.append(f"{name}_probe{i}")
    return tuple(names)


# ---- oven ------------------------------------------------------------------------------------
def knob(parent: mujoco.MjsBody, name: str, pos, *, joint_range=None, friction_torque: float = 0.1,
         rgba=(0.67, 0.67, 0.67)) -> str | None:
    """A control knob on a front face that looks along the root's -x: a round
    base and a grip bar (2.2 cm tall, 1.1 cm wide) the fingers close around.
    With `joint_range` it turns on a hinge whose axis points out of the face
    (positive = anticlockwise seen from the front), held by friction as
    CoppeliaSim's zero-velocity motor does; returns the joint name."""
    body = parent.add_body(name=name, pos=list(pos))
    joint = None
    if joint_range is not None:
        joint = f"{name}_joint"
        body.add_joint(name=joint, type=mujoco.mjtJoint.mjJNT_HINGE, axis=[-1, 0, 0],
                       range=list(joint_range), frictionloss=friction_torque, damping=0.01,
                       armature=0.001)
    along_x = [0.7071068, 0.0, 0.7071068, 0.0]
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.02, 0.003, 0], pos=[0.009, 0, 0],
                  quat=along_x, rgba=[*rgba, 1.0], contype=0, conaffinity=0, group=1)
    bar = panel(body, (0.011, 0.0055, 0.011), (0, 0, 0), rgba, collide=joint is not None,
                name=f"{name}_grip")
    bar.mass = 0.1
    panel(body, (0.0005, 0.0015, 0.008), (-0.0112, 0, 0.003), DARK, collide=False)  # marker
    return joint


def oven(scene: SceneBuilder, parent: mujoco.MjsBody, name: str, *, active_knob,
         decor_knobs=(), body_min=(0.04, -0.31, 0.0), body_max=(0.467, 0.258, 0.596),
         rgba=(0.95, 0.95, 0.95)) -> str:
    """A free-standing oven whose front faces the root's -x: a cabinet (one
    collision box), a stove top with burners, a door hinged at its bottom
    (closed), a tray on a slide inside, a row of decorative knobs and one
    turning knob `<name>_knob` at (x, y, z) `active_knob`.  Returns the
    turning knob's joint name."""
    lo, hi = np.asarray(body_min), np.asarray(body_max)
    half, mid = (hi - lo) / 2, (hi + lo) / 2
    cabinet = parent.add_body(name=f"{name}_frame")
    panel(cabinet, half, mid, rgba, name=f"{name}_cabinet")
    panel(cabinet, (half[0], half[1], 0.014), (mid[0], mid[1], hi[2] + 0.014), DARK, collide=False,
          name=f"{name}_stove_top")
    for dx in (-0.09, 0.09):
        for dy in (-0.13, 0.13):
            disc(cabinet, 0.045, 0.006, (mid[0] + dx, mid[1] + dy, hi[2] + 0.03), GREY)
    # Door: hinged at its bottom front edge about the root's y; q = pi/2 is
    # closed (RLBench's convention), q = 0 lies open towards the robot.
    door = cabinet.add_body(name=f"{name}_door", pos=[lo[0] - 0.017, mid[1], 0.1])
    door.add_joint(name=f"{name}_door_joint", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0],
                   range=[0.0, np.pi / 2], ref=np.pi / 2, frictionloss=1.0, damping=0.5,
                   armature=0.02)
    panel(door, (0.017, half[1] - 0.01, 0.17), (0, 0, 0.17), (0.67, 0.67, 0.67),
          name=f"{name}_door_panel").mass = 0.1
    panel(door, (0.0005, half[1] * 0.6, 0.09), (-0.0175, 0, 0.2), DARK, collide=False)  # window
    rod(door, (-0.03, -half[1] * 0.6, 0.31), (-0.03, half[1] * 0.6, 0.31), 0.008, GREY)
    scene.initial_joints[f"{name}_door_joint"] = np.pi / 2
    tray = cabinet.add_body(name=f"{name}_tray", pos=[mid[0], mid[1], 0.288])
    tray.add_joint(name=f"{name}_tray_joint", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[-1, 0, 0],
                   range=[0.0, 0.3], damping=5.0)
    panel(tray, (0.145, 0.235, 0.005), (0, 0, 0), GREY, collide=False).mass = 1.36
    for i, pos in enumerate(decor_knobs):
        knob(cabinet, f"{name}_knob_decor{i}", pos)
    return knob(cabinet, f"{name}_knob", active_knob, joint_range=(0.0, np.pi / 2))
