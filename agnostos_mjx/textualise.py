"""X-ICM textualisation: poses and objects as the integers and strings the LLM sees.

Conventions (X-ICM / RoboPrompt ``utils.py``, PerAct settings):

* Workspace ``SCENE_BOUNDS = (x_min, y_min, z_min, x_max, y_max, z_max)`` in metres, cut into
  ``VOXEL_SIZE = 100`` bins per axis (1 cm). A position becomes 3 voxel indices 0..99 and
  decodes to the voxel centre.
* Rotations are discretised at ``ROTATION_RESOLUTION = 5`` degrees as extrinsic x-y-z Euler
  angles (scipy ``as_euler('xyz', degrees=True)``), shifted by +180 and rounded, giving bins
  0..71 (x, z) and 18..54 (y, whose angle lies in [-90, 90]).
* Quaternions in this project are **(w, x, y, z)** (MuJoCo order); scipy's (x, y, z, w) order is
  only used in the tests. The Euler conversion follows scipy's quaternion algorithm (Bernardes
  & Viollet 2022), written in ``jax.numpy`` so that everything here can run under ``jit``. The array
  functions are themselves ``jax.jit``-wrapped (compiled once per input shape and dtype), since
  eager op-by-op dispatch is slow.
* An action is 7 ints: ``[vx, vy, vz, rx, ry, rz, gripper_open]`` with 1 = open, 0 = closed.

Two documented fixes with respect to the original code:

1. ``point_to_voxel`` clips below at 0 as well as above at 99; the original
   ``point_to_voxel_index`` had no lower clip, so points below the bounds gave negative indices.
2. ``format_objects`` always prints plain Python ints; the original printed the ``np.int32``
   values with ``str()``, which under numpy >= 2 reads ``np.int32(51)`` and changes the prompt.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

SCENE_BOUNDS: tuple[float, float, float, float, float, float] = (-0.3, -0.5, 0.6, 0.7, 0.5, 1.6)
VOXEL_SIZE: int = 100
ROTATION_RESOLUTION: int = 5

_N_ROT_BINS = 360 // ROTATION_RESOLUTION  # 72; bin 72 (= +180 deg) is the same angle as bin 0
_BOUNDS_MIN = SCENE_BOUNDS[:3]
_BOUNDS_MAX = SCENE_BOUNDS[3:]
# Per-axis voxel edge in metres, computed in float64 like the original (each is 0.01).
_VOXEL_RES = tuple((hi - lo) / VOXEL_SIZE for lo, hi in zip(_BOUNDS_MIN, _BOUNDS_MAX, strict=True))

ArrayLike = Any  # numpy array, jax array or nested sequence


# --------------------------------------------------------------------------------------------
# Positions
# --------------------------------------------------------------------------------------------


@jax.jit
def point_to_voxel(points: ArrayLike) -> jnp.ndarray:
    """Map positions (..., 3) in metres to voxel indices (..., 3), int32 in [0, 99].

    ``floor((p - min) / 0.01)`` as in X-ICM's ``point_to_voxel_index``, clipped to
    [0, VOXEL_SIZE - 1] on both sides. The lower clip is a fix: the original only clipped
    above, so a point below the workspace produced a negative index in the prompt.
    """
    p = jnp.asarray(points)
    if not jnp.issubdtype(p.dtype, jnp.floating):
        p = p.astype(jnp.float32)
    lo = jnp.asarray(_BOUNDS_MIN, dtype=p.dtype)
    res = jnp.asarray(_VOXEL_RES, dtype=p.dtype)
    idx = jnp.floor((p - lo) / res)
    return jnp.clip(idx, 0, VOXEL_SIZE - 1).astype(jnp.int32)


@jax.jit
def voxel_to_point(indices: ArrayLike) -> jnp.ndarray:
    """Map voxel indices (..., 3) to the voxel centres (..., 3): ``min + 0.01 * idx + 0.005``."""
    idx = jnp.asarray(indices)
    dtype = idx.dtype if jnp.issubdtype(idx.dtype, jnp.floating) else jnp.float32
    idx = idx.astype(dtype)
    lo = jnp.asarray(_BOUNDS_MIN, dtype=dtype)
    res = jnp.asarray(_VOXEL_RES, dtype=dtype)
    return lo + res * idx + res / 2


# --------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------


def _as_float(x: ArrayLike) -> jnp.ndarray:
    a = jnp.asarray(x)
    return a if jnp.issubdtype(a.dtype, jnp.floating) else a.astype(jnp.float32)


@jax.jit
def quat_to_euler_xyz(quat_wxyz: ArrayLike) -> jnp.ndarray:
    """Quaternion (..., 4) in (w, x, y, z) order -> extrinsic x-y-z Euler angles in degrees.

    Same result as scipy ``Rotation.from_quat([x, y, z, w]).as_euler('xyz', degrees=True)``:
    x and z in [-180, 180], y in [-90, 90]. It is a port of scipy's quaternion-based algorithm
    for the fixed sequence 'xyz' (extrinsic), including its gimbal-lock rule (z set to 0), so
    bins agree with the original except at float rounding boundaries. The input need not be
    normalised (the algorithm only uses ratios).
    """
    q = _as_float(quat_wxyz)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    # Sequence x-y-z extrinsic: i, j, k = 0, 1, 2, even permutation (sign = +1).
    a = w - y
    b = x + z
    c = y + w
    d = z - x
    theta_y = 2.0 * jnp.arctan2(jnp.hypot(c, d), jnp.hypot(a, b))
    half_sum = jnp.arctan2(b, a)
    half_diff = jnp.arctan2(d, c)
    # scipy uses 1e-7 in float64; float32 cannot resolve that close to pi.
    eps = max(1e-7, 100.0 * float(jnp.finfo(q.dtype).eps))
    lock_zero = jnp.abs(theta_y) <= eps
    lock_pi = jnp.abs(theta_y - jnp.pi) <= eps
    angle_x = jnp.where(
        lock_zero, 2.0 * half_sum, jnp.where(lock_pi, -2.0 * half_diff, half_sum - half_diff)
    )
    angle_z = jnp.where(lock_zero | lock_pi, 0.0, half_sum + half_diff)
    angle_y = theta_y - jnp.pi / 2

    def wrap(t: jnp.ndarray) -> jnp.ndarray:
        t = jnp.where(t < -jnp.pi, t + 2 * jnp.pi, t)
        return jnp.where(t > jnp.pi, t - 2 * jnp.pi, t)

    angles = jnp.stack([wrap(angle_x), wrap(angle_y), wrap(angle_z)], axis=-1)
    return jnp.rad2deg(angles)


@jax.jit
def euler_xyz_to_quat(euler_deg: ArrayLike) -> jnp.ndarray:
    """Extrinsic x-y-z Euler angles in degrees (..., 3) -> quaternion (w, x, y, z) (..., 4).

    Same as scipy ``from_euler('xyz', angles, degrees=True)`` (then reordered to w-first):
    the rotation is Rz(c) Ry(b) Rx(a), i.e. q = qz * qy * qx, with scipy's sign (not flipped).
    """
    half = jnp.deg2rad(_as_float(euler_deg)) / 2
    cx, sx = jnp.cos(half[..., 0]), jnp.sin(half[..., 0])
    cy, sy = jnp.cos(half[..., 1]), jnp.sin(half[..., 1])
    cz, sz = jnp.cos(half[..., 2]), jnp.sin(half[..., 2])
    w = cz * cy * cx + sz * sy * sx
    x = cz * cy * sx - sz * sy * cx
    y = cz * sy * cx + sz * cy * sx
    z = sz * cy * cx - cz * sy * sx
    return jnp.stack([w, x, y, z], axis=-1)


@jax.jit
def quat_to_euler_bins(quat_wxyz: ArrayLike) -> jnp.ndarray:
    """Quaternion (w, x, y, z) (..., 4) -> Euler bins int32 (..., 3) at 5 degrees.

    Mirrors ``quaternion_to_discrete_euler``: normalise, flip to w >= 0, Euler xyz degrees,
    +180, /5, round half to even (``np.around``), and bin 72 (+180 deg) wraps to 0. Note that a
    top-down gripper (x angle near +-180) lands on bins 0/1 or 70/71: a discontinuity kept on
    purpose because it is what the LLM saw in the original prompts.
    """
    q = _as_float(quat_wxyz)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    q = jnp.where(q[..., :1] < 0, -q, q)
    euler = quat_to_euler_xyz(q) + 180.0
    bins = jnp.round(euler / ROTATION_RESOLUTION).astype(jnp.int32)
    return jnp.mod(bins, _N_ROT_BINS)


@jax.jit
def euler_bins_to_quat(bins: ArrayLike) -> jnp.ndarray:
    """Euler bins (..., 3) -> quaternion (w, x, y, z) (..., 4): ``from_euler(bins*5 - 180)``."""
    angles = _as_float(bins) * ROTATION_RESOLUTION - 180.0
    return euler_xyz_to_quat(angles)


# --------------------------------------------------------------------------------------------
# 7-int actions
# --------------------------------------------------------------------------------------------


@jax.jit
def encode_action(pos: ArrayLike, quat_wxyz: ArrayLike, gripper_open: ArrayLike) -> jnp.ndarray:
    """Gripper pose and state -> X-ICM action ints (..., 7) int32.

    ``[voxel(pos) (3), euler bins(quat) (3), gripper]``. The original wrote
    ``int(obs.gripper_open)`` of RLBench's already-binary flag; here the flag is binarised with
    ``gripper_open >= 0.5 -> 1`` so that a 0/1 flag (float, int or bool) passes unchanged and
    a stray float cannot truncate 0.99 to 0.
    """
    vox = point_to_voxel(pos)
    rot = quat_to_euler_bins(quat_wxyz)
    grip = (jnp.asarray(gripper_open) >= 0.5).astype(jnp.int32)
    grip = jnp.broadcast_to(grip, vox.shape[:-1])[..., None]
    return jnp.concatenate([vox, rot, grip], axis=-1)


@jax.jit
def decode_action(ints: ArrayLike) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """X-ICM action ints (..., 7) -> (position (..., 3), quat (w, x, y, z) (..., 4), gripper (...)).

    As in ``_postprocess``: voxel centre, ``from_euler`` of the bins, gripper passed through
    (returned as float 0./1., the RLBench ``Discrete`` gripper action). No range checks: use
    ``validate_action_ints`` first.
    """
    a = jnp.asarray(ints)
    if a.shape[-1] != 7:
        raise ValueError(f"an action has 7 ints, got trailing shape {a.shape[-1]}")
    pos = voxel_to_point(a[..., :3])
    quat = euler_bins_to_quat(a[..., 3:6])
    grip = a[..., 6].astype(jnp.float32)
    return pos, quat, grip


@jax.jit
def validate_action_ints(ints: ArrayLike) -> jnp.ndarray:
    """Bool mask (...) of actions whose 7 ints are in range.

    Positions 0..99, rotation bins 0..71, gripper 0 or 1. The original did not check, so an LLM
    output such as 100 or -3 went straight to the planner; callers decide what to do with it.
    """
    a = jnp.asarray(ints)
    if a.shape[-1] != 7:
        raise ValueError(f"an action has 7 ints, got trailing shape {a.shape[-1]}")
    pos_ok = jnp.all((a[..., :3] >= 0) & (a[..., :3] <= VOXEL_SIZE - 1), axis=-1)
    rot_ok = jnp.all((a[..., 3:6] >= 0) & (a[..., 3:6] <= _N_ROT_BINS - 1), axis=-1)
    grip_ok = (a[..., 6] == 0) | (a[..., 6] == 1)
    return pos_ok & rot_ok & grip_ok


# --------------------------------------------------------------------------------------------
# Strings
# --------------------------------------------------------------------------------------------


def _int_list(values: ArrayLike) -> list[int]:
    """Plain Python ints, so ``str`` never prints ``np.int32(...)`` (fix for numpy >= 2)."""
    out = []
    for v in np.asarray(values).reshape(-1).tolist():
        if isinstance(v, float) and not float(v).is_integer():
            raise ValueError(f"expected integer values, got {v!r}")
        out.append(int(v))
    return out


def format_objects(instruction: str, objects: Mapping[str, Sequence[int]]) -> str:
    """The observation text of ``form_obs(cross_task_eval=1)``.

    ``"['instruction': " + instruction + ", " + str(dict) + "]"``, the dict in insertion order
    with each value a list of 3 plain ints, e.g.
    ``['instruction': close the red jar, {'lid': [52, 38, 17], 'jar': [47, 61, 16]}]``.
    """
    d: dict[str, list[int]] = {}
    for name, value in objects.items():
        ints = _int_list(value)
        if len(ints) != 3:
            raise ValueError(f"object {name!r} needs 3 voxel indices, got {ints}")
        d[str(name)] = ints
    return "['instruction': " + instruction + ", " + str(d) + "]"


def format_actions(actions: ArrayLike | Sequence[Sequence[int]]) -> str:
    """``str(list_of_7_int_lists)``: ``[[52, 38, 24, 0, 39, 0, 1], [52, 38, 18, 0, 39, 0, 0]]``.

    Accepts an (N, 7) array or a list of 7-int sequences; prints plain Python ints.
    """
    rows = [_int_list(a) for a in actions]
    for r in rows:
        if len(r) != 7:
            raise ValueError(f"an action has 7 ints, got {r}")
    return str(rows)


def format_demo(
    instruction: str,
    objects: Mapping[str, Sequence[int]],
    actions: ArrayLike | Sequence[Sequence[int]],
) -> str:
    """One in-context demo segment: ``objects + ">" + actions + ", "`` (the trailing ", "
    separates demos in the one-line user prompt)."""
    return format_objects(instruction, objects) + ">" + format_actions(actions) + ", "


def format_query(instruction: str, objects: Mapping[str, Sequence[int]]) -> str:
    """The query that ends the prompt: ``objects + ">"``; the LLM continues with the actions."""
    return format_objects(instruction, objects) + ">"


__all__ = [
    "ROTATION_RESOLUTION",
    "SCENE_BOUNDS",
    "VOXEL_SIZE",
    "decode_action",
    "encode_action",
    "euler_bins_to_quat",
    "euler_xyz_to_quat",
    "format_actions",
    "format_demo",
    "format_objects",
    "format_query",
    "point_to_voxel",
    "quat_to_euler_bins",
    "quat_to_euler_xyz",
    "validate_action_ints",
    "voxel_to_point",
]
