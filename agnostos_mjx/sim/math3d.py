"""Rigid-body maths for numpy and jax.numpy arrays alike (leading batch axes
allowed).  Quaternions are (w, x, y, z), MuJoCo's order.

Functions pick their array module from their inputs: numpy in, numpy out (the
CPU control path, where XLA's per-op overhead on tiny arrays dominates), jax in,
jax out (on device, inside jit)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

Array = np.ndarray | jax.Array


def array_module(*arrays):
    """numpy if every input is a numpy array or scalar, else jax.numpy."""
    if any(isinstance(a, jax.Array) or isinstance(a, jax.core.Tracer) for a in arrays):
        return jnp
    return np


def quat_mul(a: Array, b: Array) -> Array:
    xp = array_module(a, b)
    aw, ax, ay, az = xp.moveaxis(xp.asarray(a), -1, 0)
    bw, bx, by, bz = xp.moveaxis(xp.asarray(b), -1, 0)
    return xp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: Array) -> Array:
    xp = array_module(q)
    return xp.asarray(q) * xp.array([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: Array) -> Array:
    xp = array_module(q)
    q = xp.asarray(q)
    return q / xp.linalg.norm(q, axis=-1, keepdims=True)


def quat_rotate(q: Array, v: Array) -> Array:
    """Rotate vector(s) v by unit quaternion(s) q."""
    xp = array_module(q, v)
    q = xp.asarray(q)
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * xp.cross(u, v)
    return v + w * t + xp.cross(u, t)


def quat_to_mat(q: Array) -> Array:
    xp = array_module(q)
    w, x, y, z = xp.moveaxis(xp.asarray(q), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def axis_angle_quat(axis: Array, angle: Array) -> Array:
    xp = array_module(axis, angle)
    axis = xp.asarray(axis)
    half = 0.5 * xp.asarray(angle)[..., None]
    return xp.concatenate([xp.cos(half), xp.sin(half) * axis], axis=-1)


def yaw_quat(yaw: Array) -> Array:
    xp = array_module(yaw)
    return axis_angle_quat(xp.array([0.0, 0.0, 1.0]), yaw)


def euler_xyz_quat(rx: float, ry: float, rz: float) -> Array:
    """Extrinsic x-y-z Euler angles (radians) -> quaternion (scipy's 'xyz')."""
    xp = array_module(rx, ry, rz)
    qx = axis_angle_quat(xp.array([1.0, 0.0, 0.0]), rx)
    qy = axis_angle_quat(xp.array([0.0, 1.0, 0.0]), ry)
    qz = axis_angle_quat(xp.array([0.0, 0.0, 1.0]), rz)
    return quat_mul(qz, quat_mul(qy, qx))


def quat_error(target: Array, current: Array) -> Array:
    """Rotation vector (world frame) that takes `current` to `target`."""
    xp = array_module(target, current)
    dq = quat_mul(target, quat_conj(current))
    dq = xp.where(dq[..., :1] < 0, -dq, dq)
    sin_half = xp.linalg.norm(dq[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * xp.arctan2(sin_half, dq[..., :1])
    scale = xp.where(sin_half > 1e-9, angle / xp.maximum(sin_half, 1e-9), 2.0)
    return dq[..., 1:] * scale


def quat_angle(a: Array, b: Array) -> Array:
    """Angle (radians) between two orientations."""
    xp = array_module(a, b)
    dot = xp.abs(xp.sum(quat_normalize(a) * quat_normalize(b), axis=-1))
    return 2.0 * xp.arccos(xp.clip(dot, 0.0, 1.0))


def slerp(a: Array, b: Array, t: Array) -> Array:
    """Spherical interpolation, t in [0, 1] broadcast against the quaternions."""
    xp = array_module(a, b, t)
    dot = xp.sum(a * b, axis=-1, keepdims=True)
    b = xp.where(dot < 0, -b, b)
    dot = xp.abs(dot)
    theta = xp.arccos(xp.clip(dot, -1.0, 1.0))
    sin_theta = xp.sin(theta)
    t = xp.asarray(t)[..., None] if xp.ndim(t) == xp.ndim(a) - 1 else t
    wa = xp.where(sin_theta > 1e-6, xp.sin((1 - t) * theta) / xp.maximum(sin_theta, 1e-6), 1 - t)
    wb = xp.where(sin_theta > 1e-6, xp.sin(t * theta) / xp.maximum(sin_theta, 1e-6), t)
    return quat_normalize(wa * a + wb * b)


def apply_delta(pos: Array, quat: Array, delta_pos: Array, delta_quat: Array
                ) -> tuple[Array, Array]:
    """A pose (pos, quat wxyz) moved by a relative action: the position plus `delta_pos`
    (world frame), `delta_quat` composed on the left (a rotation about the world axes, as
    RLBench's ``absolute_mode=False`` and robosuite's OSC apply deltas), normalised."""
    xp = array_module(quat, delta_quat)
    quat = quat / xp.linalg.norm(quat, axis=-1, keepdims=True)
    return pos + delta_pos, quat_normalize(quat_mul(delta_quat, quat))


def pose_delta(pos: Array, quat: Array, target_pos: Array, target_quat: Array
               ) -> tuple[Array, Array]:
    """The relative action that `apply_delta` turns from the pose (pos, quat) into the
    target: (target_pos - pos, target_quat * conj(quat))."""
    return target_pos - pos, quat_mul(target_quat, quat_conj(quat))


def transform_point(pos: Array, quat: Array, local: Array) -> Array:
    """World position of a point given in a frame (pos, quat)."""
    return pos + quat_rotate(quat, local)


def mat_to_quat(m: Array) -> Array:
    """Rotation matrix (..., 3, 3) -> unit quaternion (w, x, y, z); branch-free
    (Shepperd's four cases, selected by the largest diagonal term)."""
    xp = array_module(m)
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    trace = m00 + m11 + m22

    def root(x):
        return 2.0 * xp.sqrt(xp.maximum(x, 1e-12))

    s0, s1, s2, s3 = root(1 + trace), root(1 + m00 - m11 - m22), root(1 + m11 - m00 - m22), \
        root(1 + m22 - m00 - m11)
    cases = [
        xp.stack([0.25 * s0, (m21 - m12) / s0, (m02 - m20) / s0, (m10 - m01) / s0], -1),
        xp.stack([(m21 - m12) / s1, 0.25 * s1, (m01 + m10) / s1, (m02 + m20) / s1], -1),
        xp.stack([(m02 - m20) / s2, (m01 + m10) / s2, 0.25 * s2, (m12 + m21) / s2], -1),
        xp.stack([(m10 - m01) / s3, (m02 + m20) / s3, (m12 + m21) / s3, 0.25 * s3], -1),
    ]
    choice = xp.argmax(xp.stack([trace, m00, m11, m22], -1), axis=-1)[..., None]
    q = xp.where(choice == 0, cases[0], xp.where(choice == 1, cases[1],
                                                  xp.where(choice == 2, cases[2], cases[3])))
    return quat_normalize(q)


# ---- rotation representations (what policy servers send) --------------------------------
# Conventions follow scipy.spatial.transform.Rotation, checked against it in
# tests/test_transports.py; no scipy at runtime.  Quaternions stay (w, x, y, z) here.
def euler_xyz_to_quat(angles: Array) -> Array:
    """Extrinsic x-y-z Euler angles (..., 3) in radians -> unit quaternions (..., 4):
    scipy's ``Rotation.from_euler("xyz", angles)`` (R = Rz(c) Ry(b) Rx(a))."""
    xp = array_module(angles)
    angles = xp.asarray(angles)
    half = 0.5 * angles
    c, s = xp.cos(half), xp.sin(half)
    cx, cy, cz = c[..., 0], c[..., 1], c[..., 2]
    sx, sy, sz = s[..., 0], s[..., 1], s[..., 2]
    return xp.stack([cz * cy * cx + sz * sy * sx,
                     cz * cy * sx - sz * sy * cx,
                     cz * sy * cx + sz * cy * sx,
                     sz * cy * cx - cz * sy * sx], axis=-1)


def quat_to_euler_xyz(q: Array) -> Array:
    """Unit quaternions (..., 4) -> extrinsic x-y-z Euler angles (..., 3), radians,
    exactly as scipy's ``Rotation.as_euler("xyz")`` computes them (the quaternion method
    of Bernardes & Viollet, 2022): first and third angle in [-pi, pi], second in
    [-pi/2, pi/2]; at gimbal lock (second angle within 1e-7 of +-pi/2) the third is 0."""
    xp = array_module(q)
    q = xp.asarray(q)
    q = q / xp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    # Axes i, j, k = x, y, z (an even permutation): a rotation about the intermediate
    # axis j turns the problem into the symmetric (proper Euler) case.
    a, b, c, d = w - y, x + z, y + w, z - x
    half_sum, half_diff = xp.arctan2(b, a), xp.arctan2(d, c)
    second = 2.0 * xp.arctan2(xp.hypot(c, d), xp.hypot(a, b))
    eps = 1e-7
    near_zero, near_pi = xp.abs(second) <= eps, xp.abs(second - xp.pi) <= eps
    regular = ~(near_zero | near_pi)
    first = xp.where(regular, half_sum - half_diff,
                     xp.where(near_zero, 2.0 * half_sum, -2.0 * half_diff))
    third = xp.where(regular, half_sum + half_diff, 0.0)
    angles = xp.stack([first, second - xp.pi / 2, third], axis=-1)
    # into [-pi, pi], keeping an exact +-pi as computed (scipy's compiled path does so)
    return xp.where(angles < -xp.pi, angles + 2 * xp.pi,
                    xp.where(angles > xp.pi, angles - 2 * xp.pi, angles))


def rotvec_to_quat(v: Array) -> Array:
    """Rotation vectors (axis * angle, radians) (..., 3) -> unit quaternions (..., 4):
    scipy's ``Rotation.from_rotvec``."""
    xp = array_module(v)
    v = xp.asarray(v)
    angle = xp.linalg.norm(v, axis=-1, keepdims=True)
    small = angle < 1e-3  # sin(t/2)/t by its Taylor series near 0
    safe = xp.where(small, 1.0, angle)
    scale = xp.where(small, 0.5 - angle ** 2 / 48 + angle ** 4 / 3840, xp.sin(0.5 * safe) / safe)
    return xp.concatenate([xp.cos(0.5 * angle), scale * v], axis=-1)


def quat_to_rotvec(q: Array) -> Array:
    """Unit quaternions (..., 4) -> rotation vectors (..., 3), angle in [0, pi]:
    scipy's ``Rotation.as_rotvec``."""
    xp = array_module(q)
    q = xp.asarray(q)
    q = q / xp.linalg.norm(q, axis=-1, keepdims=True)
    q = xp.where(q[..., :1] < 0, -q, q)
    s = xp.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * xp.arctan2(s, q[..., :1])
    small = angle < 1e-3
    safe = xp.where(small, 1.0, s)
    scale = xp.where(small, 2.0 + angle ** 2 / 12 + 7 * angle ** 4 / 2880, angle / safe)
    return scale * q[..., 1:]


def xyzw_to_axis_angle_f32(xyzw: np.ndarray) -> np.ndarray:
    """Scalar-last unit quaternions (..., 4) -> axis * angle (..., 3), angle in [0, pi], in
    float32 arithmetic: LIBERO's state, which the remote adapter sends served policies and
    the LeRobot export's libero layout stores, bit for bit alike."""
    q = np.where(xyzw[..., 3:4] < 0, -xyzw, xyzw)
    s = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., 3:4])
    return np.where(s > 1e-12, q[..., :3] / np.maximum(s, 1e-12) * angle, 0.0).astype(np.float32)


def rot6d_to_mat(d6: Array) -> Array:
    """6-D rotations (..., 6) -> rotation matrices (..., 3, 3).  The 6 numbers are the
    first two *columns* of the matrix, column 0 then column 1 (Zhou et al., "On the
    Continuity of Rotation Representations in Neural Networks", 2019); they need not be
    orthonormal: Gram-Schmidt makes them so, the third column is their cross product.
    (PyTorch3D's ``matrix_to_rotation_6d`` stores the first two *rows* instead.)"""
    xp = array_module(d6)
    d6 = xp.asarray(d6)
    a1, a2 = d6[..., :3], d6[..., 3:6]
    b1 = a1 / xp.linalg.norm(a1, axis=-1, keepdims=True)
    a2 = a2 - xp.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = a2 / xp.linalg.norm(a2, axis=-1, keepdims=True)
    return xp.stack([b1, b2, xp.cross(b1, b2)], axis=-1)


def mat_to_rot6d(m: Array) -> Array:
    """Rotation matrices (..., 3, 3) -> their first two columns (..., 6), column 0 first."""
    xp = array_module(m)
    m = xp.asarray(m)
    return xp.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1)


def solve_spd(a: Array, b: Array) -> Array:
    """x with a x = b for small symmetric positive definite a (..., n, n), b (..., n).
    numpy: its LU solve.  jax: a Cholesky factorisation unrolled into elementwise
    arithmetic, which XLA fuses into a few kernels with no solver-library call, so the
    IK loops around it can run on a GPU as one CUDA graph (control.jit_for_robot)."""
    xp = array_module(a, b)
    if xp is np:
        return np.linalg.solve(a, b[..., None])[..., 0]
    n = a.shape[-1]
    low = [[None] * n for _ in range(n)]  # the factor's entries, each (...,)
    for j in range(n):
        diag = a[..., j, j] - sum(low[j][k] * low[j][k] for k in range(j))
        low[j][j] = jnp.sqrt(diag)
        for i in range(j + 1, n):
            low[i][j] = (a[..., i, j] - sum(low[i][k] * low[j][k] for k in range(j))) / low[j][j]
    y: list = []
    for i in range(n):  # low y = b
        y.append((b[..., i] - sum(low[i][k] * y[k] for k in range(i))) / low[i][i])
    x: list = [None] * n
    for i in reversed(range(n)):  # low^T x = y
        x[i] = (y[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) / low[i][i]
    return jnp.stack(x, -1)


def halton(n: int, dims: int) -> np.ndarray:
    """The first n points (skipping 0) of the Halton sequence in [0, 1)^dims."""
    primes = [2, 3, 5, 7, 11, 13, 17, 19, 23, 29][:dims]
    out = np.zeros((n, dims))
    for d, base in enumerate(primes):
        for i in range(n):
            k, f, x = i + 1, 1.0, 0.0
            while k:
                f /= base
                x += f * (k % base)
                k //= base
            out[i, d] = x
    return out
