"""Small helpers every builder family and task shares: free bodies, sensor
volumes, poses given in a task root's frame, headings, top-down grasps, and
spawning objects on a plane of the task root.

Why these exist: RLBench carries objects by a kinematic attach and checks
success with proximity-sensor volumes; here a graspable is a free body (held
by a weld on close, see runtime/key_action.py) and a volume is an invisible box site read
by `conditions.Detected`.  MuJoCo free joints must hang off the world body, so
a task creates its free bodies at the origin and its sampler places them in
world coordinates by composing the task root's pose with a local one.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import mujoco

from agnostos_mjx.sim.math3d import axis_angle_quat, euler_xyz_quat, quat_mul, quat_rotate, yaw_quat
from agnostos_mjx.sim.world import SceneBuilder
from agnostos_mjx.tasks.base import sample_on_plane
from agnostos_mjx.tasks.builders.primitives import panel

IDENTITY = (1.0, 0.0, 0.0, 0.0)
# Sites of this group are hidden by the default visualisation (groups 0-2 show).
HIDDEN_GROUP = 4
# The gripper pointing down with its fingers closing along the y axis of the
# frame it is composed with (the world's, or a root's via `frame_quat`).
DOWN = euler_xyz_quat(jnp.pi, 0.0, jnp.pi)
# Pointing down with the fingers across DOWN's: they close along the world/root x axis.
DOWN_ACROSS = euler_xyz_quat(jnp.pi, 0.0, jnp.pi / 2)
# Panda link0 on the table (spec section 2).
ROBOT_BASE_XY = (-0.268, -0.006)

Pose = tuple[jnp.ndarray, jnp.ndarray]


# ---- free bodies ----------------------------------------------------------------------------
def free_body(scene: SceneBuilder, name: str, *, pos=(0.0, 0.0, 0.0), joint: str = "",
              damping: float = 0.0, gravcomp: float = 0.0) -> mujoco.MjsBody:
    """A dynamic body on a free joint, parented to the world (free joints
    cannot hang under a mocap root).  Its sampler sets its world pose every
    episode, so `pos` only matters for the model's default state.  `joint`
    names the free joint (unnamed by default); `damping` slows all six DoFs
    (e.g. a light prop that must not bounce); `gravcomp` 1 makes it float."""
    body = scene.world.add_body(name=name, pos=list(pos), gravcomp=gravcomp)
    body.add_freejoint(name=joint).damping = [damping, 0.0, 0.0]
    return body


def free_box(scene: SceneBuilder, name: str, half, rgba, mass: float, *,
             geom: str | None = None, friction: float | None = None,
             pos=(0.0, 0.0, 0.0)) -> mujoco.MjsBody:
    """A free cuboid of half sizes `half` and an explicit `mass` (RLBench's
    dynamic, respondable cuboid: a block, a grocery box).  Its geom is called
    `geom`, by default `name`, so samplers can recolour it by name;
    `friction` overrides the sliding friction (default torsional/rolling)."""
    body = free_body(scene, name, pos=pos)
    box = panel(body, half, (0.0, 0.0, 0.0), rgba, name=name if geom is None else geom)
    box.mass = mass
    if friction is not None:
        box.friction = [friction, 0.005, 0.0001]
    return body


# ---- sensor volumes -------------------------------------------------------------------------
def sensor_volume(body: mujoco.MjsBody, name: str, pos, half, *, quat=IDENTITY,
                  rgba=(0.0, 1.0, 0.0, 0.0)) -> str:
    """An invisible box site standing for an RLBench proximity-sensor volume,
    centred at `pos` in `body`'s frame.  `Detected` reads its pose; pass it
    the same `half` sizes.  Returns the site name (list it in a task's
    observed frames).  Give `rgba` an alpha to see it in the MuJoCo viewer
    (group 4 is hidden from rendered observations)."""
    body.add_site(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, pos=list(pos), quat=list(quat),
                  size=list(half), rgba=list(rgba), group=HIDDEN_GROUP)
    return name


def grasp_site(body: mujoco.MjsBody, name: str, pos) -> str:
    """An invisible point marker (RLBench's dummies, e.g. `*_grasp_point`)
    at `pos` in `body`'s frame: where the expert puts the tip, the point the
    attach test checks, or a point a task observes.  Returns the site name."""
    body.add_site(name=name, pos=list(pos), size=[0.005, 0, 0], rgba=[0, 1, 0, 0],
                  group=HIDDEN_GROUP)
    return name


# ---- poses ----------------------------------------------------------------------------------
def pose_in_root(root_pos: jnp.ndarray, root_quat: jnp.ndarray, local_pos,
                 local_quat=IDENTITY) -> Pose:
    """World pose of a pose (`local_pos`, `local_quat`) given in the frame
    (`root_pos`, `root_quat`), e.g. a free body's resting pose in its task
    root.  For an upright local pose of heading `yaw`, pass `yaw_quat(yaw)`."""
    local_pos = jnp.asarray(local_pos, jnp.float32)
    return (root_pos + quat_rotate(root_quat, local_pos),
            quat_mul(root_quat, jnp.asarray(local_quat, jnp.float32)))


def yaw_of(quat) -> jnp.ndarray:
    """Heading of a frame about the world z axis: the angle of its x axis
    projected on the table (for an upright frame, its rotation about z)."""
    w, x, y, z = (quat[..., i] for i in range(4))
    return jnp.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def nearest_yaw(angle, ref, period: float):
    """The angle equal to `angle` modulo `period` nearest `ref` (an object's
    heading up to its grasp symmetry, as close as possible to the natural
    yaw); `ref` itself for period 0 (an object any yaw suits)."""
    if period == 0.0:
        return ref
    return ref + (angle - ref) - period * jnp.round((angle - ref) / period)


def square_yaw(yaw, symmetry: float = jnp.pi / 2) -> jnp.ndarray:
    """The yaw in [-symmetry/2, symmetry/2) equivalent to `yaw` for an object
    with `symmetry`-fold rotational symmetry (a square face pair: pi/2; a
    two-finger grasp: pi): lines the fingers up with the faces without
    twisting the wrist far from its start pose."""
    return jnp.mod(yaw + symmetry / 2, symmetry) - symmetry / 2


def down_grasp(yaw=0.0, pitch=0.0, *, wrap: bool = True) -> jnp.ndarray:
    """Gripper pointing down with its fingers closing along the heading `yaw`
    + 90 deg (the y axis of a frame with that yaw).

    The two-finger grasp is symmetric under a half turn, so by default the
    yaw is wrapped into +-90 deg of the start pose, which keeps the wrist
    joint far from its limits; `wrap=False` keeps `yaw` as given (for a
    motion that turns the wrist continuously, e.g. a tap).  `pitch` tilts the
    approach axis about the fingers towards the frame's +x (pi/2: level,
    pointing along +x), e.g. to lay a held object down."""
    yaw = jnp.asarray(yaw, jnp.float32)
    wrapped = square_yaw(yaw, jnp.pi) if wrap else yaw
    same = jnp.cos(wrapped - yaw)  # +1, or -1 where the wrap turned the frame
    tilt = axis_angle_quat(jnp.array([0.0, 1.0, 0.0]), -same * jnp.asarray(pitch, jnp.float32))
    return quat_mul(yaw_quat(wrapped), quat_mul(tilt, DOWN))


def natural_yaw(pos) -> jnp.ndarray:
    """The heading from the robot base to the point `pos`: the gripper yaw
    the arm reaches there without turning its wrist far."""
    return jnp.arctan2(pos[..., 1] - ROBOT_BASE_XY[1], pos[..., 0] - ROBOT_BASE_XY[0])


# ---- spawning -------------------------------------------------------------------------------
def spawn_on_root_plane(key: jax.Array, root: Pose, half_extents, plane_center, plane_half, *,
                        yaw_range: float = jnp.pi, others: tuple = (),
                        min_distance: float = 0.01, height: float = 0.0,
                        offset: tuple[float, float] | None = None, tries: int = 64) -> Pose:
    """RLBench's SpawnBoundary for one object on a plane of the task root
    (`plane_center`, `plane_half` in the root frame): a heading within
    +-`yaw_range` and a spot where its footprint (`half_extents`, centred
    `offset` from the object's origin) lies inside the plane, clear of the
    `others` ((xy, yaw, half_extents) in the root frame).  Returns the
    object's world pose, its origin `height` above the plane."""
    xy, yaw = sample_on_plane(key, half_extents, yaw_range, plane_center=plane_center,
                              plane_half=plane_half, others=others, min_distance=min_distance,
                              tries=tries)
    return _on_root_plane(root, xy, yaw, height, offset)


def spawn_many_on_root_plane(key: jax.Array, root: Pose, footprints: Sequence, plane_center,
                             plane_half, *, heights: float | Sequence[float] = 0.0,
                             yaw_range: float = jnp.pi, min_distance: float = 0.01,
                             tries: int = 64) -> list[Pose]:
    """Several objects spawned one after the other on a root plane (as
    `spawn_on_root_plane`), each clear of those before it: one footprint
    (half extents) per object, and the height of each origin above the
    plane (one for all, or one each).  Returns their world poses."""
    if isinstance(heights, int | float):
        heights = [heights] * len(footprints)
    placed, poses = [], []
    for k, half, height in zip(jax.random.split(key, len(footprints)), footprints, heights):
        xy, yaw = sample_on_plane(k, half, yaw_range, plane_center=plane_center,
                                  plane_half=plane_half, others=tuple(placed),
                                  min_distance=min_distance, tries=tries)
        placed.append((xy, yaw, jnp.asarray(half)))
        poses.append(_on_root_plane(root, xy, yaw, height, None))
    return poses


def _on_root_plane(root: Pose, xy: jnp.ndarray, yaw: jnp.ndarray, height: float,
                   offset: tuple[float, float] | None) -> Pose:
    """World pose of an object whose footprint centre sits at `xy` of the
    root plane with heading `yaw` (its origin `offset` back from that centre)."""
    quat = yaw_quat(yaw)
    local = jnp.array([xy[0], xy[1], height])
    if offset is not None:
        local = local - quat_rotate(quat, jnp.array([*offset, 0.0]))
    return pose_in_root(*root, local, quat)


__all__ = ["DOWN", "HIDDEN_GROUP", "IDENTITY", "ROBOT_BASE_XY", "Pose", "down_grasp", "free_body",
           "free_box", "grasp_site", "natural_yaw", "nearest_yaw", "pose_in_root", "sensor_volume",
           "spawn_many_on_root_plane", "spawn_on_root_plane", "square_yaw", "yaw_of"]
