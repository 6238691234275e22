"""The task API: one declarative class per task, RLBench style.

A task declares its scene (via builders), the objects named in X-ICM's text,
language templates per variation, a jittable initial-state sampler, success
and failure conditions, and expert waypoints relative to its objects.  The
runtime (agnostos_mjx/runtime/) knows nothing task-specific.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp

from agnostos_mjx.sim.actions import KeyActions  # defined there without JAX; re-exported here
from agnostos_mjx.sim.conditions import Condition, never
from agnostos_mjx.sim.math3d import quat_mul, quat_rotate, yaw_quat
from agnostos_mjx.sim.observables import Observation
from agnostos_mjx.sim.visual_state import StateColor
from agnostos_mjx.sim.world import Placement  # defined with the scene it places; re-exported here
from agnostos_mjx.tasks.catalog import Split

TABLE_Z = 0.752
# Centre and extent of RLBench's `workspace` plane.  The centre (0.25, 0) is
# where 33 of 35 task models are saved; the extent is not documented, we use
# 0.6 x 0.7 m (inferred from the action bounds = workspace +-0.2 m).
WORKSPACE_CENTER = (0.25, 0.0)
WORKSPACE_HALF = (0.30, 0.35)
MAX_KEY_ACTIONS = 25


def key_actions(steps: list[tuple[jnp.ndarray, jnp.ndarray, float]], valid=None) -> KeyActions:
    pos = jnp.stack([jnp.asarray(p, jnp.float32) for p, _, _ in steps])
    quat = jnp.stack([jnp.asarray(q, jnp.float32) for _, q, _ in steps])
    grip = jnp.asarray([g for _, _, g in steps], jnp.float32)
    valid = jnp.ones(len(steps), bool) if valid is None else jnp.asarray(valid)
    return KeyActions(pos, quat, grip, valid)


def in_frame(obs: Observation, frame: str, offset=(0.0, 0.0, 0.0)) -> jnp.ndarray:
    """World position of a point given in an observed frame."""
    return obs.pos(frame) + quat_rotate(obs.quat(frame), jnp.asarray(offset, jnp.float32))


def frame_quat(obs: Observation, frame: str, local_quat) -> jnp.ndarray:
    """World orientation of a gripper pose given relative to an observed frame."""
    return quat_mul(obs.quat(frame), jnp.asarray(local_quat, jnp.float32))


def _fits(center, yaw, half_extents, box_center, box_half):
    """Whether a yawed rectangle lies inside an axis-aligned box (2-D)."""
    c, s = jnp.abs(jnp.cos(yaw)), jnp.abs(jnp.sin(yaw))
    hx = c * half_extents[0] + s * half_extents[1]
    hy = s * half_extents[0] + c * half_extents[1]
    return (jnp.abs(center[..., 0] - box_center[0]) <= box_half[0] - hx) & (
        jnp.abs(center[..., 1] - box_center[1]) <= box_half[1] - hy
    )


def _rects_overlap(c1, yaw1, h1, c2, yaw2, h2):
    """Separating-axis test for two yawed rectangles."""
    axes = []
    for yaw in (yaw1, yaw2):
        axes += [jnp.stack([jnp.cos(yaw), jnp.sin(yaw)], -1), jnp.stack([-jnp.sin(yaw), jnp.cos(yaw)], -1)]
    d = c2 - c1

    def radius(yaw, h, axis):
        u = jnp.stack([jnp.cos(yaw), jnp.sin(yaw)], -1)
        v = jnp.stack([-jnp.sin(yaw), jnp.cos(yaw)], -1)
        return h[0] * jnp.abs(jnp.sum(u * axis, -1)) + h[1] * jnp.abs(jnp.sum(v * axis, -1))

    separated = jnp.zeros(jnp.shape(d)[:-1], bool)
    for axis in axes:
        gap = jnp.abs(jnp.sum(d * axis, -1)) - radius(yaw1, h1, axis) - radius(yaw2, h2, axis)
        separated |= gap > 0
    return ~separated


def sample_on_plane(
    key: jax.Array,
    half_extents: tuple[float, float],
    yaw_range: float,
    plane_center=WORKSPACE_CENTER,
    plane_half=WORKSPACE_HALF,
    others: tuple = (),
    min_distance: float = 0.01,
    tries: int = 64,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """RLBench's SpawnBoundary.sample, vectorised: draw `tries` candidates of
    (x, y, yaw), keep the first whose rotated footprint fits the plane and
    neither overlaps nor comes closer than `min_distance` to the `others`
    (each (xy, yaw, half_extents)).  Returns (xy, yaw)."""
    kx, ky, kyaw = jax.random.split(key, 3)
    xy = jnp.stack(
        [
            jax.random.uniform(kx, (tries,), minval=-plane_half[0], maxval=plane_half[0]),
            jax.random.uniform(ky, (tries,), minval=-plane_half[1], maxval=plane_half[1]),
        ],
        -1,
    ) + jnp.asarray(plane_center)
    yaw = jax.random.uniform(kyaw, (tries,), minval=-yaw_range, maxval=yaw_range)
    ok = _fits(xy, yaw, half_extents, plane_center, plane_half)
    for oxy, oyaw, ohalf in others:
        far = jnp.linalg.norm(xy - oxy, axis=-1) >= min_distance
        ok &= far & ~_rects_overlap(xy, yaw, jnp.asarray(half_extents), oxy, oyaw, jnp.asarray(ohalf))
    first = jnp.argmax(ok)  # falls back to candidate 0 if none fits (never seen in tests)
    return xy[first], yaw[first]


def place_root(key: jax.Array, half_extents: tuple[float, float], yaw_range: float,
               offset=(0.0, 0.0)) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Place a task root on the table workspace with a random yaw.

    `offset` is the footprint centre in the root frame (the root itself need not
    be the centre of what it carries).  Returns (root position, root quat)."""
    xy, yaw = sample_on_plane(key, half_extents, yaw_range)
    q = yaw_quat(yaw)
    origin = jnp.concatenate([xy, jnp.array([TABLE_Z])]) - quat_rotate(q, jnp.array([*offset, 0.0]))
    return origin, q


class Task:
    """Base class: subclasses fill in the class attributes and methods."""

    name: ClassVar[str]
    split: ClassVar[Split]
    num_variations: ClassVar[int] = 1
    # Display name used in X-ICM's text -> observed frame (body or site) name.
    objects: ClassVar[dict[str, str]] = {}
    # Frames whose pose is observed (objects' frames are added automatically).
    frames: ClassVar[tuple[str, ...]] = ()
    # Task joints whose position is observed.
    joints: ClassVar[tuple[str, ...]] = ()
    # Bodies the gripper attaches when it closes on them (RLBench's kinematic
    # grasp): free objects, or articulated parts such as drawers, which then
    # stay on their joints.
    graspables: ClassVar[tuple[str, ...]] = ()
    # Frame tested against the attach volume, per graspable (default: the body).
    grasp_points: ClassVar[tuple[str, ...]] = ()
    # Bounding radius around each grasp point, used by the attach test.
    graspable_radius: ClassVar[tuple[float, ...]] = ()
    max_key_actions: ClassVar[int] = MAX_KEY_ACTIONS
    notes: ClassVar[str] = ""

    def descriptions(self, variation: int) -> list[str]:
        raise NotImplementedError

    def build(self, scene) -> None:
        """Add the task's bodies to the scene (a world.SceneBuilder)."""
        raise NotImplementedError

    def sample(self, key: jax.Array, variation: jnp.ndarray) -> Placement:
        raise NotImplementedError

    def success(self, variation: jnp.ndarray) -> Condition:
        raise NotImplementedError

    def failure(self, variation: jnp.ndarray) -> Condition:
        return never()

    def expert(self, obs: Observation, variation: jnp.ndarray) -> KeyActions:
        raise NotImplementedError

    def state_colors(self, variation: jnp.ndarray) -> tuple[StateColor, ...]:
        """Colours that RLBench's task.step() paints during an episode (see
        visual_state.py); none by default."""
        return ()

    @property
    def observed_frames(self) -> tuple[str, ...]:
        frames = list(self.objects.values()) + list(self.frames) + list(self.graspables)
        frames += list(self.grasp_points)
        return tuple(dict.fromkeys(frames))

    @property
    def grasp_frames(self) -> tuple[str, ...]:
        return self.grasp_points or self.graspables

    def __repr__(self) -> str:
        return f"<Task {self.name} ({self.split.value}, {self.num_variations} variations)>"
