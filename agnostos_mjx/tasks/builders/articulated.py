"""Articulated pieces: spring push buttons, drawer chests and hinged doors."""

from __future__ import annotations

import mujoco
import numpy as np

from agnostos_mjx.sim.world import SceneBuilder
from agnostos_mjx.tasks.builders.common import grasp_site
from agnostos_mjx.tasks.builders.primitives import WHITE, WOOD, disc, panel, rod


def push_button(scene: SceneBuilder, parent: mujoco.MjsBody, name: str, pos=(0.0, 0.0, 0.0), *,
                base_half=(0.05, 0.05, 0.0105), base_rgba=(0.5, 0.0, 0.0),
                plate_radius: float = 0.028, plate_top: float = 0.029, wrap_height: float = 0.010,
                travel=(-0.007, 0.003), rest: float = 0.003, stiffness: float = 250.0,
                damping: float = 6.25, plate_rgba=(1.0, 0.0, 0.0)) -> str:
    """A spring-loaded push button (RLBench's target_button): a static base,
    and a plate + ring on a vertical prismatic joint held at `rest` by a
    spring (CoppeliaSim's spring-like position control, K and C as there).
    `plate_top` is the plate's top height above `pos` when the joint is at
    `rest`.  Returns the joint name."""
    x, y, z = pos
    panel(parent, base_half, (x, y, z + base_half[2] - 0.002), base_rgba, name=f"{name}_base")
    plate = parent.add_body(name=f"{name}_plate", pos=[x, y, z], gravcomp=1.0)
    plate.add_joint(name=f"{name}_joint", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1],
                    range=list(travel), stiffness=stiffness, springref=rest, damping=damping,
                    armature=0.01)
    top = plate_top - rest
    disc(plate, plate_radius, 0.001, (0, 0, top - 0.001), plate_rgba, name=f"{name}_top")
    disc(plate, plate_radius * 0.999, wrap_height / 2, (0, 0, top - wrap_height / 2), plate_rgba,
         name=f"{name}_wrap")
    half = plate_radius / np.sqrt(2.0)
    geom = panel(plate, (half, half, 0.004), (0, 0, top - 0.004), plate_rgba)
    geom.mass = 0.05
    geom.rgba = [0, 0, 0, 0]
    scene.initial_joints[f"{name}_joint"] = rest
    return f"{name}_joint"


def drawer_chest(scene: SceneBuilder, parent: mujoco.MjsBody, name: str, *,
                 levels=("bottom", "middle", "top"), width: float = 0.38,
                 depth: float = 0.38, drawer_height: float = 0.118, floor_z: float = 0.089,
                 travel: float = 0.30, rgba=WOOD) -> list[str]:
    """A chest of drawers whose fronts face the root's +y (RLBench's drawer
    model): a static frame on legs and one free-sliding drawer per level with
    a bar handle.  Adds a site `<name>_handle_<level>` at each handle (where
    RLBench's waypoint anchors sit) and returns the joint names."""
    hw, hd, t = width / 2, depth / 2, 0.01
    top_z = floor_z + len(levels) * (drawer_height + 0.002) + 0.008
    mid_z = (floor_z + top_z) / 2
    half_h = (top_z - floor_z) / 2
    panel(parent, (hw, t, half_h), (0, -hd + t, mid_z), rgba)  # back
    panel(parent, (t, hd, half_h), (-hw + t, 0, mid_z), rgba)  # sides
    panel(parent, (t, hd, half_h), (hw - t, 0, mid_z), rgba)
    panel(parent, (hw, hd, t / 2), (0, 0, top_z - t / 2), rgba)  # top
    panel(parent, (hw, hd, t / 2), (0, 0, floor_z + t / 2), rgba)  # bottom
    for sx in (-1, 1):
        for sy in (-1, 1):
            rod(parent, (sx * (hw - 0.02), sy * (hd - 0.02), 0.0),
                (sx * (hw - 0.02), sy * (hd - 0.02), floor_z), 0.012, (0.8, 0.8, 0.8))
    joints = []
    inner = hw - 2 * t - 0.004
    for i, level in enumerate(levels):
        z0 = floor_z + t + 0.002 + i * (drawer_height + 0.002)
        zc = z0 + drawer_height / 2
        body = parent.add_body(name=f"{name}_{level}", pos=[0, 0, 0])
        body.add_joint(name=f"{name}_joint_{level}", type=mujoco.mjtJoint.mjJNT_SLIDE,
                       axis=[0, 1, 0], range=[0, travel], damping=2.0, armature=0.05)
        hh = drawer_height / 2 - 0.004
        panel(body, (inner, 0.005, hh), (0, hd - 0.005, zc), WHITE)  # front
        panel(body, (inner, hd - 0.03, 0.004), (0, 0.0, z0 + 0.006), WHITE)  # floor
        panel(body, (0.004, hd - 0.03, hh * 0.6), (-inner + 0.004, 0.0, zc - hh * 0.3), WHITE)
        panel(body, (0.004, hd - 0.03, hh * 0.6), (inner - 0.004, 0.0, zc - hh * 0.3), WHITE)
        panel(body, (inner, 0.004, hh * 0.6), (0, -hd + 0.03, zc - hh * 0.3), WHITE)  # back
        # Handle: a bar in front of the face on two standoffs.
        panel(body, (0.07, 0.007, 0.007), (0, hd + 0.016, zc), (0.3, 0.3, 0.3))
        for sx in (-1, 1):
            panel(body, (0.006, 0.006, 0.006), (sx * 0.064, hd + 0.004, zc), (0.3, 0.3, 0.3))
        grasp_site(body, f"{name}_handle_{level}", (0, hd + 0.016, zc))
        body.gravcomp = 0.0
        joints.append(f"{name}_joint_{level}")
    names = [f"{name}_{lv}" for lv in levels]
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            scene.exclude(a, b)
    return joints


def hinged_door(scene: SceneBuilder, parent: mujoco.MjsBody, name: str, *, hinge_pos, axis,
                panel_half, panel_offset, limits, initial: float, friction_torque: float,
                rgba=WHITE, mass: float = 0.17) -> str:
    """A door on a revolute joint whose motor holds it with a limited torque
    (CoppeliaSim velocity control at zero speed ~ MuJoCo joint friction).
    `panel_offset` places the panel relative to the hinge in the closed pose.
    Returns the joint name."""
    body = parent.add_body(name=name, pos=list(hinge_pos))
    body.add_joint(name=f"{name}_joint", type=mujoco.mjtJoint.mjJNT_HINGE, axis=list(axis),
                   range=list(limits), frictionloss=friction_torque, damping=0.5, armature=0.02)
    geom = panel(body, panel_half, panel_offset, rgba, name=f"{name}_panel")
    geom.mass = mass
    scene.initial_joints[f"{name}_joint"] = initial
    return f"{name}_joint"
