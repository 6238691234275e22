"""Tests for X-ICM textualisation (scipy is the reference for the rotation conventions)."""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from agnostos_mjx.sim import textualise as tx

HOME_ACTION = [57, 49, 87, 0, 39, 0, 1]


def _wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    return np.roll(q_xyzw, 1, axis=-1)


def _xyzw(q_wxyz: np.ndarray) -> np.ndarray:
    return np.roll(np.asarray(q_wxyz, dtype=np.float64), -1, axis=-1)


def _reference_bins(q_xyzw: np.ndarray) -> np.ndarray:
    """The original ``quaternion_to_discrete_euler`` in float64 scipy."""
    q = q_xyzw / np.linalg.norm(q_xyzw, axis=-1, keepdims=True)
    q = np.where(q[..., 3:] < 0, -q, q)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy warns at gimbal lock
        euler = Rotation.from_quat(q).as_euler("xyz", degrees=True) + 180
    disc = np.around(euler / 5).astype(int)
    disc[disc == 72] = 0
    return disc


def _angle_deg(q1_wxyz: np.ndarray, q2_wxyz: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations, sign-invariant."""
    r = Rotation.from_quat(_xyzw(q1_wxyz)).inv() * Rotation.from_quat(_xyzw(q2_wxyz))
    return np.degrees(r.magnitude())


def _random_quats_xyzw(n: int, seed: int) -> np.ndarray:
    return Rotation.random(n, random_state=seed).as_quat()


# ---------------------------------------------------------------- positions


def test_constants() -> None:
    assert tx.SCENE_BOUNDS == (-0.3, -0.5, 0.6, 0.7, 0.5, 1.6)
    assert tx.VOXEL_SIZE == 100
    assert tx.ROTATION_RESOLUTION == 5


def test_voxel_round_trip_within_half_voxel() -> None:
    rng = np.random.default_rng(0)
    lo, hi = np.array(tx.SCENE_BOUNDS[:3]), np.array(tx.SCENE_BOUNDS[3:])
    pts = rng.uniform(lo, hi, size=(1000, 3))
    idx = tx.point_to_voxel(pts)
    assert idx.dtype == np.int32 and idx.shape == (1000, 3)
    back = np.asarray(tx.voxel_to_point(idx))
    assert np.all(np.abs(back - pts) <= 0.005 + 1e-5)
    # Re-encoding a voxel centre gives the same voxel.
    np.testing.assert_array_equal(np.asarray(tx.point_to_voxel(back)), np.asarray(idx))


def test_point_to_voxel_known_values() -> None:
    idx = tx.point_to_voxel(np.array([[0.275, -0.005, 1.475], [-0.3, -0.5, 0.6]]))
    np.testing.assert_array_equal(np.asarray(idx), [[57, 49, 87], [0, 0, 0]])


def test_point_to_voxel_clips_both_sides() -> None:
    # Below the bounds: the original gave negative indices; the fix clips to 0.
    below = tx.point_to_voxel(np.array([-0.35, -0.9, 0.0]))
    np.testing.assert_array_equal(np.asarray(below), [0, 0, 0])
    above = tx.point_to_voxel(np.array([0.7, 0.5, 1.6]))  # the max edge itself
    np.testing.assert_array_equal(np.asarray(above), [99, 99, 99])
    far = tx.point_to_voxel(np.array([5.0, 5.0, 5.0]))
    np.testing.assert_array_equal(np.asarray(far), [99, 99, 99])


def test_point_to_voxel_accepts_jax_and_float32_batches() -> None:
    pts = jax.numpy.zeros((2, 4, 3), dtype=jax.numpy.float32)
    out = tx.point_to_voxel(pts)
    assert isinstance(out, np.ndarray) and out.shape == (2, 4, 3) and out.dtype == np.int32
    # x = 0 and y = 0 sit exactly on edges: the original's epsilons put them below.
    np.testing.assert_array_equal(out[0, 0], [29, 49, 0])


def test_voxel_to_point_centre() -> None:
    np.testing.assert_allclose(np.asarray(tx.voxel_to_point([0, 0, 0])), [-0.295, -0.495, 0.605],
                               atol=1e-6)
    np.testing.assert_allclose(np.asarray(tx.voxel_to_point([99, 99, 99])), [0.695, 0.495, 1.595],
                               atol=1e-6)


# ---------------------------------------------------------------- rotations


def test_euler_matches_scipy_on_random_quaternions() -> None:
    q = _random_quats_xyzw(2000, seed=1)
    ref = Rotation.from_quat(q).as_euler("xyz", degrees=True)
    ours = np.asarray(tx.quat_to_euler_xyz(_wxyz(q)))
    diff = np.abs((ours - ref + 180) % 360 - 180)  # angles are defined modulo 360
    away_from_lock = np.abs(ref[:, 1]) < 89.0
    assert np.all(diff[away_from_lock] < 1e-2)
    assert np.all(np.abs(ours[:, 1]) <= 90.0 + 1e-4)


def test_euler_to_quat_matches_scipy() -> None:
    rng = np.random.default_rng(2)
    angles = rng.uniform([-180, -90, -180], [180, 90, 180], size=(500, 3))
    ref = Rotation.from_euler("xyz", angles, degrees=True).as_quat()
    ours = np.asarray(tx.euler_xyz_to_quat(angles))
    np.testing.assert_allclose(ours, _wxyz(ref), atol=1e-5)  # same sign as scipy too


def test_bins_against_scipy_random() -> None:
    q = _random_quats_xyzw(2000, seed=3)
    bins = np.asarray(tx.quat_to_euler_bins(_wxyz(q)))
    assert bins.dtype == np.int32 and bins.shape == (2000, 3)
    assert bins.min() >= 0 and bins[:, [0, 2]].max() <= 71
    assert bins[:, 1].min() >= 18 and bins[:, 1].max() <= 54
    np.testing.assert_array_equal(bins, _reference_bins(q))
    # Decoded rotations: within the 2.5 deg per-axis quantisation (3 axes -> <= 7.5 deg).
    decoded = np.asarray(tx.euler_bins_to_quat(bins))
    assert np.all(_angle_deg(decoded, _wxyz(q)) <= 7.5 + 1e-3)
    # Our decode equals scipy's decode of the same bins.
    ref_dec = Rotation.from_euler("xyz", bins * 5 - 180, degrees=True).as_quat()
    np.testing.assert_allclose(decoded, _wxyz(ref_dec), atol=1e-5)


def test_bins_sign_invariance() -> None:
    q = _wxyz(_random_quats_xyzw(500, seed=4))
    np.testing.assert_array_equal(np.asarray(tx.quat_to_euler_bins(q)),
                                  np.asarray(tx.quat_to_euler_bins(-q)))


def test_bins_unnormalised_input() -> None:
    q = _wxyz(_random_quats_xyzw(100, seed=5))
    np.testing.assert_array_equal(np.asarray(tx.quat_to_euler_bins(q)),
                                  np.asarray(tx.quat_to_euler_bins(3.7 * q)))


@pytest.mark.parametrize(
    ("x_deg", "x_bin"),
    [(180.0, 0), (179.0, 0), (-179.0, 0), (177.0, 71), (-177.0, 1), (173.0, 71), (-173.0, 1),
     (172.0, 70), (-172.0, 2)],
)
def test_top_down_gripper_near_180(x_deg: float, x_bin: int) -> None:
    # A top-down gripper: x angle near +-180; bin 72 wraps to 0.
    q = _wxyz(Rotation.from_euler("xyz", [x_deg, 10.0, 30.0], degrees=True).as_quat())
    bins = np.asarray(tx.quat_to_euler_bins(q))
    assert bins[0] == x_bin
    np.testing.assert_array_equal(bins[1:], [38, 42])
    np.testing.assert_array_equal(bins, _reference_bins(_xyzw(q)))
    decoded = np.asarray(tx.euler_bins_to_quat(bins))
    assert _angle_deg(decoded, q) <= 3.0


def test_near_180_bins_are_neighbours_in_rotation() -> None:
    # 0/1 and 70/71 look far apart as numbers but are neighbouring rotations.
    q_a = np.asarray(tx.euler_bins_to_quat(np.array([71, 36, 36])))
    q_b = np.asarray(tx.euler_bins_to_quat(np.array([1, 36, 36])))
    q_0 = np.asarray(tx.euler_bins_to_quat(np.array([0, 36, 36])))
    assert _angle_deg(q_a, q_0) == pytest.approx(5.0, abs=1e-3)
    assert _angle_deg(q_b, q_0) == pytest.approx(5.0, abs=1e-3)


def test_gimbal_lock_decodes_to_same_rotation() -> None:
    for y in (90.0, -90.0):
        q = _wxyz(Rotation.from_euler("xyz", [30.0, y, 40.0], degrees=True).as_quat())
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = Rotation.from_quat(_xyzw(q)).as_euler("xyz", degrees=True)
        ours = np.asarray(tx.quat_to_euler_xyz(q))
        np.testing.assert_allclose(ours, ref, atol=1e-2)
        assert ours[2] == 0.0  # scipy's rule: third angle set to 0
        decoded = np.asarray(tx.euler_bins_to_quat(tx.quat_to_euler_bins(q)))
        assert _angle_deg(decoded, q) <= 7.5


# ---------------------------------------------------------------- golden: the original's integers


def _reference_voxels(points: np.ndarray) -> np.ndarray:
    """RoboPrompt / X-ICM ``point_to_voxel_index`` verbatim in float64, plus our lower clip."""
    bb_mins = np.array(tx.SCENE_BOUNDS[0:3])[None]
    bb_maxs = np.array(tx.SCENE_BOUNDS[3:])[None]
    dims_m_one = np.array([tx.VOXEL_SIZE] * 3)[None] - 1
    bb_ranges = bb_maxs - bb_mins
    res = bb_ranges / (np.array([tx.VOXEL_SIZE] * 3) + 1e-12)
    idx = np.minimum(np.floor((points - bb_mins) / (res + 1e-12)).astype(np.int64), dims_m_one)
    return np.maximum(idx, 0)  # the documented fix: no negative indices


def _reference_actions(pos: np.ndarray, q_xyzw: np.ndarray, grip: np.ndarray) -> np.ndarray:
    return np.concatenate([_reference_voxels(pos), _reference_bins(q_xyzw),
                           grip.astype(int)[:, None]], axis=-1)


def test_voxel_edges_exactly_as_the_original() -> None:
    # The original divides by range / (100 + 1e-12) + 1e-12 (about 0.010000000001), so a point
    # exactly on an edge lands in the lower voxel; the simplified floor((p - min) / 0.01)
    # would give 40 and 1 here.
    np.testing.assert_array_equal(tx.point_to_voxel(np.array([0.0, -0.49, 1.0])), [29, 0, 39])
    np.testing.assert_array_equal(tx.point_to_voxel(np.array([0.0, -0.49, 1.0]) + 1e-9),
                                  [30, 1, 40])
    np.testing.assert_array_equal(tx.point_to_voxel(np.array([0.0, -0.49, 1.0]) - 1e-9),
                                  [29, 0, 39])


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_both_sides_of_every_voxel_edge(axis: int) -> None:
    k = np.arange(1, tx.VOXEL_SIZE)
    edge = tx.SCENE_BOUNDS[axis] + 0.01 * k
    for offset, expected in [(-1e-9, k - 1), (1e-9, k), (0.0, None)]:
        pts = np.full((len(k), 3), 0.1)
        pts[:, axis] = edge + offset
        ours = tx.point_to_voxel(pts)
        np.testing.assert_array_equal(ours, _reference_voxels(pts))
        if expected is not None:
            np.testing.assert_array_equal(ours[:, axis], expected)


@pytest.mark.parametrize("pitch", [90.0, -90.0])
def test_gimbal_lock_threshold_as_scipy(pitch: float) -> None:
    # scipy's threshold is 1e-7 rad (5.7e-6 deg) on the second angle: inside it the third angle
    # is 0 (bin 36); 1e-8 deg or rad away from +-90 is still locked, 1e-5 deg is not.
    sign = np.sign(pitch)
    for away, locked in [(0.0, True), (1e-8, True), (np.rad2deg(1e-8), True),
                         (np.rad2deg(0.9e-7), True), (np.rad2deg(1.1e-7), False), (1e-5, False)]:
        q = _wxyz(Rotation.from_euler("xyz", [30.0, pitch - sign * away, 40.0],
                                      degrees=True).as_quat())
        bins = tx.quat_to_euler_bins(q)
        np.testing.assert_array_equal(bins, _reference_bins(_xyzw(q)))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = Rotation.from_quat(_xyzw(q)).as_euler("xyz", degrees=True)
        np.testing.assert_array_equal(tx.quat_to_euler_xyz(q), ref)
        assert (bins[2] == 36) == locked, (away, bins)


def _golden_poses(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n poses: a third random, the rest on or within 1e-9 m / 1e-9 deg of voxel edges, Euler
    bin boundaries (x.5 bins), +-180 degrees and gimbal lock, unnormalised, w < 0."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array(tx.SCENE_BOUNDS[:3]), np.array(tx.SCENE_BOUNDS[3:])
    third = n // 3
    pos_random = rng.uniform(lo - 0.05, hi + 0.05, size=(third, 3))
    k = rng.integers(0, tx.VOXEL_SIZE + 1, size=(n - third, 3))
    jitter = rng.choice([0.0, 1e-9, -1e-9, 1e-12, -1e-12, 4e-11, 1e-7], size=(n - third, 3))
    pos_edges = lo + 0.01 * k + jitter
    pos = np.concatenate([pos_random, pos_edges])

    q_random = Rotation.random(third, random_state=seed).as_quat()
    angles = rng.integers(-72, 73, size=(n - third, 3)) * 2.5  # rounding boundaries (x.5 bins)
    angles += rng.choice([0.0, 1e-9, -1e-9, 1e-6, -1e-6], size=angles.shape)
    angles[:, 1] = np.clip(angles[:, 1], -90, 90)
    lock = rng.random(n - third) < 0.2
    angles[lock, 1] = rng.choice([90.0, -90.0], lock.sum()) * (
        1 - rng.choice([0.0, 1e-8, 1e-10, 1e-7], lock.sum()))
    q_edges = Rotation.from_euler("xyz", angles, degrees=True).as_quat()
    quat = np.concatenate([q_random, q_edges])
    quat *= rng.choice([1.0, -1.0, 0.5, 3.0], size=(n, 1))  # sign flips, unnormalised
    grip = rng.integers(0, 2, n).astype(float)
    return pos, quat, grip


def test_golden_100k_poses_match_the_original_integers() -> None:
    pos, q_xyzw, grip = _golden_poses(100_000, seed=14)
    ours = tx.encode_action(pos, _wxyz(q_xyzw), grip)
    ref = _reference_actions(pos, q_xyzw, grip)
    mismatch = np.flatnonzero(np.any(ours != ref, axis=-1))
    assert mismatch.size == 0, (mismatch[:5], ours[mismatch[:5]], ref[mismatch[:5]])


def test_golden_per_pose_calls_match_batched() -> None:
    # The original encodes one pose at a time; batching must not change a single bit.
    pos, q_xyzw, grip = _golden_poses(300, seed=15)
    batched = tx.encode_action(pos, _wxyz(q_xyzw), grip)
    for i in range(len(pos)):
        single = tx.encode_action(pos[i], _wxyz(q_xyzw[i]), grip[i])
        np.testing.assert_array_equal(single, batched[i])
        np.testing.assert_array_equal(single, _reference_actions(pos[i:i + 1], q_xyzw[i:i + 1],
                                                                 grip[i:i + 1])[0])


def test_zero_quaternion_raises_like_scipy() -> None:
    with pytest.raises(ValueError):
        tx.quat_to_euler_bins(np.zeros(4))


# ---------------------------------------------------------------- actions


def test_home_action_decodes_to_home_pose() -> None:
    pos, quat, grip = tx.decode_action(np.array(HOME_ACTION))
    np.testing.assert_allclose(np.asarray(pos), [0.275, -0.005, 1.475], atol=1e-6)
    quat = np.asarray(quat)
    quat = quat if quat[0] >= 0 else -quat
    np.testing.assert_allclose(quat, [0.131, 0.0, 0.991, 0.0], atol=1e-3)
    assert float(grip) == 1.0


def test_encode_decode_round_trip() -> None:
    rng = np.random.default_rng(6)
    n = 300
    ints = np.stack(
        [rng.integers(0, 100, n), rng.integers(0, 100, n), rng.integers(0, 100, n),
         rng.integers(0, 72, n), rng.integers(19, 54, n), rng.integers(0, 72, n),
         rng.integers(0, 2, n)],
        axis=-1,
    ).astype(np.int32)
    pos, quat, grip = tx.decode_action(ints)
    again = tx.encode_action(pos, quat, grip)
    assert again.dtype == np.int32 and again.shape == (n, 7)
    np.testing.assert_array_equal(again, ints)


def test_encode_action_home_pose_and_gripper_rule() -> None:
    q = _wxyz(Rotation.from_euler("xyz", [-180.0, 15.0, -180.0], degrees=True).as_quat())
    a = tx.encode_action(np.array([0.275, -0.005, 1.475]), q, 1.0)
    np.testing.assert_array_equal(np.asarray(a), HOME_ACTION)
    for flag, bit in [(0.0, 0), (1.0, 1), (True, 1), (False, 0), (0, 0), (1, 1)]:
        assert int(tx.encode_action(np.zeros(3), q, flag)[6]) == bit
    batch = tx.encode_action(np.zeros((2, 3)), np.stack([q, q]), np.array([1.0, 0.0]))
    np.testing.assert_array_equal(np.asarray(batch[:, 6]), [1, 0])


def test_validate_action_ints() -> None:
    good = np.array(HOME_ACTION)
    bad = [
        [100, 49, 87, 0, 39, 0, 1],
        [57, -1, 87, 0, 39, 0, 1],
        [57, 49, 87, 72, 39, 0, 1],
        [57, 49, 87, 0, -3, 0, 1],
        [57, 49, 87, 0, 39, 0, 2],
        [57, 49, 87, 0, 39, 0, -1],
    ]
    assert bool(tx.validate_action_ints(good))
    assert bool(tx.validate_action_ints([99, 99, 99, 71, 71, 71, 0]))
    assert bool(tx.validate_action_ints([0, 0, 0, 0, 0, 0, 0]))
    mask = np.asarray(tx.validate_action_ints(np.array([HOME_ACTION, *bad])))
    np.testing.assert_array_equal(mask, [True] + [False] * len(bad))
    with pytest.raises(ValueError):
        tx.validate_action_ints([1, 2, 3, 4, 5, 6])


# ---------------------------------------------------------------- strings


OBJECTS = {"lid": [52, 38, 17], "jar": [47, 61, 16]}
ACTIONS = [[52, 38, 24, 0, 39, 0, 1], [52, 38, 18, 0, 39, 0, 0]]


def test_format_objects_golden() -> None:
    s = tx.format_objects("close the red jar", OBJECTS)
    assert s == "['instruction': close the red jar, {'lid': [52, 38, 17], 'jar': [47, 61, 16]}]"


def test_format_objects_numpy_ints_print_plain() -> None:
    objs = {"lid": np.array([52, 38, 17], dtype=np.int32),
            "jar": jax.numpy.array([47, 61, 16], dtype=jax.numpy.int32)}
    s = tx.format_objects("close the red jar", objs)
    assert s == "['instruction': close the red jar, {'lid': [52, 38, 17], 'jar': [47, 61, 16]}]"
    assert "np.int" not in s


def test_format_objects_keeps_insertion_order_and_empty() -> None:
    s = tx.format_objects("turn on the light", {"button": (1, 2, 3), "button wrap": (4, 5, 6)})
    assert s == (
        "['instruction': turn on the light, {'button': [1, 2, 3], 'button wrap': [4, 5, 6]}]"
    )
    assert tx.format_objects("x", {}) == "['instruction': x, {}]"
    with pytest.raises(ValueError):
        tx.format_objects("x", {"a": [1, 2]})


def test_format_actions_golden() -> None:
    assert tx.format_actions(ACTIONS) == "[[52, 38, 24, 0, 39, 0, 1], [52, 38, 18, 0, 39, 0, 0]]"
    assert (tx.format_actions(np.array(ACTIONS, dtype=np.int32))
            == "[[52, 38, 24, 0, 39, 0, 1], [52, 38, 18, 0, 39, 0, 0]]")
    assert tx.format_actions([]) == "[]"


def test_format_demo_golden() -> None:
    s = tx.format_demo("close the red jar", OBJECTS, ACTIONS)
    assert s == (
        "['instruction': close the red jar, {'lid': [52, 38, 17], 'jar': [47, 61, 16]}]"
        ">[[52, 38, 24, 0, 39, 0, 1], [52, 38, 18, 0, 39, 0, 0]], "
    )


def test_format_query_golden() -> None:
    s = tx.format_query("put the ball in the hoop", {"hoop": [40, 50, 30], "ball": [45, 52, 21]})
    assert s == (
        "['instruction': put the ball in the hoop, {'hoop': [40, 50, 30], 'ball': [45, 52, 21]}]>"
    )


def test_spec_example_segment() -> None:
    actions = [[52, 38, 24, 0, 39, 0, 1], [52, 38, 18, 0, 39, 0, 0], [52, 38, 28, 0, 39, 0, 0],
               [47, 61, 26, 0, 39, 2, 0], [47, 61, 21, 0, 39, 2, 1]]
    expected = (
        "['instruction': close the red jar, {'lid': [52, 38, 17], 'jar': [47, 61, 16]}]>"
        "[[52, 38, 24, 0, 39, 0, 1], [52, 38, 18, 0, 39, 0, 0], [52, 38, 28, 0, 39, 0, 0], "
        "[47, 61, 26, 0, 39, 2, 0], [47, 61, 21, 0, 39, 2, 1]], "
    )
    assert tx.format_demo("close the red jar", OBJECTS, actions) == expected
