"""Key actions -> joint position targets, batched over worlds.

Pure functions over numpy or jax arrays (see math3d.array_module): jax on a device,
numpy on CPU (XLA's per-op overhead on these tiny 7-joint kernels is large there).

Pipeline per key action (RLBench's MoveArmThenGripper with planning):
workspace check -> damped-least-squares IK (joint limits, warm start, a few
restarts) -> Cartesian-linear path if every intermediate pose solves, else a
joint-space path -> time-scaled position targets for the physics substeps,
then a separate gripper phase once the arm has arrived.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from collections.abc import Callable
from dataclasses import dataclass

import jax
import mujoco
import numpy as np

from agnostos_mjx.infra.cuda_graphs import graph_jit
from agnostos_mjx.sim.math3d import (
    array_module,
    halton,
    mat_to_quat,
    quat_angle,
    quat_error,
    quat_to_mat,
    slerp,
    solve_spd,
)
from agnostos_mjx.sim.world import ARM_JOINTS, FINGER_OPEN, HOME_QPOS

# Valid targets for the tip: PerAct's scene bounds in x and y, and from the
# table top up 1 m in z (the AGNOSTOS RLBench fork's boundary check).
ACTION_BOUNDS = ((-0.3, -0.5, 0.752), (0.7, 0.5, 1.752))
BOUNDS_TOL = 1e-5  # m
IK_POS_TOL = 0.005  # m
IK_ROT_TOL = np.deg2rad(3.0)
CART_SEGMENTS = 12
MAX_TIP_SPEED = 0.5  # m/s
MAX_JOINT_SPEED = 1.5  # rad/s
MIN_MOVE_TIME = 0.3  # s
SETTLE_TIME = 0.15  # s, hold after arriving so joint speeds fall below PerAct's 0.1 rad/s
GRIPPER_TIME = 0.3  # s
STEP_BUCKETS = (64, 128, 256, 512)


class Status(enum.IntEnum):
    """Why a key action could not be executed (0 = it could)."""

    OK = 0
    OUT_OF_WORKSPACE = 1
    UNREACHABLE = 2
    INVALID_ACTION = 3


@dataclass(frozen=True, eq=False)
class PandaKinematics:
    """Forward kinematics of the Panda chain read from the compiled model, so
    IK and physics can never disagree about link offsets."""

    base_pos: np.ndarray
    base_quat: np.ndarray
    link_pos: np.ndarray  # (7, 3) offset of link i in its parent
    link_quat: np.ndarray  # (7, 4)
    hand_pos: np.ndarray
    hand_quat: np.ndarray
    tip_pos: np.ndarray
    tip_quat: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    home: np.ndarray

    @classmethod
    def from_model(cls, m: mujoco.MjModel) -> PandaKinematics:
        links = [m.body(f"link{i}") for i in range(1, 8)]
        ranges = np.array([m.joint(j).range for j in ARM_JOINTS])
        tip = m.site("tip")
        return cls(
            base_pos=m.body("link0").pos.copy(),
            base_quat=m.body("link0").quat.copy(),
            link_pos=np.array([b.pos for b in links]),
            link_quat=np.array([b.quat for b in links]),
            hand_pos=m.body("hand").pos.copy(),
            hand_quat=m.body("hand").quat.copy(),
            tip_pos=tip.pos.copy(),
            tip_quat=tip.quat.copy(),
            lower=ranges[:, 0],
            upper=ranges[:, 1],
            home=np.array(HOME_QPOS),
        )

    @functools.cached_property
    def fingerprint(self) -> bytes:
        """The kinematic constants as bytes: equal for every task (one Panda), so jitted
        programs keyed by it (`jit_for_robot`) compile once per run, not once per task."""
        return b"".join(np.ascontiguousarray(getattr(self, f.name), np.float64).tobytes()
                        for f in dataclasses.fields(self))

    @functools.cached_property
    def _constant_frames(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(base rotation, link rotations, tip offset and rotation in the last link): the
        fixed parts of `forward`, computed once (they were 40% of a numpy IK step)."""
        hand_rot = quat_to_mat(np.asarray(self.hand_quat))
        return (quat_to_mat(np.asarray(self.base_quat)), quat_to_mat(np.asarray(self.link_quat)),
                np.asarray(self.hand_pos) + hand_rot @ np.asarray(self.tip_pos),
                hand_rot @ quat_to_mat(np.asarray(self.tip_quat)))

    def forward(self, q):
        """Tip (pos, quat) and each joint's (origin, z axis) in the world, for
        joint vectors q (..., 7).  Rotation matrices, not quaternions: about
        8x fewer array operations, which is what numpy's per-call cost needs."""
        xp = array_module(q)
        batch = q.shape[:-1]
        base_rot, link_rot, tip_offset, tip_rot = self._constant_frames
        rot = xp.broadcast_to(xp.asarray(base_rot), (*batch, 3, 3))
        pos = xp.broadcast_to(xp.asarray(self.base_pos), (*batch, 3))
        cos, sin = xp.cos(q)[..., None], xp.sin(q)[..., None]
        origins, axes = [], []
        for i in range(7):
            pos = pos + rot @ xp.asarray(self.link_pos[i])
            rot = rot @ xp.asarray(link_rot[i])
            origins.append(pos)
            axes.append(rot[..., :, 2])
            x, y = rot[..., :, 0], rot[..., :, 1]  # rot @ Rz(q_i), column by column
            rot = xp.stack([cos[..., i, :] * x + sin[..., i, :] * y,
                            cos[..., i, :] * y - sin[..., i, :] * x, rot[..., :, 2]], axis=-1)
        pos = pos + rot @ xp.asarray(tip_offset)
        rot = rot @ xp.asarray(tip_rot)
        return pos, mat_to_quat(rot), xp.stack(origins, -2), xp.stack(axes, -2)

    def tip_pose(self, q):
        pos, quat, _, _ = self.forward(q)
        return pos, quat

    def jacobian(self, q):
        """Geometric Jacobian (..., 6, 7): linear rows then angular rows."""
        pos, _, origins, axes = self.forward(q)
        return _jacobian(pos, origins, axes)


def _jacobian(pos, origins, axes):
    """Geometric Jacobian of revolute joints from their world origins and axes."""
    xp = array_module(pos, origins, axes)
    lin = xp.cross(axes, pos[..., None, :] - origins)
    return xp.concatenate([xp.swapaxes(lin, -1, -2), xp.swapaxes(axes, -1, -2)], axis=-2)


def _fori(xp, n: int, body, init, converged=None):
    """A fixed-count loop: lax.fori_loop under JAX; a Python loop for numpy,
    which may stop early once `converged(state)` holds (checked every 5 steps)."""
    if xp is np:
        for i in range(n):
            init = body(i, init)
            if converged is not None and i % 5 == 4 and converged(init):
                break
        return init
    return jax.lax.fori_loop(0, n, body, init)


def _dls_step(kin: PandaKinematics, q, target_pos, target_quat, restart: bool = False):
    """One damped-least-squares step from q (..., 7); returns (next q, position error,
    rotation error), the errors measured at q (before the step).

    The plain step (warm start, Cartesian paths) keeps a constant weak pull to mid-range:
    its fixed point is the posture the experts were tuned with, the tip ~1 mm off the
    target.  A `restart` step, from a seed far from the target, fades the pull with the
    error (so it converges exactly) and takes joints resting on a limit that the step would
    push further out of the solve (their columns zeroed, solved again), so the other joints
    make up the motion instead of the clipped step stalling there."""
    xp = array_module(q, target_pos, target_quat)
    lower, upper = xp.asarray(kin.lower), xp.asarray(kin.upper)
    weight = xp.asarray([1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
    pos, quat, origins, axes = kin.forward(q)
    pos_err, rot_err = target_pos - pos, quat_error(target_quat, quat)
    err = xp.concatenate([pos_err, rot_err], -1) * weight
    jac = _jacobian(pos, origins, axes) * weight[:, None]
    # min |J dq - e|^2 + lam^2 |dq|^2 + mu^2 |q + dq - rest|^2 (weak pull to mid-range)
    sq = xp.sum(err**2, -1)
    lam2 = 1e-4 + 0.01 * sq
    mu2 = 1e-4 * (xp.minimum(1.0, sq / 1e-4) if restart else xp.ones_like(sq))
    pull_rhs = mu2[..., None] * (0.5 * (lower + upper) - q)

    def solve(j):
        jt = xp.swapaxes(j, -1, -2)
        lhs = jt @ j + (lam2 + mu2)[..., None, None] * xp.eye(7)
        rhs = (jt @ err[..., None])[..., 0] + pull_rhs
        return solve_spd(lhs, rhs)

    dq = solve(jac)
    if restart:
        blocked = ((q <= lower + 1e-6) & (dq < 0)) | ((q >= upper - 1e-6) & (dq > 0))
        dq = xp.where(blocked, 0.0, solve(jac * ~blocked[..., None, :]))
    norm = xp.linalg.norm(dq, axis=-1, keepdims=True)
    dq = dq * xp.minimum(1.0, 0.4 / (norm + 1e-9))
    return (xp.clip(q + dq, lower, upper), xp.linalg.norm(pos_err, axis=-1),
            xp.linalg.norm(rot_err, axis=-1))  # a rotation vector's norm is its angle


def _ik_from(kin: PandaKinematics, q0, target_pos, target_quat, iters: int,
             restart: bool = False):
    """Damped least squares from q0 (..., 7) for a fixed number of steps (numpy
    may stop once every row has converged); returns (q, pos error, rot error)."""
    xp = array_module(q0, target_pos, target_quat)

    def converged(q):
        pos, quat = kin.tip_pose(q)
        return bool(np.all(np.linalg.norm(target_pos - pos, axis=-1) < 0.1 * IK_POS_TOL)
                    and np.all(quat_angle(target_quat, quat) < 0.1 * IK_ROT_TOL))

    q = _fori(xp, iters, lambda _, q: _dls_step(kin, q, target_pos, target_quat, restart)[0], q0,
              converged)
    pos, quat = kin.tip_pose(q)
    return q, xp.linalg.norm(target_pos - pos, axis=-1), quat_angle(target_quat, quat)


SPREAD_SEEDS = 24  # fixed restarts spread over the joint ranges (Halton points)
_SPREAD_UNIT = halton(SPREAD_SEEDS, 7)


def _spread_seeds(kin: PandaKinematics) -> np.ndarray:
    """(SPREAD_SEEDS, 7) deterministic configurations covering the joint ranges
    (5% in from each limit), so a restart exists near every IK branch."""
    span = kin.upper - kin.lower
    return kin.lower + 0.05 * span + 0.9 * span * _SPREAD_UNIT


def _local_seeds(kin: PandaKinematics, q_init):
    """(4, ..., 7): the warm start, home and home with the wrist turned by +-pi."""
    xp = array_module(q_init)
    flip = xp.asarray([0, 0, 0, 0, 0, 0, np.pi])
    home = xp.broadcast_to(xp.asarray(kin.home), q_init.shape)
    return xp.clip(xp.stack([q_init, home, home + flip, home - flip]), kin.lower, kin.upper)


def _ok(pos_err, rot_err, scale: float = 1.0):
    return (pos_err < scale * IK_POS_TOL) & (rot_err < scale * IK_ROT_TOL)


STALL_CHECK = 10  # iterations between progress checks of a restart
STALL_GAIN = 0.98  # a restart whose error did not fall below this fraction is dropped
STEP_TOL = 1e-4  # rad: a solution within tolerance whose step is smaller has converged


def _descend_np(kin: PandaKinematics, q0: np.ndarray, target: np.ndarray, target_pos: np.ndarray,
                target_quat: np.ndarray, n_targets: int, iters: int, restart: bool):
    """Damped least squares on rows q0 (R, 7) aimed at target_pos/quat[target]. A row stops
    once it has converged (within tolerance and no longer moving) or, out of tolerance, once
    it stalls (a local minimum, or an unreachable target); with `restart` all rows of a
    target stop at its first converged row. Easy batches thus cost a few steps and hopeless
    restarts little. Returns (q, pos error, rot error) per row, the errors at the returned
    q."""
    q, pe, re = q0.copy(), np.full(len(q0), np.inf), np.full(len(q0), np.inf)
    rows = np.arange(len(q0))
    solved = np.zeros(n_targets, bool)
    last = np.full(len(q0), np.inf)  # error at the previous progress check
    for i in range(iters):
        t = target[rows]
        q_next, pe[rows], re[rows] = _dls_step(kin, q[rows], target_pos[t], target_quat[t],
                                               restart)
        ok = _ok(pe[rows], re[rows])
        done = ok & (np.abs(q_next - q[rows]).max(-1) < STEP_TOL)
        solved[t[done]] = restart
        keep = ~done & ~solved[t]
        if i % STALL_CHECK == STALL_CHECK - 1:
            err = pe[rows] / IK_POS_TOL + re[rows] / IK_ROT_TOL
            keep &= ok | (err < STALL_GAIN * last[rows])
            last[rows] = err
        rows = rows[keep]
        q[rows] = q_next[keep]
        if not rows.size:
            return q, pe, re
    pos, quat = kin.tip_pose(q[rows])
    t = target[rows]
    pe[rows] = np.linalg.norm(target_pos[t] - pos, axis=-1)
    re[rows] = quat_angle(target_quat[t], quat)
    return q, pe, re


def _nearest_ok(q_init, qs, pe, re, n_seeds: int):
    """Per target, the row (of n_seeds rows per target, seed-major) within tolerance nearest
    the warm start, else the one with the smallest error."""
    n = len(q_init)
    cost = np.where(_ok(pe, re), np.linalg.norm(qs - np.tile(q_init, (n_seeds, 1)), axis=-1),
                    1e3 + pe + re)
    best = np.argmin(cost.reshape(n_seeds, n), axis=0) * n + np.arange(n)
    return qs[best], pe[best], re[best]


def _solve_ik_np(kin: PandaKinematics, q_init, target_pos, target_quat, iters: int,
                 spread: bool):
    """Numpy IK in two stages: the warm start, home and the wrist flips (the plain step, as the
    Cartesian paths use; the solution nearest the warm start), then, for the targets these
    missed, restarts from the spread seeds, batched; a restart's solution is kept only where
    the first stage failed."""
    shape = q_init.shape[:-1]
    q_init = q_init.reshape(-1, 7)
    target_pos, target_quat = target_pos.reshape(-1, 3), target_quat.reshape(-1, 4)
    n = len(q_init)
    local = _local_seeds(kin, q_init)
    qs, pes, res = _descend_np(kin, local.reshape(-1, 7), np.tile(np.arange(n), len(local)),
                               target_pos, target_quat, n, iters, restart=False)
    q, pe, re = _nearest_ok(q_init, qs, pes, res, len(local))
    todo = np.flatnonzero(~_ok(pe, re))
    if spread and todo.size:
        seeds = np.broadcast_to(_spread_seeds(kin)[:, None], (SPREAD_SEEDS, todo.size, 7))
        qs, pes, res = _descend_np(kin, seeds.reshape(-1, 7), np.tile(np.arange(todo.size),
                                                                      SPREAD_SEEDS),
                                   target_pos[todo], target_quat[todo], todo.size, iters,
                                   restart=True)
        q[todo], pe[todo], re[todo] = _nearest_ok(q_init[todo], qs, pes, res, SPREAD_SEEDS)
    return q.reshape(*shape, 7), _ok(pe, re).reshape(shape), pe.reshape(shape), re.reshape(shape)


def solve_ik(kin: PandaKinematics, q_init, target_pos, target_quat, iters: int = 100,
             spread: bool = True):
    """Batched IK (..., 7) with restarts from the warm start, home, two wrist-flipped homes and
    (with `spread`) SPREAD_SEEDS configurations spread over the joint ranges. Returns (q,
    ok, pos_err, rot_err) of the solution nearest the warm start among those within
    tolerance. Numpy stops each target at its first converged restart; JAX (inside jit) runs
    every restart for `iters` steps. `spread=False` asks whether a target is reachable near
    the warm start's branch (how a scripted expert moves)."""
    xp = array_module(q_init, target_pos, target_quat)
    if xp is np:
        return _solve_ik_np(kin, np.asarray(q_init, np.float64), np.asarray(target_pos, np.float64),
                            np.asarray(target_quat, np.float64), iters, spread)
    starts = [(_local_seeds(kin, q_init), False)]
    if spread:
        starts.append((xp.broadcast_to(xp.asarray(_spread_seeds(kin))[:, None],
                                       (SPREAD_SEEDS, *q_init.shape)), True))
    runs = [_ik_from(kin, seeds, target_pos[None], target_quat[None], iters, restart)
            for seeds, restart in starts]
    qs, pe, re = (xp.concatenate(parts) for parts in zip(*runs, strict=True))
    ok = _ok(pe, re)
    cost = xp.where(ok, xp.linalg.norm(qs - q_init[None], axis=-1), 1e3 + pe + re)
    best = xp.argmin(cost, axis=0)
    pick = lambda a: xp.take_along_axis(a, best[None, ..., None] if a.ndim == qs.ndim else  # noqa: E731
                                        best[None], axis=0)[0]
    return pick(qs), pick(ok), pick(pe), pick(re)


_ROBOT_PROGRAMS: dict[tuple, Callable] = {}


def jit_for_robot(fn: Callable, kin: PandaKinematics) -> Callable:
    """`jax.jit(partial(fn, kin))`, shared by every task with the same robot in this process
    (a cache keyed by the kinematic constants), so the IK programs of a run compile once; on
    a GPU the IK's loops run as CUDA graphs (cuda_graphs.graph_jit)."""
    key = (fn, kin.fingerprint)
    if key not in _ROBOT_PROGRAMS:
        _ROBOT_PROGRAMS[key] = graph_jit(functools.partial(fn, kin))
    return _ROBOT_PROGRAMS[key]


def _smoothstep(xp, x):
    x = xp.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def within_bounds(pos):
    """Whether tip positions (..., 3) lie in ACTION_BOUNDS, inclusive up to float32 rounding:
    a target clipped to the bounds in float32 (0.752 -> 0.75199997) is inside."""
    xp = array_module(pos)
    lo, hi = xp.asarray(ACTION_BOUNDS[0]), xp.asarray(ACTION_BOUNDS[1])
    return xp.all((pos >= lo - BOUNDS_TOL) & (pos <= hi + BOUNDS_TOL), -1)


CART_ITERS = 25  # IK steps per Cartesian segment (warm-started from the previous one)
MAX_SEGMENT_JUMP = 0.5  # rad: a larger joint jump between segments is a branch switch


def _cartesian_np(kin: PandaKinematics, q0, p0, r0, target_pos, target_quat, todo):
    """The Cartesian chain in numpy on an active set: a world leaves a segment's loop once it
    has converged (errors within a tenth of the tolerance) and leaves the chain once a
    segment fails (its move then follows the joint path), so easy worlds cost a few steps
    and no world waits for the hardest one. Returns (path (B, S+1, 7), ok)."""
    path = np.repeat(q0[:, None], CART_SEGMENTS + 1, axis=1)
    ok = np.asarray(todo, bool).copy()
    rows = np.flatnonzero(ok)
    for k in range(1, CART_SEGMENTS + 1):
        if not rows.size:
            break
        t = k / CART_SEGMENTS
        goal_p = p0[rows] + t * (target_pos[rows] - p0[rows])
        goal_q = slerp(r0[rows], target_quat[rows], np.full(rows.size, t))
        start = path[rows, k - 1]
        q, live = start.copy(), np.arange(rows.size)
        for _ in range(CART_ITERS):
            step, pe, re = _dls_step(kin, q[live], goal_p[live], goal_q[live])
            moving = ~_ok(pe, re, 0.1)
            q[live[moving]] = step[moving]
            live = live[moving]
            if not live.size:
                break
        pos, quat = kin.tip_pose(q)
        seg_ok = (_ok(np.linalg.norm(goal_p - pos, axis=-1), quat_angle(goal_q, quat))
                  & (np.abs(q - start).max(-1) < MAX_SEGMENT_JUMP))
        path[rows, k:] = q[:, None]
        ok[rows[~seg_ok]] = False
        rows = rows[seg_ok]
    return path, ok


def _checked_targets(target_pos, target_quat):
    """(pos, unit quat, finite, inside the bounds) of B targets: non-finite ones replaced by
    a harmless pose (their status says INVALID_ACTION), quaternions normalised."""
    xp = array_module(target_pos, target_quat)
    finite = xp.all(xp.isfinite(target_pos), -1) & xp.all(xp.isfinite(target_quat), -1)
    target_pos = xp.where(finite[:, None], target_pos, 0.0)
    norm = xp.linalg.norm(xp.where(finite[:, None], target_quat, 1.0), axis=-1, keepdims=True)
    target_quat = xp.where(finite[:, None] & (norm > 1e-6), target_quat / xp.maximum(norm, 1e-6),
                           xp.asarray([1.0, 0.0, 0.0, 0.0]))
    return target_pos, target_quat, finite, within_bounds(target_pos)


def _status(finite, inside, solved):
    """The planner's verdict per world (Status codes, int32)."""
    xp = array_module(finite, inside, solved)
    return xp.where(
        ~finite, int(Status.INVALID_ACTION),
        xp.where(~inside, int(Status.OUT_OF_WORKSPACE),
                 xp.where(solved, int(Status.OK), int(Status.UNREACHABLE))),
    ).astype(xp.int32)


def plan_arm(kin: PandaKinematics, q0, target_pos, target_quat):
    """Plan the arm motion of B worlds (q0 (B, 7), targets (B, 3)/(B, 4)).
    Returns (path (B, CART_SEGMENTS+1, 7), duration (B,) seconds, status (B,))."""
    xp = array_module(q0, target_pos, target_quat)
    target_pos, target_quat, finite, inside = _checked_targets(target_pos, target_quat)
    q_goal, ok_goal, _, _ = solve_ik(kin, q0, target_pos, target_quat)

    # Cartesian-linear path: chain IK along the straight line, warm-started.
    p0, r0 = kin.tip_pose(q0)
    if xp is np:
        cart_path, cart_ok = _cartesian_np(kin, q0, p0, r0, target_pos, target_quat,
                                           finite & inside)
    else:  # a scan over the segments: one traced segment, so the program compiles quickly
        def segment(carry, t):
            q, ok = carry
            goal_p, goal_q = p0 + t * (target_pos - p0), slerp(r0, target_quat, xp.full(len(q0), t))

            def step(c):  # as _cartesian_np: a world stops once within a tenth of tolerance
                i, q, live = c
                q_next, pe, re = _dls_step(kin, q, goal_p, goal_q)
                live = live & ~_ok(pe, re, 0.1)
                return i + 1, xp.where(live[:, None], q_next, q), live

            _, q_next, _ = jax.lax.while_loop(lambda c: (c[0] < CART_ITERS) & c[2].any(),
                                              step, (0, q, ok))
            pos, quat = kin.tip_pose(q_next)
            ok = ok & _ok(xp.linalg.norm(goal_p - pos, axis=-1), quat_angle(goal_q, quat)) \
                & (xp.max(xp.abs(q_next - q), -1) < MAX_SEGMENT_JUMP)
            return (q_next, ok), q_next

        ts = xp.arange(1, CART_SEGMENTS + 1, dtype=q0.dtype) / CART_SEGMENTS
        (_, cart_ok), qs = jax.lax.scan(segment, (q0, finite & inside), ts)
        cart_path = xp.concatenate([q0[:, None], xp.swapaxes(qs, 0, 1)], 1)
    ts = xp.linspace(0.0, 1.0, CART_SEGMENTS + 1)[None, :, None]
    joint_path = q0[:, None] + ts * (q_goal - q0)[:, None]
    path = xp.where(cart_ok[:, None, None], cart_path, joint_path)

    status = _status(finite, inside, cart_ok | ok_goal)
    dist = xp.linalg.norm(target_pos - p0, axis=-1)
    joint_dist = xp.max(xp.abs(xp.diff(path, axis=1)).sum(1), -1)
    duration = xp.maximum(MIN_MOVE_TIME, xp.maximum(dist / MAX_TIP_SPEED,
                                                    joint_dist / MAX_JOINT_SPEED))
    path = xp.where((status == Status.OK)[:, None, None], path, q0[:, None])
    return path, duration, status


def _along_path(path, duration, t):
    """Joint targets (B, T, 7) at times t (1 or B, T) since the move began: each world
    follows its `path` (B, S, 7) with a smooth time profile of its own `duration` (B,)."""
    xp = array_module(path, duration, t)
    s = _smoothstep(xp, t / duration[:, None]) * (path.shape[1] - 1)
    i = xp.clip(xp.floor(s).astype(xp.int32), 0, path.shape[1] - 2)
    frac = (s - i)[..., None]
    take = lambda idx: xp.take_along_axis(path, idx[..., None], axis=1)  # noqa: E731
    return take(i) * (1 - frac) + take(i + 1) * frac


def arm_targets_at(path, duration, t):
    """Joint targets (B, T, 7) at the times t (T,) since the move began (s)."""
    return _along_path(path, duration, t[None])


def bucket_steps(seconds, dt: float):
    """Round durations up to a few lengths (STEP_BUCKETS, then multiples of the last), so
    moves of similar length share a timeline on every backend.  Scalar or array."""
    xp = array_module(seconds)
    need = xp.ceil(xp.asarray(seconds) / dt).astype(xp.int32)
    out = xp.ceil(need / STEP_BUCKETS[-1]).astype(xp.int32) * STEP_BUCKETS[-1]
    for b in reversed(STEP_BUCKETS):
        out = xp.where(need <= b, b, out)
    return int(out) if xp is np and np.ndim(out) == 0 else out


def gripper_target_at(start, goal, t):
    """Finger position targets at time t (s) of the gripper phase: start, goal and t
    broadcast together."""
    xp = array_module(start, goal, t)
    s = xp.clip(t / (0.6 * GRIPPER_TIME), 0.0, 1.0)
    return start + s * (goal - start)


def finger_target(open_amount):
    xp = array_module(open_amount)
    return xp.clip(open_amount, 0.0, 1.0) * FINGER_OPEN


def reachable(kin: PandaKinematics, q, pos, quat, valid):
    """Whether each world's key actions (B, K) are inside the bounds and solvable by IK
    near the expert's branch, warm-started along the sequence: a Python loop over numpy
    (float64) on the host, one `lax.scan` under JAX (thousands of worlds reset at once)."""
    xp = array_module(q, pos, quat, valid)

    def body(carry, action):
        q, ok = carry
        p, r, v = action
        q_k, ok_k, _, _ = solve_ik(kin, q, p, r, spread=False)
        ok = ok & (~v | (ok_k & within_bounds(p)))
        return (xp.where(v[:, None], q_k, q), ok), None

    dtype = np.float64 if xp is np else np.float32
    pos, quat = xp.asarray(pos, dtype), xp.asarray(quat, dtype)
    xs = (xp.swapaxes(pos, 0, 1), xp.swapaxes(quat, 0, 1), xp.swapaxes(xp.asarray(valid), 0, 1))
    carry = (xp.asarray(q, dtype), xp.ones(len(q), bool))
    if xp is np:
        for action in zip(*xs):
            carry, _ = body(carry, action)
    else:
        carry, _ = jax.lax.scan(body, carry, xs)
    return carry[1]


# ---- dense control (runtime/dense.py) -------------------------------------------------------
DENSE_IK_ITERS = 100  # damped least squares steps from the warm start (numpy stops earlier)
FINGER_SPEED = FINGER_OPEN / (0.6 * GRIPPER_TIME)  # m/s: the key action's full ramp, 0.18 s


def dense_ik(kin: PandaKinematics, q0, target_pos, target_quat):
    """The joint goal of one dense control step: damped least squares warm-started at the
    current joints q0 (B, 7), no seeds elsewhere and no path (a target a control period
    away is near); returns (q (B, 7), status (B,)), q0 where the status is not OK.

    Targets are clipped into ACTION_BOUNDS, not refused: the arm's own trajectory between
    key actions leaves the box (by 0.3 mm in a place_wine demo), so the dense export's
    frames do too.  The plain step first (the experts' posture); where it stalls out of
    tolerance, typically on a joint limit, the limit-aware restart step from the same warm
    start.  Numpy stops each world once it converges; JAX runs DENSE_IK_ITERS steps of
    both."""
    xp = array_module(q0, target_pos, target_quat)
    target_pos, target_quat, finite, _ = _checked_targets(target_pos, target_quat)
    target_pos = xp.clip(target_pos, xp.asarray(ACTION_BOUNDS[0]), xp.asarray(ACTION_BOUNDS[1]))
    if xp is np:
        n = len(q0)
        q0 = np.asarray(q0, np.float64)
        q, pe, re = _descend_np(kin, q0, np.arange(n), target_pos, target_quat, n,
                                DENSE_IK_ITERS, restart=False)
        todo = np.flatnonzero(~_ok(pe, re))
        if todo.size:
            q2, pe2, re2 = _descend_np(kin, q0[todo], np.arange(todo.size), target_pos[todo],
                                       target_quat[todo], todo.size, DENSE_IK_ITERS,
                                       restart=True)
            q[todo], pe[todo], re[todo] = q2, pe2, re2
    else:
        q, pe, re = _ik_from(kin, q0, target_pos, target_quat, DENSE_IK_ITERS)
        q2, pe2, re2 = _ik_from(kin, q0, target_pos, target_quat, DENSE_IK_ITERS, restart=True)
        retry = ~_ok(pe, re)
        q = xp.where(retry[:, None], q2, q)
        pe, re = xp.where(retry, pe2, pe), xp.where(retry, re2, re)
    status = _status(finite, xp.ones_like(finite), _ok(pe, re))
    return xp.where((status == Status.OK)[:, None], q, q0), status


def gripper_toward(start, goal, t):
    """Finger targets moving from `start` toward `goal` at FINGER_SPEED for t seconds
    (dense control: the gripper is commanded directly, at the gripper's rate)."""
    xp = array_module(start, goal, t)
    reach = FINGER_SPEED * t
    return start + xp.clip(goal - start, -reach, reach)
