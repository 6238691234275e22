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
