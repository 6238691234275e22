"""Furniture and loose objects for the seen pick-and-place / articulated tasks:
free graspable bodies, sensor volumes, a two-handle tap, a wine rack, a
cupboard and a shape sorter with its shapes.

Everything is built from primitive geoms (boxes for contact; visual cylinders
where the original is round), see `primitives`.
"""

from __future__ import annotations

import mujoco
import numpy as np

from agnostos_mjx.tasks.builders.primitives import WHITE, WOOD, disc, panel, rod
from agnostos_mjx.world import SceneBuilder


def free_body(scene: SceneBuilder, name: str) -> mujoco.MjsBody:
    """A dynamic body on a free joint; its pose is set by the sampler
    (Placement.bodies) and it is meant to be added to a task's graspables."""
    body = scene.world.add_body(name=name)
    body.add_freejoint()
    return body


def free_box(scene: SceneBuilder, name: str, half, rgba, mass: float) -> mujoco.MjsBody:
    """A free cuboid of the given half sizes and mass (a block, a grocery box)."""
    body = free_body(scene, name)
    panel(body, half, (0.0, 0.0, 0.0), rgba, name=f"{name}_geom").mass = mass
    return body


def sensor_volume(body: mujoco.MjsBody, name: str, half, pos=(0.0, 0.0, 0.0)) -> str:
    """An invisible box site standing for an RLBench proximity sensor volume
    (tested by conditions.Detected with the same half sizes)."""
    body.add_site(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half), pos=list(pos),
                  rgba=[0.0, 1.0, 0.0, 0.0], group=4)
    return name


CHROME = (0.75, 0.75, 0.78)


def two_handle_tap(scene: SceneBuilder, parent: mujoco.MjsBody, *, spacing: float = 0.12,
                   pedestal_height: float = 0.08, bar_half=(0.045, 0.008, 0.008),
                   rgba=CHROME, handle_rgba=WHITE) -> tuple[str, str]:
    """A two-handle tap standing on the table: a base plate, a column whose
    spout points along the parent's -x, and two bar handles on pedestals at
    y = +spacing (left, seen from the spout's side) and -spacing (right),
    each on a free-turning vertical hinge (`left_joint`, `right_joint`, as in
    RLBench).  Handle bodies are `tap_left` / `tap_right`; a site
    `tap_<side>_grasp` marks the bar centre.  Returns the joint names."""
    panel(parent, (0.04, spacing + 0.04, 0.01), (0.0, 0.0, 0.01), rgba, name="tap_base")
    disc(parent, 0.02, 0.09, (0.0, 0.0, 0.11), rgba)
    panel(parent, (0.014, 0.014, 0.09), (0.0, 0.0, 0.11), rgba).rgba = [0, 0, 0, 0]
    rod(parent, (0.0, 0.0, 0.19), (-0.12, 0.0, 0.19), 0.012, rgba, name="tap_spout")
    rod(parent, (-0.12, 0.0, 0.19), (-0.12, 0.0, 0.16), 0.012, rgba)
    joints = []
    for side, y in (("left", spacing), ("right", -spacing)):
        disc(parent, 0.018, pedestal_height / 2, (0.0, y, pedestal_height / 2), rgba)
        panel(parent, (0.012, 0.012, pedestal_height / 2), (0.0, y, pedestal_height / 2),
              rgba).rgba = [0, 0, 0, 0]
        handle = parent.add_body(name=f"tap_{side}", pos=[0.0, y, pedestal_height])
        handle.add_joint(name=f"{side}_joint", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1],
                         damping=0.2, frictionloss=0.05, armature=0.005)
        bar_z = 0.012 + bar_half[2]
        disc(handle, 0.015, 0.01, (0.0, 0.0, 0.01), handle_rgba)
        panel(handle, bar_half, (0.0, 0.0, bar_z), handle_rgba, name=f"tap_{side}_bar").mass = 0.05
        for sx in (-1, 1):  # rounded bar ends
            disc(handle, bar_half[1] * 1.6, bar_half[2] * 1.2,
                 (sx * bar_half[0], 0.0, bar_z), handle_rgba)
        handle.add_site(name=f"tap_{side}_grasp", pos=[0.0, 0.0, bar_z], size=[0.005, 0, 0],
                        rgba=[0, 1, 0, 0], group=4)
        scene.exclude(parent.name, f"tap_{side}")
        joints.append(f"{side}_joint")
    return joints[0], joints[1]


CREAM = (0.99, 0.93, 0.74)
GLASS_BROWN = (0.41, 0.23, 0.11)


def octagonal_prism(body: mujoco.MjsBody, radius: float, half_length: float, pos, rgba,
                    mass: float, name: str = "") -> None:
    """A round part that must stand and roll on boxes: a visual cylinder plus
    an octagonal collision prism (two boxes, one turned 45 degrees) about the
    body's z axis (MJX-jax has no cylinder-box contacts)."""
    disc(body, radius, half_length, pos, rgba, name=name)
    apothem = radius * 0.96
    for k, yaw in enumerate((0.0, np.pi / 4)):
        geom = panel(body, (apothem, apothem, half_length), pos, rgba,
                     quat=(np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)))
        geom.rgba = [0, 0, 0, 0]
        geom.mass = mass / 2
        if k == 0 and name:
            geom.name = f"{name}_collision"


def wine_bottle(scene: SceneBuilder, name: str = "wine_bottle", *, radius: float = 0.033,
                height: float = 0.246, mass: float = 0.543) -> mujoco.MjsBody:
    """A free wine bottle (RLBench's: 0.066 m across, 0.246 m tall, 0.543 kg)
    whose body frame is at its centre, axis along its z, the neck towards +z."""
    body = free_body(scene, name)
    body_half = 0.35 * height
    octagonal_prism(body, radius, body_half, (0.0, 0.0, -height / 2 + body_half), GLASS_BROWN,
                    0.85 * mass, name=f"{name}_body")
    neck_half = (height - 2 * body_half) / 2
    neck_z = height / 2 - neck_half
    disc(body, 0.35 * radius, neck_half, (0.0, 0.0, neck_z), GLASS_BROWN)
    panel(body, (0.012, 0.012, neck_half), (0.0, 0.0, neck_z), GLASS_BROWN,
          name=f"{name}_neck").mass = 0.15 * mass
    return body


def wine_rack(scene: SceneBuilder, parent: mujoco.MjsBody, name: str, slots_x, *,
              y_range=(0.154, 0.396), x_range=(-0.114, 0.215), base_top: float = 0.061,
              rail_top: float = 0.087, divider_top: float = 0.132, gap: float = 0.04,
              rgba=CREAM) -> None:
    """A static bottle rack: a base slab, rails along y with a `gap` under
    each slot (a bottle of radius r rests with its axis about
    sqrt(r^2 - (gap/2)^2) above `rail_top`), and low dividers between slots.
    Adds bodies `<name>_bottom` (base) and `<name>_top` (rails, dividers)."""
    cy, hy = (y_range[0] + y_range[1]) / 2, (y_range[1] - y_range[0]) / 2
    cx, hx = (x_range[0] + x_range[1]) / 2, (x_range[1] - x_range[0]) / 2
    bottom = parent.add_body(name=f"{name}_bottom")
    panel(bottom, (hx, hy, (base_top - 0.007) / 2), (cx, cy, (base_top + 0.007) / 2), rgba)
    top = parent.add_body(name=f"{name}_top")
    edges = [x_range[0]] + [e for x in sorted(slots_x) for e in (x - gap / 2, x + gap / 2)]
    edges.append(x_range[1])
    rail_half_z = (rail_top - base_top) / 2
    for lo, hi in zip(edges[0::2], edges[1::2]):
        panel(top, ((hi - lo) / 2, hy, rail_half_z), ((lo + hi) / 2, cy, base_top + rail_half_z),
              rgba)
    xs = sorted(slots_x)
    for a, b in zip(xs[:-1], xs[1:]):
        panel(top, (0.004, hy, (divider_top - rail_top) / 2),
              ((a + b) / 2, cy, (rail_top + divider_top) / 2), rgba)


__all__ = ["CHROME", "CREAM", "WHITE", "WOOD", "disc", "free_body", "free_box", "octagonal_prism",
           "rod", "sensor_volume", "two_handle_tap", "wine_bottle", "wine_rack"]
