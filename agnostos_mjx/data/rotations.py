"""Rotation representations of the LeRobot export's states and actions (numpy, float64,
leading batch axes allowed).  Kept here, not in math3d.py (which is jax-aware and uses
MuJoCo's (w, x, y, z) order): every function of this module takes and returns RLBench's
scalar-last quaternions (x, y, z, w), the order of ``gripper_pose``.

* ``quat``: (qx, qy, qz, qw), unit, sign made canonical (qw >= 0; q and -q are one rotation).
* ``euler``: extrinsic x-y-z Euler angles (rx, ry, rz) in radians, R = Rz(rz) Ry(ry) Rx(rx),
  scipy's ``Rotation.as_euler('xyz')`` (X-ICM's and RoboPrompt's convention); ry in
  [-pi/2, pi/2], rx and rz in (-pi, pi].  At gimbal lock (|ry| = pi/2) rz is set to 0.
* ``axis_angle``: the rotation vector axis * angle (ax, ay, az), angle in [0, pi] (LIBERO's
  and robosuite's ``quat2axisangle``; identical to remote/adapter.py's ``libero_state``).
* ``rot6d``: the first two columns of the rotation matrix, (r11, r21, r31, r12, r22, r32)
  (Zhou et al. 2019, "On the continuity of rotation representations"); back to a rotation
  by Gram-Schmidt.
"""

from __future__ import annotations

import numpy as np

ROTATIONS = ("quat", "euler", "axis_angle", "rot6d")
# Per-dimension names of each representation (info.json's feature ``names``).
ROTATION_NAMES: dict[str, tuple[str, ...]] = {
    "quat": ("qx", "qy", "qz", "qw"),
    "euler": ("rx", "ry", "rz"),
    "axis_angle": ("ax", "ay", "az"),
    "rot6d": ("r11", "r21", "r31", "r12", "r22", "r32"),
}


def canonical_quat(xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) with qw >= 0."""
    q = np.asarray(xyzw, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def quat_to_matrix(xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) -> rotation matrices (..., 3, 3)."""
    x, y, z, w = np.moveaxis(canonical_quat(xyzw), -1, 0)
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> canonical quaternions (..., 4) (Shepperd)."""
    m = np.asarray(m, np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    cands = np.stack([  # 4 q's scaled by 4 * (their largest component), pick the best
        np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                  m[..., 1, 0] - m[..., 0, 1], 1 + trace], -1),
        np.stack([1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0],
                  m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] - m[..., 1, 2]], -1),
        np.stack([m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22,
                  m[..., 1, 2] + m[..., 2, 1], m[..., 0, 2] - m[..., 2, 0]], -1),
        np.stack([m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                  1 - m00 - m11 + m22, m[..., 1, 0] - m[..., 0, 1]], -1)], -2)
    best = np.argmax(np.stack([trace, m00, m11, m22], -1), -1)
    q = np.take_along_axis(cands, best[..., None, None], -2)[..., 0, :]
    return canonical_quat(q)


def quat_to_euler(xyzw: np.ndarray) -> np.ndarray:
    """-> extrinsic x-y-z Euler angles (..., 3), radians (scipy's ``as_euler('xyz')``)."""
    r = quat_to_matrix(xyzw)
    sy = np.clip(-r[..., 2, 0], -1.0, 1.0)
    ry = np.arcsin(sy)
    locked = np.abs(sy) > 1 - 1e-12
    rx = np.where(locked, np.arctan2(-r[..., 1, 2], r[..., 1, 1]),
                  np.arctan2(r[..., 2, 1], r[..., 2, 2]))
    rz = np.where(locked, 0.0, np.arctan2(r[..., 1, 0], r[..., 0, 0]))
    return np.stack([rx, ry, rz], -1)


def euler_to_quat(rxyz: np.ndarray) -> np.ndarray:
    """Extrinsic x-y-z Euler angles (..., 3), radians -> canonical quaternions."""
    a = np.asarray(rxyz, np.float64) / 2
    cx, cy, cz = np.cos(a[..., 0]), np.cos(a[..., 1]), np.cos(a[..., 2])
    sx, sy, sz = np.sin(a[..., 0]), np.sin(a[..., 1]), np.sin(a[..., 2])
    q = np.stack([sx * cy * cz - cx * sy * sz, cx * sy * cz + sx * cy * sz,
                  cx * cy * sz - sx * sy * cz, cx * cy * cz + sx * sy * sz], -1)
    return canonical_quat(q)


def quat_to_axis_angle(xyzw: np.ndarray) -> np.ndarray:
    """-> rotation vectors (..., 3), angle in [0, pi]."""
    q = canonical_quat(xyzw)
    s = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., 3:4])
    return np.where(s > 1e-12, q[..., :3] / np.maximum(s, 1e-12) * angle, 0.0)


def axis_angle_to_quat(rotvec: np.ndarray) -> np.ndarray:
    v = np.asarray(rotvec, np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    axis = np.where(angle > 1e-12, v / np.maximum(angle, 1e-12), 0.0)
    return canonical_quat(np.concatenate([axis * np.sin(angle / 2), np.cos(angle / 2)], -1))


def quat_to_rot6d(xyzw: np.ndarray) -> np.ndarray:
    """-> (..., 6): the rotation matrix's first column, then its second."""
    m = quat_to_matrix(xyzw)
    return np.concatenate([m[..., :, 0], m[..., :, 1]], -1)


def rot6d_to_quat(r6: np.ndarray) -> np.ndarray:
    r6 = np.asarray(r6, np.float64)
    a, b = r6[..., :3], r6[..., 3:]
    c1 = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b - np.sum(c1 * b, -1, keepdims=True) * c1
    c2 = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return matrix_to_quat(np.stack([c1, c2, np.cross(c1, c2)], -1))


_TO = {"quat": canonical_quat, "euler": quat_to_euler, "axis_angle": quat_to_axis_angle,
       "rot6d": quat_to_rot6d}
_FROM = {"quat": canonical_quat, "euler": euler_to_quat, "axis_angle": axis_angle_to_quat,
         "rot6d": rot6d_to_quat}


def check_rotation(name: str) -> str:
    if name not in ROTATIONS:
        raise ValueError(f"unknown rotation {name!r}; choose from {', '.join(ROTATIONS)}")
    return name


def from_quat(xyzw: np.ndarray, rotation: str) -> np.ndarray:
    """Scalar-last quaternions (..., 4) -> `rotation` (..., len(ROTATION_NAMES[rotation]))."""
    return _TO[check_rotation(rotation)](xyzw)


def to_quat(values: np.ndarray, rotation: str) -> np.ndarray:
    """`rotation` values -> canonical scalar-last quaternions (..., 4)."""
    return _FROM[check_rotation(rotation)](values)
