"""Table-top pieces for the block family of tasks: flat coloured target
patches, square rings and peg boards, a stick and a broom, the multi-plane
spawn sampler RLBench uses to scatter objects (SpawnBoundary over several
planes) and the experts' square-grasp yaw.

Free blocks, detector volumes (`sensor_volume`), root-frame poses
(`pose_in_root`) and headings (`yaw_of`) are the shared ones of `common`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from agnostos_mjx.sim.math3d import axis_angle_quat, quat_conj, quat_rotate
from agnostos_mjx.sim.world import SceneBuilder
from agnostos_mjx.tasks.base import TABLE_Z, sample_on_plane
from agnostos_mjx.tasks.builders.common import (
    ROBOT_BASE_XY,
    free_body,
    grasp_site,
    square_yaw,
    yaw_of,
)
from agnostos_mjx.tasks.builders.primitives import panel, rod


def flat_patch(parent: mujoco.MjsBody, name: str, pos, half_xy, rgba) -> mujoco.MjsGeom:
    """A coloured target square lying on the table (static, non-respondable:
    objects slide over it).  `pos` is the patch centre on the table."""
    x, y, z = pos
    return panel(parent, (half_xy[0], half_xy[1], 0.0005), (x, y, z + 0.0005), rgba,
                 collide=False, name=name)


def robot_keep_out(root_pos: jnp.ndarray, root_quat: jnp.ndarray, half: float = 0.3):
    """The square around the robot base, in a task root's frame, as an `others`
    entry for the samplers: objects right in front of the base need the arm
    folded at its joint limits, where straight-line moves fail (RLBench
    resamples such scenes when planning fails)."""
    local = quat_rotate(quat_conj(root_quat), jnp.asarray(ROBOT_BASE_XY + (TABLE_Z,)) - root_pos)
    return local[:2], -yaw_of(root_quat), jnp.asarray((half, half))


def spawn_on_planes(key: jax.Array, half_extents, planes, others: tuple = (),
                    min_distance: float = 0.01, yaw_range: float = jnp.pi):
    """RLBench's SpawnBoundary over several planes (each (centre xy, half xy)
    in the root frame): pick a plane with probability proportional to its
    area, then sample a collision-free (xy, yaw) on it.  Returns (xy, yaw)."""
    centers = jnp.asarray([c for c, _ in planes], jnp.float32)
    halves = jnp.asarray([h for _, h in planes], jnp.float32)
    k_plane, k_pose = jax.random.split(key)
    area = halves[:, 0] * halves[:, 1]
    index = jax.random.choice(k_plane, len(planes), p=area / area.sum())
    return sample_on_plane(k_pose, half_extents, yaw_range, plane_center=centers[index],
                           plane_half=halves[index], others=others, min_distance=min_distance)


def square_grasp_yaw(quat: jnp.ndarray, avoid=None) -> jnp.ndarray:
    """A gripper yaw that lines the fingers up with a square object's faces.

    Of the two face pairs, the default is the one needing least wrist turn
    (yaw in [-pi/4, pi/4]); with `avoid` (a world direction, e.g. towards a
    tower next to the object) it is the pair whose closing axis lies most
    across that direction, so the open fingers and the hand, which are long
    along the closing axis, stay clear of it."""
    yaw = square_yaw(yaw_of(quat))
    if avoid is None:
        return yaw
    other = yaw - jnp.sign(yaw + 1e-6) * jnp.pi / 2
    # With yaw a, the gripper's fingers close along world (-sin a, cos a).
    def along(a):
        return jnp.abs(-jnp.sin(a) * avoid[0] + jnp.cos(a) * avoid[1])
    return jnp.where(along(yaw) <= along(other), yaw, other)


def square_ring(scene: SceneBuilder, name: str, outer_half: float, wall: float,
                half_height: float, rgba, mass: float) -> mujoco.MjsBody:
    """A free square frame of four bars (RLBench's square_ring): its hole,
    2 * (outer_half - wall) wide, slides over a square peg."""
    body = free_body(scene, name, pos=(0.0, 0.0, TABLE_Z + half_height))
    mid = outer_half - wall / 2
    for k, (x, y, hx, hy) in enumerate(((mid, 0, wall / 2, outer_half),
                                        (-mid, 0, wall / 2, outer_half),
                                        (0, mid, outer_half - wall, wall / 2),
                                        (0, -mid, outer_half - wall, wall / 2))):
        panel(body, (hx, hy, half_height), (x, y, 0.0), rgba, name=f"{name}_bar{k}").mass = mass / 4
    return body


def peg_board(parent: mujoco.MjsBody, name: str, peg_name: str, base_half, peg_half, peg_x,
              base_rgba, peg_rgba) -> list[str]:
    """A static board centred on its parent's origin with square pegs standing
    on it in a row along x (RLBench's square_base with pillars).  Each peg is
    a body and a geom named `<peg_name><k>`, so samplers can recolour it;
    returns the peg names."""
    panel(parent, base_half, (0.0, 0.0, base_half[2]), base_rgba, name=name)
    pegs = []
    for k, x in enumerate(peg_x):
        peg = parent.add_body(name=f"{peg_name}{k}", pos=[x, 0.0, 2 * base_half[2]])
        panel(peg, peg_half, (0.0, 0.0, peg_half[2]), peg_rgba, name=f"{peg_name}{k}")
        pegs.append(f"{peg_name}{k}")
    return pegs


def stick(scene: SceneBuilder, name: str, half_length: float, half_width: float, rgba,
          mass: float, grip_from_end: float) -> mujoco.MjsBody:
    """A free square-section stick along its local x axis with a site
    `<name>_grasp` `grip_from_end` in from its -x end (where the expert holds it)."""
    body = free_body(scene, name, pos=(0.0, 0.0, TABLE_Z + half_width))
    panel(body, (half_length, half_width, half_width), (0.0, 0.0, 0.0), rgba, name=name).mass = mass
    grasp_site(body, f"{name}_grasp", (-half_length + grip_from_end, 0.0, 0.0))
    return body


def rotation_between(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """The smallest rotation (quat) taking unit vector `a` onto unit vector `b`;
    a held tool turned by it keeps its roll about its own axis."""
    axis = jnp.cross(a, b)
    sin = jnp.linalg.norm(axis)
    angle = jnp.arctan2(sin, jnp.dot(a, b))
    axis = jnp.where(sin > 1e-6, axis / jnp.maximum(sin, 1e-6), jnp.array([0.0, 0.0, 1.0]))
    return axis_angle_quat(axis, angle)


def broom(scene: SceneBuilder, name: str, head_half, handle_length: float, lean: float,
          grip_height: float, rgba, mass: float) -> mujoco.MjsBody:
    """A free broom whose frame sits at the middle of its head's underside.
    The head is level in the broom frame; the handle leans by `lean` (rad)
    towards the frame's +y, so the broom rests against a holder on that side.
    Sites `<name>_grasp` (on the handle axis at `grip_height` above the floor
    of the head) and `<name>_head` (head underside) locate it for experts."""
    body = free_body(scene, name, pos=(0.0, 0.0, TABLE_Z))
    head = panel(body, head_half, (0.0, 0.0, head_half[2]), rgba, name=f"{name}_head")
    head.mass = 0.7 * mass
    axis = np.array([0.0, np.sin(lean), np.cos(lean)])
    start = np.array([0.0, 0.0, 2 * head_half[2]])
    handle = rod(body, start, start + handle_length * axis, 0.012, rgba, collide=True,
                 name=f"{name}_handle")
    handle.mass = 0.3 * mass
    grip = start + (grip_height - start[2]) / axis[2] * axis
    grasp_site(body, f"{name}_grasp", grip)
    grasp_site(body, f"{name}_head", (0.0, 0.0, 0.0))
    return body
