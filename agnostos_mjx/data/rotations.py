"""Rotation representations of the LeRobot export's states and actions (numpy, float64,
leading batch axes allowed), in RLBench's scalar-last quaternion order (x, y, z, w), the
order of ``gripper_pose``.  The conversions themselves are math3d.py's (MuJoCo's (w, x, y, z)
order, the ones the policy-server adapter uses); this module only reorders and names them.

* ``quat``: (qx, qy, qz, qw), unit, sign made canonical (qw >= 0; q and -q are one rotation).
* ``euler``: extrinsic x-y-z Euler angles (rx, ry, rz) in radians, R = Rz(rz) Ry(ry) Rx(rx),
  scipy's ``Rotation.as_euler('xyz')`` (X-ICM's and RoboPrompt's convention); ry in
  [-pi/2, pi/2], rx and rz in [-pi, pi].  At gimbal lock (|ry| = pi/2) rz is set to 0.
* ``axis_angle``: the rotation vector axis * angle (ax, ay, az), angle in [0, pi] (LIBERO's
  and robosuite's ``quat2axisangle``; identical to remote/adapter.py's ``libero_state``).
* ``rot6d``: the first two columns of the rotation matrix, (r11, r21, r31, r12, r22, r32)
  (Zhou et al. 2019, "On the continuity of rotation representations"); back to a rotation
  by Gram-Schmidt.
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.sim.math3d import (
    euler_xyz_to_quat,
    mat_to_quat,
    mat_to_rot6d,
    quat_to_euler_xyz,
    quat_to_mat,
    quat_to_rotvec,
    rot6d_to_mat,
    rotvec_to_quat,
)

ROTATIONS = ("quat", "euler", "axis_angle", "rot6d")
# Per-dimension names of each representation (info.json's feature ``names``).
ROTATION_NAMES: dict[str, tuple[str, ...]] = {
    "quat": ("qx", "qy", "qz", "qw"),
    "euler": ("rx", "ry", "rz"),
    "axis_angle": ("ax", "ay", "az"),
    "rot6d": ("r11", "r21", "r31", "r12", "r22", "r32"),
}


def _wxyz(xyzw: np.ndarray) -> np.ndarray:
    return np.asarray(xyzw, np.float64)[..., [3, 0, 1, 2]]


def canonical_quat(xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) with qw >= 0."""
    q = np.asarray(xyzw, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def _xyzw(wxyz: np.ndarray) -> np.ndarray:
    """math3d's (w, x, y, z) -> canonical (x, y, z, w)."""
    return canonical_quat(np.asarray(wxyz, np.float64)[..., [1, 2, 3, 0]])


def quat_to_euler(xyzw: np.ndarray) -> np.ndarray:
    return quat_to_euler_xyz(_wxyz(xyzw))


def euler_to_quat(rxyz: np.ndarray) -> np.ndarray:
    return _xyzw(euler_xyz_to_quat(np.asarray(rxyz, np.float64)))


def quat_to_axis_angle(xyzw: np.ndarray) -> np.ndarray:
    return quat_to_rotvec(_wxyz(xyzw))


def axis_angle_to_quat(rotvec: np.ndarray) -> np.ndarray:
    return _xyzw(rotvec_to_quat(np.asarray(rotvec, np.float64)))


def quat_to_rot6d(xyzw: np.ndarray) -> np.ndarray:
    """-> (..., 6): the rotation matrix's first column, then its second."""
    return mat_to_rot6d(quat_to_mat(_wxyz(canonical_quat(xyzw))))


def rot6d_to_quat(r6: np.ndarray) -> np.ndarray:
    return _xyzw(mat_to_quat(rot6d_to_mat(np.asarray(r6, np.float64))))


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
