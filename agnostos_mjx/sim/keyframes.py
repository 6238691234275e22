"""PerAct / ARM keyframe ("keypoint") discovery, as used by X-ICM to turn a demo into actions.

A faithful re-implementation of ``keypoint_discovery(demo, stopping_delta=0.1)`` with the
``'heuristic'`` method (ARM ``demo_loading_utils.py``, PerAct ``helpers/demo_loading_utils.py``,
X-ICM ``_keypoint_discovery``), on plain arrays instead of an RLBench ``Demo``. Keeping the
original's quirks matters: the keyframes define the demo actions the LLM imitates.
"""

from __future__ import annotations

import numpy as np

STOPPED_BUFFER_FRAMES = 4  # after a stop, the next 4 frames cannot be stops (>= 5 apart)


def _is_stopped(
    gripper_open: np.ndarray,
    joint_velocities: np.ndarray,
    i: int,
    stopped_buffer: int,
    delta: float,
) -> bool:
    """The original ``_is_stopped``: still arm, gripper steady over i-2..i+1, buffer expired.

    ``i - 1`` and ``i - 2`` use Python negative indexing exactly like the original
    (``demo[i - 1]`` on a list), so at i = 0 and 1 they wrap to the end of the demo. Frame 0 is
    never a keypoint, but a "stop" found there still arms the buffer and blocks frames 1..4.
    """
    n = len(gripper_open)
    is_second_to_last = i == n - 2
    gripper_steady = i < n - 2 and bool(
        gripper_open[i] == gripper_open[i + 1]
        and gripper_open[i] == gripper_open[i - 1]
        and gripper_open[i - 2] == gripper_open[i - 1]
    )
    small_delta = bool(np.allclose(joint_velocities[i], 0, atol=delta))
    return stopped_buffer <= 0 and small_delta and not is_second_to_last and gripper_steady


def discover_keyframes(
    gripper_open: np.ndarray,
    joint_velocities: np.ndarray,
    stopping_delta: float = 0.1,
) -> list[int]:
    """Keyframe indices of a demo, in increasing order.

    Args:
        gripper_open: (T,) gripper flag per frame, 1 = open, 0 = closed.
        joint_velocities: (T, n_joints) arm joint velocities in rad/s (7 for the Panda).
        stopping_delta: an arm is still when every |joint velocity| <= this.

    Frame i (i != 0) is a keyframe if the gripper flag changed from frame i-1, if i is the last
    frame, or if the arm is "stopped" (see ``_is_stopped``: still, gripper unchanged over
    i-2..i+1 which needs i < T-2, not the second-to-last frame, and the stop buffer expired; a
    stop sets the buffer to 4, every other frame decrements it). Finally, if the last two
    keyframes are consecutive frames, the second-to-last one is dropped.
    """
    g = np.asarray(gripper_open)
    v = np.asarray(joint_velocities)
    if g.ndim != 1:
        raise ValueError(f"gripper_open must be (T,), got shape {g.shape}")
    if v.ndim != 2 or v.shape[0] != g.shape[0]:
        raise ValueError(f"joint_velocities must be (T, n), T={g.shape[0]}, got {v.shape}")
    n = g.shape[0]

    keyframes: list[int] = []
    stopped_buffer = 0
    prev_open = g[0] if n else None
    for i in range(n):
        stopped = _is_stopped(g, v, i, stopped_buffer, stopping_delta)
        stopped_buffer = STOPPED_BUFFER_FRAMES if stopped else stopped_buffer - 1
        last = i == n - 1
        if i != 0 and (g[i] != prev_open or last or stopped):
            keyframes.append(i)
        prev_open = g[i]
    if len(keyframes) > 1 and keyframes[-1] - 1 == keyframes[-2]:
        keyframes.pop(-2)
    return keyframes


def merge_repeated_keyframes(
    keyframes: list[int] | np.ndarray,
    positions: np.ndarray,
    quats: np.ndarray,
    gripper_open: np.ndarray,
    max_distance: float = 0.01,
    max_angle_deg: float = 5.0,
) -> list[int]:
    """Merge runs of consecutive keyframes at the same pose (keeping the last).

    Our controller holds the arm still after each waypoint until the servos
    settle; RLBench starts the next path at once.  On a hold the PerAct rule
    finds a "stop" every 5 frames, so one waypoint would become several
    identical key actions (wasting the LLM's 256-token budget).  Keyframes
    within `max_distance` metres and `max_angle_deg` of the next one with the
    same gripper flag are dropped.  Arrays are per frame (positions (T, 3),
    quats (T, 4) wxyz, gripper_open (T,)).
    """
    keys = [int(k) for k in keyframes]
    out: list[int] = []
    for k, nxt in zip(keys, keys[1:] + [None]):
        if nxt is not None and gripper_open[k] == gripper_open[nxt]:
            near = np.linalg.norm(positions[k] - positions[nxt]) <= max_distance
            dot = abs(float(np.dot(quats[k], quats[nxt])))
            angle = np.degrees(2 * np.arccos(min(1.0, dot)))
            if near and angle <= max_angle_deg:
                continue
        out.append(k)
    return out


__all__ = ["STOPPED_BUFFER_FRAMES", "discover_keyframes", "merge_repeated_keyframes"]
