"""Household appliances with hinged parts: barbecue grill, fridge, laptop, toilet.

Each builder lays its piece out in the parent frame at the positions of the
RLBench scene model (spec section of the task that uses it), so a task only
places the root.  Moving parts reuse `hinged_door`; the builders add what a
plain panel lacks (handles, rims, tilted or free-swinging parts) and sites at
visual centres, where X-ICM's text places an object whose body frame sits on
a hinge.
"""

from __future__ import annotations

import mujoco
import numpy as np

from agnostos_mjx.sim.world import SceneBuilder
from agnostos_mjx.tasks.builders.articulated import hinged_door
from agnostos_mjx.tasks.builders.common import grasp_site
from agnostos_mjx.tasks.builders.primitives import panel, rod

GRILL_RGBA = (0.25, 0.25, 0.25)
GRILL_LID_RGBA = (0.4, 0.4, 0.4)
GRATE_RGBA = (0.59, 0.59, 0.59)
HANDLE_RGBA = (0.5, 0.5, 0.5)
# The barbecue of open_grill (root frame): firebox x[0.114, 0.321], y +-0.276,
# rim at z 0.293, grate top at z 0.276, lid hinged on the back edge over y < 0.03.
GRILL_X = (0.114, 0.321)
GRILL_HALF_Y = 0.276
GRILL_RIM_Z = 0.293
GRATE_Z = 0.276
GRILL_LID_HINGE = (0.319, -0.116, 0.293)
# RLBench places the grill through its `grill_root` plane (0.325 x 0.455 m at
# x = 0.125), smaller than the grill itself: (half extents, centre) for place_root.
GRILL_BOUNDARY_HALF, GRILL_BOUNDARY_CENTER = (0.1625, 0.2275), (0.125, 0.0)


def grill(scene: SceneBuilder, parent: mujoco.MjsBody, name: str = "grill") -> mujoco.MjsBody:
    """A static barbecue on four legs: a firebox whose grate (top at GRATE_Z)
    lies 17 mm below a rim, so food placed on it stays put.  Returns the body
    (its frame is the parent's; a site `<name>_center` marks the visual centre)."""
    body = parent.add_body(name=name)
    x0, x1 = GRILL_X
    cx, hx, hy = (x0 + x1) / 2, (x1 - x0) / 2, GRILL_HALF_Y
    floor_z = 0.17
    panel(body, (hx, hy, (GRATE_Z - 0.006 - floor_z) / 2), (cx, 0, (GRATE_Z - 0.006 + floor_z) / 2),
          GRILL_RGBA)  # firebox below the grate
    panel(body, (hx - 0.01, hy - 0.01, 0.003), (cx, 0, GRATE_Z - 0.003), GRATE_RGBA,
          name=f"{name}_grate")
    rim_h = (GRILL_RIM_Z - GRATE_Z) / 2
    rim_z = GRATE_Z + rim_h
    for sx in (-1, 1):
        panel(body, (0.005, hy, rim_h), (cx + sx * (hx - 0.005), 0, rim_z), GRILL_RGBA)
    for sy in (-1, 1):
        panel(body, (hx, 0.005, rim_h), (cx, sy * (hy - 0.005), rim_z), GRILL_RGBA)
    for k in range(-4, 5):  # grate bars, visual only
        y = k * (hy - 0.02) / 4.5
        rod(body, (x0 + 0.012, y, GRATE_Z + 0.002), (x1 - 0.012, y, GRATE_Z + 0.002), 0.003,
            (0.2, 0.2, 0.2))
    for sx in (-1, 1):
        for sy in (-1, 1):
            leg = (cx + sx * (hx - 0.015), sy * (hy - 0.015))
            rod(body, (*leg, 0.0), (*leg, floor_z), 0.012, GRILL_RGBA)
    panel(body, (hx - 0.015, hy - 0.015, 0.005), (cx, 0, 0.06), GRILL_RGBA)  # shelf between legs
    grasp_site(body, f"{name}_center", (cx, 0, 0.15))
    return body


def grill_lid(scene: SceneBuilder, parent: mujoco.MjsBody, name: str = "grill_lid",
              grill_name: str = "grill") -> str:
    """The hinged cover of open_grill over one half of the grate: hinge on the
    back edge about +y (positive opens), a motor of 1 N m at zero speed that
    holds it where it is left, and a bar handle 5 cm in front of its front
    edge.  The bar is its own body `<name>_handle`, free to spin about its
    axis on two standoffs: a gripper holding it keeps its orientation while
    the lid swings, as a round handle turns inside a real grip.  Sites
    `<name>_hinge` and `<name>_center`.  Returns the lid joint name."""
    hinge = GRILL_LID_HINGE
    joint = hinged_door(scene, parent, name, hinge_pos=hinge, axis=(0, 1, 0),
                        panel_half=(0.0975, 0.1465, 0.0495), panel_offset=(-0.1005, 0.0005, 0.0505),
                        limits=(0.0, 1.047), initial=0.0, friction_torque=1.0,
                        rgba=GRILL_LID_RGBA, mass=0.661)
    lid = scene.spec.body(name)
    bar = (0.081 - hinge[0], 0.0, 0.319 - hinge[2])  # root x = 0.081, z = 0.319
    for sy in (-1, 1):
        panel(lid, (0.02, 0.005, 0.005), (bar[0] + 0.02, sy * 0.045, bar[2]),
              HANDLE_RGBA).mass = 0.01
    handle = lid.add_body(name=f"{name}_handle", pos=list(bar))
    handle.add_joint(name=f"{name}_handle_joint", type=mujoco.mjtJoint.mjJNT_HINGE,
                     axis=[0, 1, 0], damping=0.01, armature=0.001)
    panel(handle, (0.007, 0.04, 0.007), (0, 0, 0), HANDLE_RGBA).mass = 0.02
    grasp_site(lid, f"{name}_center", (-0.1005, 0.0, 0.0505))
    grasp_site(parent, f"{name}_hinge", hinge)
    scene.exclude(name, grill_name)
    scene.exclude(f"{name}_handle", grill_name)
    return joint


LAPTOP_HINGE = (-0.03, 0.033, 0.115)
LAPTOP_LID_TILT = 0.227  # rad: the open lid leans back 13 degrees past upright


def laptop(scene: SceneBuilder, parent: mujoco.MjsBody, name: str = "laptop") -> str:
    """close_laptop_lid's laptop on its brown holder block: a static base and
    a free-swinging lid (RLBench's motor has 1e-5 N m) hinged on the base's
    rear edge about +x; joint 0 = open and leaning back, positive closes.
    The lid passes through the base (no lid-base contact) so that it comes
    to rest on its 105-degree limit rather than on the keyboard at 103,
    just above the 1.79 rad success threshold.  Bodies `<name>_holder`,
    `<name>_base`, `<name>_lid`; site `<name>_lid_center`.  Returns the joint
    name."""
    holder = parent.add_body(name=f"{name}_holder", pos=[-0.014, -0.074, 0.049])
    panel(holder, (0.2, 0.15, 0.05), (0, 0, 0), (0.31, 0.19, 0.15))
    base = parent.add_body(name=f"{name}_base", pos=[-0.029, -0.093, 0.106])
    panel(base, (0.1735, 0.1265, 0.0075), (0, 0, 0), (0.75, 0.75, 0.78))
    panel(base, (0.15, 0.06, 0.0005), (0, 0.023, 0.008), (0.15, 0.15, 0.17),
          collide=False)  # keyboard
    panel(base, (0.04, 0.03, 0.0005), (0, -0.082, 0.008), (0.6, 0.6, 0.63),
          collide=False)  # touchpad
    joint = hinged_door(scene, parent, f"{name}_lid", hinge_pos=LAPTOP_HINGE, axis=(1, 0, 0),
                        panel_half=(0.17, 0.003, 0.1225), panel_offset=(0.003, 0.003, 0.1225),
                        limits=(0.0, 1.833), initial=0.0, friction_torque=1e-5,
                        rgba=(0.75, 0.75, 0.78), mass=0.083)
    lid = scene.spec.body(f"{name}_lid")
    lid.quat = [float(np.cos(-LAPTOP_LID_TILT / 2)), float(np.sin(-LAPTOP_LID_TILT / 2)), 0.0, 0.0]
    scene.spec.joint(joint).damping[0] = 0.01
    panel(lid, (0.155, 0.0005, 0.1), (0.003, -0.0005, 0.13), (0.1, 0.12, 0.2),
          collide=False)  # screen
    grasp_site(lid, f"{name}_lid_center", (0.003, 0.0, 0.1225))
    scene.exclude(f"{name}_lid", f"{name}_base")
    scene.exclude(f"{name}_lid", f"{name}_holder")
    return joint


TOILET_HINGE = (-0.006, -0.034, 0.237)
TOILET_SEAT_UP = 1.745  # rad, 100 degrees: up and leaning back on the cistern


def toilet(scene: SceneBuilder, parent: mujoco.MjsBody, name: str = "toilet") -> str:
    """toilet_seat_down's toilet: a bowl on a pedestal, a cistern at the back
    (-y) and a free seat hinged about +x behind the bowl; joint 0 = down on
    the bowl, positive raises it, starting up at TOILET_SEAT_UP.  The seat
    has no contact with the toilet and comes to rest on its limits, so down
    means exactly 0.  Bodies `<name>_bowl`, `<name>_cistern`, `<name>_seat`;
    site `<name>_seat_center`.  Returns the joint name."""
    bowl = parent.add_body(name=f"{name}_bowl", pos=[-0.005, 0.045, 0.2])
    panel(bowl, (0.06, 0.08, 0.075), (0, -0.01, -0.125))  # pedestal
    panel(bowl, (0.1, 0.145, 0.04), (0, 0.0, -0.01))  # bowl
    panel(bowl, (0.09, 0.13, 0.0015), (0, 0.005, 0.0315), (0.3, 0.5, 0.7),
          collide=False)  # water
    panel(bowl, (0.1, 0.02, 0.015), (0, -0.125, 0.045))  # back joint to the cistern
    cistern = parent.add_body(name=f"{name}_cistern", pos=[-0.004, -0.128, 0.362])
    panel(cistern, (0.1, 0.048, 0.104), (0, 0, 0))
    panel(cistern, (0.015, 0.01, 0.004), (0.06, 0.0, 0.106), (0.7, 0.7, 0.7),
          collide=False)  # flush button
    joint = hinged_door(scene, parent, f"{name}_seat", hinge_pos=TOILET_HINGE, axis=(1, 0, 0),
                        panel_half=(0.1125, 0.1275, 0.0055),
                        panel_offset=(0.0, 0.1275, 0.0055), limits=(0.0, TOILET_SEAT_UP),
                        initial=TOILET_SEAT_UP, friction_torque=0.0, rgba=(0.57, 0.57, 0.57),
                        mass=0.178)
    seat = scene.spec.body(f"{name}_seat")
    scene.spec.joint(joint).damping[0] = 0.002
    grasp_site(seat, f"{name}_seat_center", (0.0, 0.1275, 0.0055))
    for part in ("bowl", "cistern"):
        scene.exclude(f"{name}_seat", f"{name}_{part}")
    return joint


FRIDGE_RGBA = (0.85, 0.85, 1.0)
FRIDGE_HINGE = (0.303, -0.171)  # both doors, root frame (x, y); vertical axes
FRIDGE_TOP_OPEN = 0.6981  # rad, 40 degrees as the model saves it


def fridge(scene: SceneBuilder, parent: mujoco.MjsBody, name: str = "fridge") -> tuple[str, str]:
    """close_fridge's fridge, front towards the root's -x: a static cabinet
    (panels and three shelves, x[0.304, 0.550], y +-0.173, 0.954 m tall)
    and two doors hinged on the right (-y) front edge about +z, positive
    opening: the top door starts open at FRIDGE_TOP_OPEN and is held only by
    RLBench's 0.052 N m motor, the bottom one is closed and stiff (2.64 N m).
    Bodies `<name>_base`, `<name>_door_top`, `<name>_door_bottom`; sites
    `<name>_door_<level>_center`.  Returns the (top, bottom) joint names."""
    base = parent.add_body(name=f"{name}_base", pos=[0.427, 0.0, 0.476])
    panel(base, (0.005, 0.173, 0.477), (0.118, 0, 0), FRIDGE_RGBA)  # back
    for sy in (-1, 1):
        panel(base, (0.123, 0.005, 0.477), (0, sy * 0.168, 0), FRIDGE_RGBA)  # sides
    for z in (-0.472, 0.473):
        panel(base, (0.123, 0.173, 0.005), (0, 0, z), FRIDGE_RGBA)  # floor, roof
    panel(base, (0.123, 0.163, 0.005), (0, 0, -0.262), FRIDGE_RGBA)  # divider
    for x, half_x, z in ((0.452, 0.0955, 0.677), (0.434, 0.115, 0.375), (0.434, 0.115, 0.035)):
        panel(base, (half_x, 0.163, 0.005), (x - 0.427, 0, z - 0.476), (1.0, 1.0, 1.0))  # shelves
    doors = []
    for level, z, half_z, z_off, initial, torque, mass in (
            ("top", 0.670, 0.2725, 0.0055, FRIDGE_TOP_OPEN, 0.0522, 0.0852),
            ("bottom", 0.213, 0.1795, 0.0, 0.0, 2.64, 0.056)):
        joint = hinged_door(scene, parent, f"{name}_door_{level}",
                            hinge_pos=(*FRIDGE_HINGE, z), axis=(0, 0, 1),
                            panel_half=(0.0255, 0.172, half_z), panel_offset=(-0.0255, 0.171, z_off),
                            limits=(0.0, 1.571), initial=initial, friction_torque=torque,
                            rgba=(1.0, 1.0, 1.0), mass=mass)
        door = scene.spec.body(f"{name}_door_{level}")
        # A vertical bar handle on the outer face near the free edge.
        rod(door, (-0.065, 0.30, z_off - 0.1), (-0.065, 0.30, z_off + 0.1), 0.008, (0.6, 0.6, 0.6))
        grasp_site(door, f"{name}_door_{level}_center", (-0.0255, 0.171, z_off))
        scene.exclude(f"{name}_door_{level}", f"{name}_base")
        doors.append(joint)
    scene.exclude(f"{name}_door_top", f"{name}_door_bottom")
    return doors[0], doors[1]
