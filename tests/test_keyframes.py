"""Tests for PerAct/ARM keyframe discovery on hand-built traces.

Expected index lists are worked out by hand from the rule; ``STILL`` frames have all joint
velocities below the 0.1 rad/s threshold, all others move.
"""

from __future__ import annotations

import numpy as np
import pytest

from agnostos_mjx.sim.keyframes import discover_keyframes

MOVING = 0.5


def _trace(
    n: int, still: list[int] | range = (), closed: list[int] | range = ()
) -> tuple[np.ndarray, np.ndarray]:
    """A demo of n frames: arm still at ``still``, gripper closed at ``closed``, else open."""
    vel = np.full((n, 7), MOVING)
    for i in still:
        vel[i] = 0.0
    grip = np.ones(n)
    for i in closed:
        grip[i] = 0.0
    return grip, vel


def test_gripper_change_and_last_frame() -> None:
    # Always moving; gripper closes at 5. Keys: 5 (change), 9 (last).
    grip, vel = _trace(10, closed=range(5, 10))
    assert discover_keyframes(grip, vel) == [5, 9]


def test_gripper_reopening_is_also_a_change() -> None:
    grip, vel = _trace(12, closed=range(3, 7))
    assert discover_keyframes(grip, vel) == [3, 7, 11]


def test_stop_is_a_keyframe() -> None:
    # Still at 4, 5, 6: a stop at 4 arms the buffer so 5 and 6 are not stops. Last: 11.
    grip, vel = _trace(12, still=[4, 5, 6])
    assert discover_keyframes(grip, vel) == [4, 11]


def test_threshold_is_inclusive_and_per_joint() -> None:
    grip, vel = _trace(12)
    vel[4] = 0.1  # |v| <= 0.1 on every joint: still
    vel[9] = 0.0
    vel[9, 3] = 0.11  # one joint above the threshold: moving
    assert discover_keyframes(grip, vel) == [4, 11]
    # A larger stopping_delta turns frame 9 (buffer expired 5 frames after 4) into a stop.
    assert discover_keyframes(grip, vel, stopping_delta=0.2) == [4, 9, 11]


def test_buffer_two_stops_closer_than_five_frames_give_one_keyframe() -> None:
    # Stop at 3 sets the buffer to 4; frames 4..7 see buffer 4, 3, 2, 1, so the still frame 7
    # is not a stop. Still frame 8 sees buffer 0: a stop (5 frames after 3). Last: 14.
    grip, vel = _trace(15, still=[3, 7])
    assert discover_keyframes(grip, vel) == [3, 14]
    grip, vel = _trace(15, still=[3, 8])
    assert discover_keyframes(grip, vel) == [3, 8, 14]


def test_long_still_period_gives_a_stop_every_five_frames() -> None:
    # Still 2..13, moving elsewhere, 20 frames: stops at 2, 7, 12; last 19.
    grip, vel = _trace(20, still=range(2, 14))
    assert discover_keyframes(grip, vel) == [2, 7, 12, 19]


def test_frame_zero_stop_arms_the_buffer_via_wraparound() -> None:
    # All still, gripper always open. At i=0 the original's demo[i-1], demo[i-2] wrap to the
    # last frames (same gripper), so frame 0 is a "stop": not a keyframe, but the buffer blocks
    # 1..4. Stops: 5; 10 is the second-to-last frame (excluded); 11 is the last.
    grip, vel = _trace(12, still=range(12))
    assert discover_keyframes(grip, vel) == [5, 11]


def test_frame_zero_no_stop_when_wrapped_gripper_differs() -> None:
    # Same, but the gripper is closed at the last frame: the wrapped check at i=0 and i=1 fails
    # (frame -1 differs), so the first stop is at 2 (i-2 = 0, i-1 = 1, i+1 = 3 all open).
    # Stops at 2 and 7 (8..10 are blocked by the buffer, 10 is also second-to-last); 11 is
    # both a gripper change and the last frame.
    grip, vel = _trace(12, still=range(12), closed=[11])
    assert discover_keyframes(grip, vel) == [2, 7, 11]


def test_second_to_last_frame_is_never_a_stop() -> None:
    grip, vel = _trace(10, still=[8])
    assert discover_keyframes(grip, vel) == [9]
    grip, vel = _trace(10, still=[7])  # T-3 is fine
    assert discover_keyframes(grip, vel) == [7, 9]


def test_stop_needs_gripper_unchanged_over_i_minus_2_to_i_plus_1() -> None:
    # Gripper closes at 6. Still at 5 (i+1 differs), 7 (i-2 differs from i-1): no stops.
    # Still at 8: 6..9 all closed -> stop. Keys: 6 (change), 8 (stop), 11 (last).
    grip, vel = _trace(12, still=[5, 7, 8], closed=range(6, 12))
    assert discover_keyframes(grip, vel) == [6, 8, 11]


def test_drop_second_to_last_when_last_two_are_consecutive() -> None:
    # Stop at 3; gripper closes at 8 (change) and 9 is last: [3, 8, 9] -> 8 dropped.
    grip, vel = _trace(10, still=[3], closed=[8, 9])
    assert discover_keyframes(grip, vel) == [3, 9]
    # Only the last pair is checked: closing at 3 and reopening at 4 keeps both.
    grip, vel = _trace(10, closed=[3])
    assert discover_keyframes(grip, vel) == [3, 4, 9]


def test_drop_rule_with_two_keyframes_only() -> None:
    grip, vel = _trace(6, closed=[4, 5])  # change at 4, last at 5 -> [5]
    assert discover_keyframes(grip, vel) == [5]


def test_short_demos() -> None:
    assert discover_keyframes(np.ones(0), np.zeros((0, 7))) == []
    assert discover_keyframes(np.ones(1), np.zeros((1, 7))) == []
    assert discover_keyframes(np.ones(2), np.zeros((2, 7))) == [1]
    assert discover_keyframes(np.array([1.0, 0.0, 0.0]), np.zeros((3, 7))) == [2]


def test_returns_python_ints_and_frame_zero_never_a_key() -> None:
    grip, vel = _trace(8, still=range(8), closed=[0])  # gripper "changes" at 1 w.r.t. frame 0
    # Keys: 1 (change), 3 (first frame with 1..4 steady), 7 (last; 6 is second-to-last and
    # still inside the buffer).
    keys = discover_keyframes(grip, vel)
    assert keys == [1, 3, 7]
    assert all(type(k) is int for k in keys)


def test_shape_errors() -> None:
    with pytest.raises(ValueError):
        discover_keyframes(np.ones(5), np.zeros((4, 7)))
    with pytest.raises(ValueError):
        discover_keyframes(np.ones((5, 1)), np.zeros((5, 7)))
