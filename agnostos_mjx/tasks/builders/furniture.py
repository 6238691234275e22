"""Furniture and loose objects for the seen pick-and-place / articulated tasks:
a two-handle tap, a wine rack and bottle, a cupboard with groceries, and a
shape sorter with its shapes (free bodies, sensor volumes, grasp sites and
the experts' yaw helpers: see `common`).

Everything is built from primitive geoms (boxes for contact; visual cylinders
where the original is round), see `primitives`.
"""

from __future__ import annotations

import mujoco
import numpy as np

from agnostos_mjx.sim.world import SceneBuilder
from agnostos_mjx.tasks.builders.common import free_body, grasp_site
from agnostos_mjx.tasks.builders.primitives import WHITE, WOOD, disc, panel, rod

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
        grasp_site(handle, f"tap_{side}_grasp", (0.0, 0.0, bar_z))
        scene.exclude(parent.name, f"tap_{side}")
        joints.append(f"{side}_joint")
    return joints[0], joints[1]


CREAM = (0.99, 0.93, 0.74)
GLASS_BROWN = (0.41, 0.23, 0.11)


def octagonal_prism(body: mujoco.MjsBody, radius: float, half_length: float, pos, rgba,
                    mass: float, name: str = "") -> None:
    """A round part that must stand and roll on boxes: a visual cylinder plus
    a regular octagonal collision prism about the body's z axis (MJX-jax has
    no cylinder-box contacts).  The octagon is the union of four slabs
    (apothem x apothem*tan(22.5 deg)) turned 45 degrees apart."""
    disc(body, radius, half_length, pos, rgba, name=name)
    apothem = 0.98 * radius
    for k in range(4):
        yaw = k * np.pi / 4
        geom = panel(body, (apothem, apothem * np.tan(np.pi / 8), half_length), pos, rgba,
                     quat=(np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)))
        geom.rgba = [0, 0, 0, 0]
        geom.mass = mass / 4
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


def holed_plate(body: mujoco.MjsBody, half: tuple[float, float], z: float, thickness: float,
                holes, rgba) -> int:
    """A horizontal plate (centred on the body's x, y, top at `z`) with
    rectangular holes ((cx, cy, hx, hy), overlaps allowed), built from boxes:
    the plate is cut into columns at every hole edge; each column gets a box
    for every y-interval not covered by a hole.  Neighbouring columns with
    the same intervals are merged.  Returns the number of boxes."""
    xs = sorted({-half[0], half[0], *(min(max(c + s * h, -half[0]), half[0])
                                      for c, _, h, _ in holes for s in (-1, 1))})
    columns: list[tuple[float, float, list[tuple[float, float]]]] = []
    for x0, x1 in zip(xs[:-1], xs[1:]):
        xm = (x0 + x1) / 2
        cuts = sorted((cy - hy, cy + hy) for cx, cy, hx, hy in holes if abs(xm - cx) < hx)
        solid, y = [], -half[1]
        for lo, hi in cuts:
            if lo > y:
                solid.append((y, min(lo, half[1])))
            y = max(y, hi)
        if y < half[1]:
            solid.append((y, half[1]))
        if columns and columns[-1][2] == solid:
            columns[-1] = (columns[-1][0], x1, solid)
        else:
            columns.append((x0, x1, solid))
    count = 0
    for x0, x1, solid in columns:
        for y0, y1 in solid:
            panel(body, ((x1 - x0) / 2, (y1 - y0) / 2, thickness / 2),
                  ((x0 + x1) / 2, (y0 + y1) / 2, z - thickness / 2), rgba)
            count += 1
    return count


def shape_sorter(parent: mujoco.MjsBody, name: str, holes, *, half: float = 0.089,
                 height: float = 0.143, wall: float = 0.01, rgba=(0.8, 0.6, 0.4),
                 lid_rgba=(0.89, 0.79, 0.67)) -> mujoco.MjsBody:
    """A static shape-sorter box standing on the table (four walls, the
    table as its floor) with a lid cut by `holes` (see `holed_plate`,
    positions relative to the box centre).  Returns the box body (`name`)."""
    body = parent.add_body(name=name)
    lid = 0.012
    wall_half_z = (height - lid) / 2
    for sx in (-1, 1):
        panel(body, (wall / 2, half, wall_half_z), (sx * (half - wall / 2), 0.0, wall_half_z), rgba)
        panel(body, (half - wall, wall / 2, wall_half_z), (0.0, sx * (half - wall / 2),
                                                              wall_half_z), rgba)
    holed_plate(body, (half, half), height, lid, holes, lid_rgba)
    return body


def _prism_sides(body, length: float, width: float, height: float, rgba, mass: float) -> None:
    """A triangular prism along x (base `width` on the table, apex `height`
    up) from three boxes: a base slab and two slanted side slabs."""
    t = 0.004
    panel(body, (length / 2, width / 2, t / 2), (0.0, 0.0, -height / 2 + t / 2), rgba).mass = mass / 3
    slant = np.arctan2(height, width / 2)
    side = np.hypot(height, width / 2)
    for sy in (-1, 1):
        angle = -sy * slant  # the slab's long axis runs from the base edge up to the apex
        panel(body, (length / 2, side / 2, t / 2), (0.0, sy * width / 4, 0.0), rgba,
              quat=(np.cos(angle / 2), np.sin(angle / 2), 0.0, 0.0)).mass = mass / 3


def sorter_shape(scene: SceneBuilder, kind: str, name: str, rgba, mass: float = 0.1) -> float:
    """A free shape for the shape sorter, its body frame at its centre:
    'cube', 'cylinder', 'triangular_prism', 'star' or 'moon'.  Returns its
    half height (the centre's height above the table when it lies flat)."""
    body = free_body(scene, name)
    if kind == "cube":
        panel(body, (0.021, 0.021, 0.021), (0, 0, 0), rgba).mass = mass
        return 0.021
    if kind == "cylinder":
        octagonal_prism(body, 0.0225, 0.021, (0, 0, 0), rgba, mass)
        return 0.021
    if kind == "triangular_prism":
        _prism_sides(body, 0.046, 0.039, 0.039, rgba, mass)
        return 0.0195
    if kind == "star":
        half = 0.015
        for k in range(5):  # five rays around a hub, visual
            yaw = 2 * np.pi * k / 5 + np.pi / 2
            quat = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
            panel(body, (0.013, 0.006, half), (0.012 * np.cos(yaw), 0.012 * np.sin(yaw), 0),
                  rgba, collide=False, quat=quat)
        panel(body, (0.013, 0.013, half), (0, 0, 0), rgba).mass = mass  # RLBench's small proxy
        return half
    if kind == "moon":
        half = 0.012
        for yaw in (-0.9, 0.0, 0.9):  # a crescent of three segments, tips along x, visual
            quat = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
            panel(body, (0.011, 0.006, half), (0.017 * np.sin(yaw), 0.017 * (1 - np.cos(yaw)), 0),
                  rgba, collide=False, quat=quat)
        panel(body, (0.015, 0.0085, half), (0, 0, 0), rgba).mass = mass  # RLBench's proxy
        return half
    raise ValueError(f"unknown sorter shape {kind!r}")


def cupboard(parent: mujoco.MjsBody, name: str, *, depth: float = 0.20, width: float = 0.36,
             height: float = 0.50, shelf_z: float = 0.26, board: float = 0.015,
             rgba=WHITE) -> tuple[float, float]:
    """A static cupboard standing on the table, open towards the parent's -x
    (front face at x = 0), with a bottom compartment and a shelf at `shelf_z`.
    Returns the bottom compartment's floor height and clear height."""
    hd, hw = depth / 2, width / 2
    body = parent.add_body(name=name)
    panel(body, (hd, hw, board / 2), (hd, 0.0, board / 2), rgba)  # floor (bottom shelf)
    panel(body, (hd, hw, board / 2), (hd, 0.0, height - board / 2), rgba)  # top
    panel(body, (hd - board / 2, hw - board, board / 2), (hd + board / 2, 0.0, shelf_z), rgba)
    panel(body, (board / 2, hw, height / 2), (depth - board / 2, 0.0, height / 2), rgba)  # back
    for sy in (-1, 1):
        panel(body, (hd, board / 2, height / 2), (hd, sy * (hw - board / 2), height / 2), rgba)
    return board, shelf_z - board / 2 - board


def grocery(scene: SceneBuilder, name: str, size, rgba, round_: bool = False,
            mass: float = 0.1) -> mujoco.MjsBody:
    """A free grocery item standing upright, its body frame at its centre:
    a box of full `size` (x, y, z; keep the thinner side along y, where the
    fingers close), or with `round_` a can of diameter size[0]."""
    body = free_body(scene, name)
    half = [v / 2 for v in size]
    if round_:
        octagonal_prism(body, half[0], half[2], (0.0, 0.0, 0.0), rgba, mass, name=f"{name}_visual")
        disc(body, half[0] * 1.01, 0.004, (0.0, 0.0, half[2] - 0.004), CHROME)  # lid
    else:
        panel(body, half, (0.0, 0.0, 0.0), rgba, name=f"{name}_visual").mass = mass
        panel(body, (half[0] * 0.7, half[1] * 1.02, half[2] * 0.4), (0.0, 0.0, 0.0),
              (0.95, 0.95, 0.95), collide=False)  # label band
    return body


__all__ = ["CHROME", "CREAM", "WHITE", "WOOD", "cupboard", "disc",
           "grocery", "holed_plate", "octagonal_prism", "rod", "shape_sorter",
           "sorter_shape", "two_handle_tap", "wine_bottle", "wine_rack"]
