"""X-ICM textualisation: poses and objects as the integers and strings the LLM sees.

Conventions (X-ICM / RoboPrompt ``utils.py``, PerAct settings):

* Workspace ``SCENE_BOUNDS = (x_min, y_min, z_min, x_max, y_max, z_max)`` in metres, cut into
  ``VOXEL_SIZE = 100`` bins per axis (1 cm). A position becomes 3 voxel indices 0..99 and
  decodes to the voxel centre.
* Rotations are discretised at ``ROTATION_RESOLUTION = 5`` degrees as extrinsic x-y-z Euler
  angles (scipy ``as_euler('xyz', degrees=True)``), shifted by +180 and rounded, giving bins
  0..71 (x, z) and 18..54 (y, whose angle lies in [-90, 90]).
* Quaternions in this project are **(w, x, y, z)** (MuJoCo order); scipy's (x, y, z, w) order is
  only used inside (to keep the original's summation order) and in the tests.
* An action is 7 ints: ``[vx, vy, vz, rx, ry, rz, gripper_open]`` with 1 = open, 0 = closed.

Everything here runs on the host in float64 numpy and repeats the original's arithmetic
operation by operation, because the text the LLM sees must be identical for identical poses:

* positions: ``floor((p - min) / (range / (100 + 1e-12) + 1e-12))`` as in ``point_to_voxel_index``
  (so a point exactly on a 1 cm edge such as z = 1.0 lands in the lower voxel, 39, as it did
  in the original; 1e-9 m above the edge it lands in 40);
* rotations: ``normalize_quaternion`` (``np.linalg.norm``), flip to w >= 0, scipy's
  ``from_quat`` renormalisation and the quaternion-based ``as_euler`` of scipy 1.15 (Bernardes &
  Viollet 2022) with its gimbal-lock rule (|second angle| or |second angle - pi| <= 1e-7 rad:
  the third angle is set to 0). ``atan2`` is evaluated with the C library's (``math.atan2``)
  like scipy's compiled code: numpy's SIMD ``arctan2`` differs by 1 ulp on AVX-512 machines.

scipy is not needed at run time; the tests compare against it.

Two documented fixes with respect to the original code:

1. ``point_to_voxel`` clips below at 0 as well as above at 99; the original
   ``point_to_voxel_index`` had no lower clip, so points below the bounds gave negative indices.
2. ``format_objects`` always prints plain Python ints; the original printed the ``np.int32``
   values with ``str()``, which under numpy >= 2 reads ``np.int32(51)`` and changes the prompt.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from agnostos_mjx.sim.actions import KeyActions

SCENE_BOUNDS: tuple[float, float, float, float, float, float] = (-0.3, -0.5, 0.6, 0.7, 0.5, 1.6)
VOXEL_SIZE: int = 100
ROTATION_RESOLUTION: int = 5
GIMBAL_LOCK_EPS: float = 1e-7  # rad, scipy's threshold on the second angle

_N_ROT_BINS = 360 // ROTATION_RESOLUTION  # 72; bin 72 (= +180 deg) is the same angle as bin 0
_BOUNDS_MIN = np.array(SCENE_BOUNDS[:3])
_BOUNDS_RANGE = np.array(SCENE_BOUNDS[3:]) - _BOUNDS_MIN
# The original's divisor, epsilons included: range / (100 + 1e-12) + 1e-12 (about 0.010000000001).
_VOXEL_DIVISOR = _BOUNDS_RANGE / (np.array([VOXEL_SIZE] * 3) + 1e-12) + 1e-12
# The decoder's voxel edge, as in X-ICM's ``_postprocess``: range / 100.
_VOXEL_RES = _BOUNDS_RANGE / VOXEL_SIZE

ArrayLike = Any  # numpy array, jax array or nested sequence

_atan2 = np.frompyfunc(math.atan2, 2, 1)


def _f64(x: ArrayLike) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _libm_atan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Element-wise C-library atan2, bit-identical to scipy's compiled ``as_euler``."""
    return np.asarray(_atan2(y, x), dtype=np.float64).reshape(np.broadcast(y, x).shape)


# --------------------------------------------------------------------------------------------
# Positions
# --------------------------------------------------------------------------------------------


def point_to_voxel(points: ArrayLike) -> np.ndarray:
    """Map positions (..., 3) in metres to voxel indices (..., 3), int32 in [0, 99].

    X-ICM's ``point_to_voxel_index`` in float64, epsilons included, clipped to
    [0, VOXEL_SIZE - 1] on both sides. The lower clip is a fix: the original only clipped
    above, so a point below the workspace produced a negative index in the prompt.
    """
    idx = np.floor((_f64(points) - _BOUNDS_MIN) / _VOXEL_DIVISOR)
    return np.clip(idx, 0, VOXEL_SIZE - 1).astype(np.int32)


def voxel_to_point(indices: ArrayLike) -> np.ndarray:
    """Map voxel indices (..., 3) to the voxel centres (..., 3): ``min + res * idx + res / 2``."""
    return _BOUNDS_MIN + _VOXEL_RES * _f64(indices) + _VOXEL_RES / 2


# --------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------


def _scipy_normalise(q_xyzw: np.ndarray) -> np.ndarray:
    """scipy ``from_quat``'s own normalisation (``_normalize4``: x^2 + y^2 + z^2, then + w^2).

    A zero or non-finite quaternion raises, as scipy (and hence the original) did."""
    x, y, z, w = np.moveaxis(q_xyzw, -1, 0)
    norm = np.sqrt(((x * x + y * y) + z * z) + w * w)
    if not np.all(np.isfinite(norm) & (norm > 0)):
        raise ValueError("found zero-norm or non-finite quaternions")
    return q_xyzw / norm[..., None]


def _euler_xyz_rad(q_xyzw: np.ndarray) -> np.ndarray:
    """scipy's quaternion -> extrinsic 'xyz' Euler angles (rad) for unit quaternions (x, y, z, w).

    Sequence x-y-z is asymmetric with an even permutation (sign +1), lambda = pi / 2."""
    x, y, z, w = np.moveaxis(q_xyzw, -1, 0)
    a, b, c, d = w - y, x + z, y + w, z - x
    second = 2 * _libm_atan2(np.hypot(c, d), np.hypot(a, b))
    half_sum = _libm_atan2(b, a)
    half_diff = _libm_atan2(d, c)
    lock_zero = np.abs(second) <= GIMBAL_LOCK_EPS
    lock_pi = ~lock_zero & (np.abs(second - np.pi) <= GIMBAL_LOCK_EPS)
    first = np.where(lock_zero, 2 * half_sum,
                     np.where(lock_pi, 2 * half_diff * -1, half_sum - half_diff))
    third = np.where(lock_zero | lock_pi, 0.0, half_sum + half_diff)
    angles = np.stack([first, second - np.pi / 2, third], axis=-1)
    angles = np.where(angles < -np.pi, angles + 2 * np.pi, angles)
    return np.where(angles > np.pi, angles - 2 * np.pi, angles)


def quat_to_euler_xyz(quat_wxyz: ArrayLike) -> np.ndarray:
    """Quaternion (..., 4) in (w, x, y, z) order -> extrinsic x-y-z Euler angles in degrees.

    Bit-identical to scipy ``Rotation.from_quat([x, y, z, w]).as_euler('xyz', degrees=True)``
    (x and z in [-180, 180], y in [-90, 90]; at gimbal lock z is 0). The input need not be
    normalised."""
    q = np.roll(_f64(quat_wxyz), -1, axis=-1)
    return np.rad2deg(_euler_xyz_rad(_scipy_normalise(q)))


def _compose_xyzw(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p * q of (x, y, z, w) quaternions, in scipy's operation order."""
    cross = np.cross(p[..., :3], q[..., :3])
    vec = p[..., 3:] * q[..., :3] + q[..., 3:] * p[..., :3] + cross
    w = p[..., 3] * q[..., 3] - p[..., 0] * q[..., 0] - p[..., 1] * q[..., 1] - p[..., 2] * q[..., 2]
    return np.concatenate([vec, w[..., None]], axis=-1)


def euler_xyz_to_quat(euler_deg: ArrayLike) -> np.ndarray:
    """Extrinsic x-y-z Euler angles in degrees (..., 3) -> quaternion (w, x, y, z) (..., 4).

    scipy ``from_euler('xyz', angles, degrees=True)`` (then reordered to w-first): elementary
    quaternions composed as qz * (qy * qx), with scipy's sign (not flipped)."""
    half = np.deg2rad(_f64(euler_deg)) / 2
    elementary = []
    for axis in range(3):
        e = np.zeros((*half.shape[:-1], 4))
        e[..., 3] = np.cos(half[..., axis])
        e[..., axis] = np.sin(half[..., axis])
        elementary.append(e)
    q = _compose_xyzw(elementary[2], _compose_xyzw(elementary[1], elementary[0]))
    return np.roll(q, 1, axis=-1)


def quat_to_euler_bins(quat_wxyz: ArrayLike) -> np.ndarray:
    """Quaternion (w, x, y, z) (..., 4) -> Euler bins int32 (..., 3) at 5 degrees.

    ``quaternion_to_discrete_euler(normalize_quaternion(q))`` with the caller's flip to w >= 0:
    Euler xyz degrees, +180, /5, round half to even (``np.around``), and bin 72 (+180 deg)
    wraps to 0. A top-down gripper (x angle near +-180) lands on bins 0/1 or 70/71: a
    discontinuity kept on purpose because it is what the LLM saw in the original prompts.
    """
    q = np.roll(_f64(quat_wxyz), -1, axis=-1)  # (x, y, z, w): the original's summation order
    with np.errstate(invalid="ignore", divide="ignore"):  # a zero quaternion raises below
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., 3:] < 0, -q, q)
    euler = np.rad2deg(_euler_xyz_rad(_scipy_normalise(q))) + 180
    bins = np.around(euler / ROTATION_RESOLUTION).astype(np.int32)
    return np.where(bins == _N_ROT_BINS, 0, bins).astype(np.int32)


def euler_bins_to_quat(bins: ArrayLike) -> np.ndarray:
    """Euler bins (..., 3) -> quaternion (w, x, y, z) (..., 4): ``from_euler(bins*5 - 180)``."""
    return euler_xyz_to_quat(np.asarray(bins) * ROTATION_RESOLUTION - 180)


# --------------------------------------------------------------------------------------------
# 7-int actions
# --------------------------------------------------------------------------------------------


def encode_action(pos: ArrayLike, quat_wxyz: ArrayLike, gripper_open: ArrayLike) -> np.ndarray:
    """Gripper pose and state -> X-ICM action ints (..., 7) int32.

    ``[voxel(pos) (3), euler bins(quat) (3), gripper]``. The original wrote
    ``int(obs.gripper_open)`` of RLBench's already-binary flag; here the flag is binarised with
    ``gripper_open >= 0.5 -> 1`` so that a 0/1 flag (float, int or bool) passes unchanged and
    a stray float cannot truncate 0.99 to 0.
    """
    vox = point_to_voxel(pos)
    rot = quat_to_euler_bins(quat_wxyz)
    grip = (np.asarray(gripper_open) >= 0.5).astype(np.int32)
    grip = np.broadcast_to(grip, vox.shape[:-1])[..., None]
    return np.concatenate([vox, rot, grip], axis=-1)


def _check_width(a: np.ndarray) -> None:
    if a.shape[-1] != 7:
        raise ValueError(f"an action has 7 ints, got trailing shape {a.shape[-1]}")


def decode_action(ints: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """X-ICM action ints (..., 7) -> (position (..., 3), quat (w, x, y, z) (..., 4), gripper (...)).

    As in ``_postprocess``: voxel centre, ``from_euler`` of the bins, gripper passed through
    (returned as float 0./1., the RLBench ``Discrete`` gripper action). No range checks: use
    ``validate_action_ints`` first.
    """
    a = np.asarray(ints)
    _check_width(a)
    return voxel_to_point(a[..., :3]), euler_bins_to_quat(a[..., 3:6]), a[..., 6].astype(np.float64)


def validate_action_ints(ints: ArrayLike) -> np.ndarray:
    """Bool mask (...) of actions whose 7 ints are in range.

    Positions 0..99, rotation bins 0..71, gripper 0 or 1. The original did not check, so an LLM
    output such as 100 or -3 went straight to the planner; callers decide what to do with it.
    """
    a = np.asarray(ints)
    _check_width(a)
    pos_ok = np.all((a[..., :3] >= 0) & (a[..., :3] <= VOXEL_SIZE - 1), axis=-1)
    rot_ok = np.all((a[..., 3:6] >= 0) & (a[..., 3:6] <= _N_ROT_BINS - 1), axis=-1)
    grip_ok = (a[..., 6] == 0) | (a[..., 6] == 1)
    return pos_ok & rot_ok & grip_ok


def xicm_actions(ints: ArrayLike) -> KeyActions:
    """X-ICM's 7-integer key actions (B, 7) -> KeyActions; groups outside the valid ranges
    become invalid actions (the episode then ends as no_action)."""
    ints = np.asarray(ints)
    valid = np.asarray(validate_action_ints(ints), bool)
    safe = np.where(valid[:, None], ints, np.array([57, 49, 87, 0, 39, 0, 1]))
    pos, quat, grip = map(np.asarray, decode_action(safe))
    return KeyActions(pos, quat, grip, valid)


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
    "GIMBAL_LOCK_EPS",
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
