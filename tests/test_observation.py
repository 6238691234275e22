"""RLBench-style observations on the CPU renderer: geometry, labels, the policy hook.

Tiny batches at 48 px keep this fast; one task scene (close_jar) is reset once per module.
"""

from __future__ import annotations

import copy

import jax
import mujoco
import numpy as np
import pytest

from agnostos_mjx.policies.base import Policy
from agnostos_mjx.runtime import observation as ob
from agnostos_mjx.sim.world import build_scene
from agnostos_mjx.tasks import get_task

SIZE = 48
ALL = ob.ObservationSpec(cameras=ob.CAMERAS, height=SIZE, width=SIZE, modalities=ob.MODALITIES,
                         renderer="cpu")


@pytest.fixture(scope="module")
def scene():
    from agnostos_mjx.runtime.env import Episodes

    runner = Episodes(get_task("close_jar"), "native")
    env = runner.reset(jax.random.split(jax.random.PRNGKey(7), 2), np.array([0, 1]))
    try:
        obs = runner.observe(env, ALL)
    except RuntimeError as err:  # no headless GL
        pytest.skip(str(err))
    return runner, env, obs


def _posed(runner, env, world: int) -> mujoco.MjData:
    from agnostos_mjx.sim.world import posed_data

    return posed_data(runner.scene.model, env.physics, world)


def _surface_distance(points: np.ndarray, geom_type: int, size: np.ndarray) -> np.ndarray:
    """Unsigned distance of geom-frame points (N, 3) to a primitive's surface."""
    G = mujoco.mjtGeom  # noqa: N806
    radial = np.linalg.norm(points[:, :2], axis=1)
    if geom_type == G.mjGEOM_PLANE:
        return np.abs(points[:, 2])
    if geom_type == G.mjGEOM_SPHERE:
        return np.abs(np.linalg.norm(points, axis=1) - size[0])
    if geom_type == G.mjGEOM_CAPSULE:
        axis = np.clip(points[:, 2], -size[1], size[1])
        return np.abs(np.hypot(radial, points[:, 2] - axis) - size[0])
    if geom_type == G.mjGEOM_ELLIPSOID:  # first-order distance, exact on the surface
        scaled = np.linalg.norm(points / size, axis=1)
        grad = np.linalg.norm(points / size**2, axis=1)
        return np.abs(scaled - 1) * scaled / np.maximum(grad, 1e-9)
    half = (np.array([size[0], size[1]]) if geom_type == G.mjGEOM_CYLINDER
            else np.asarray(size[:3], float))
    q = (np.stack([radial, np.abs(points[:, 2])], 1) if geom_type == G.mjGEOM_CYLINDER
         else np.abs(points)) - half
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    return np.abs(outside + np.minimum(q.max(axis=1), 0))


def test_back_projected_points_lie_on_their_geoms(scene) -> None:
    """Every labelled pixel's world point is within 1 cm of the geom it is labelled with
    (so also of its named object), for every camera."""
    runner, env, obs = scene
    m = runner.scene.model
    for w in range(obs.batch):
        d = _posed(runner, env, w)
        for name, cam in obs.cameras.items():
            seg, pts, depth = cam.segmentation[w], cam.point_cloud[w], cam.depth[w]
            hit = (seg >= 0) & (depth < cam.far - 1e-3)  # RLBench's far plane clips
            assert hit.mean() > 0.5, name
            for g in np.unique(seg[hit]):
                p = pts[hit & (seg == g)].astype(np.float64)
                local = (p - d.geom_xpos[g]) @ d.geom_xmat[g].reshape(3, 3)
                err = _surface_distance(local, int(m.geom_type[g]), m.geom_size[g])
                assert err.max() < 0.01, (name, w, m.geom(int(g)).name, err.max())


def test_segmentation_names_and_objects(scene) -> None:
    runner, env, obs = scene
    m = runner.scene.model
    labels = obs.labels
    assert len(labels.geom_names) == m.ngeom
    assert labels.geom_names[m.geom("table").id] == "table"
    assert set(labels.objects) == {"lid", "jar"}
    for name, frame in runner.task.objects.items():
        ids = labels.objects[name]
        assert ids and all(m.body(int(m.geom_bodyid[g])).name == frame for g in ids)
        seen = sum(int(labels.mask(c.segmentation, name).sum()) for c in obs.cameras.values())
        assert seen > 0, name
    # The lid's pixels (front camera) back-project onto the lid: their mean is near its frame.
    lid = np.asarray(env.obs.pos("jar_lid0"))
    for w in range(obs.batch):
        centre = ob.segmented_object_positions(obs, w)["lid"]
        assert np.linalg.norm(centre - lid[w]) < 0.03
    objs = labels.object_segmentation(obs.cameras["front"].segmentation)
    assert set(np.unique(objs)) <= {-1, 0, 1} and (objs >= 0).any()


def test_shared_body_objects_are_disjoint() -> None:
    """place_cups' three holder spokes are sites on one body: each gets its nearest geoms."""
    labels = ob.scene_labels(build_scene(get_task("place_cups")))
    holders = [set(labels.objects[f"{k} holder"]) for k in ("first", "second", "third")]
    assert all(holders) and not (holders[0] & holders[1] or holders[1] & holders[2])


def test_camera_parameters_match_rlbench(scene) -> None:
    """Focal lengths and viewing directions of the spec's camera table (section 2)."""
    _, _, obs = scene
    k = ob.intrinsics(40.0, 128, 128)
    assert k[0, 0] == pytest.approx(-175.8, abs=0.1) and k[0, 2] == pytest.approx(63.5)
    assert ob.intrinsics(60.0, 128, 128)[1, 1] == pytest.approx(-110.9, abs=0.1)
    directions = {"front": (-0.906, 0.0, -0.423), "left_shoulder": (0.416, -0.073, -0.906),
                  "right_shoulder": (0.416, 0.073, -0.906), "overhead": (0.423, 0.0, -0.906)}
    for name, z in directions.items():
        ext = obs.cameras[name].extrinsics[0]
        np.testing.assert_allclose(ext[:3, 2], z, atol=2e-3)
        np.testing.assert_allclose(ext[:3, :3] @ ext[:3, :3].T, np.eye(3), atol=1e-5)
        assert np.linalg.det(ext[:3, :3]) == pytest.approx(1.0, abs=1e-5)
    assert obs.cameras["front"].extrinsics[0, 2, 1] > 0.8  # +y is image-up (world-up here)


def _rlbench_point_cloud(depth, extrinsics, intrinsics):
    """RLBench's pointcloud_from_depth_and_camera_params (rlbench/backend/utils.py)."""
    h, w = depth.shape
    upc = np.stack([*np.meshgrid(np.arange(w), np.arange(h)), np.ones((h, w))], -1)
    pc = upc * depth[..., None]
    c = extrinsics[:3, 3][:, None]
    r_inv = extrinsics[:3, :3].T
    ext = np.concatenate((r_inv, -r_inv @ c), -1)
    proj = np.concatenate([intrinsics @ ext, [[0, 0, 0, 1]]])
    inv = np.linalg.inv(proj)[:3]
    homo = np.concatenate([pc, np.ones((h, w, 1))], -1)
    return np.einsum("ij,hwj->hwi", inv, homo)


def test_rlbench_reader_rebuilds_our_point_cloud(scene) -> None:
    _, _, obs = scene
    for cam in obs.cameras.values():
        theirs = _rlbench_point_cloud(cam.depth[1].astype(np.float64),
                                      cam.extrinsics[1].astype(np.float64), cam.intrinsics)
        np.testing.assert_allclose(theirs, cam.point_cloud[1], atol=1e-4)


def test_proprioception(scene) -> None:
    runner, env, obs = scene
    assert obs.gripper_pose.shape == (2, 7) and obs.gripper_pose.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(obs.gripper_pose[:, 3:], axis=1), 1, atol=1e-5)
    # Start pose: tip pointing down; RLBench's quaternion (x, y, z, w) ~ (0, 0.99, 0, 0.12).
    assert abs(obs.gripper_pose[0, 4]) > 0.95
    np.testing.assert_array_equal(obs.gripper_open, [1.0, 1.0])
    np.testing.assert_allclose(obs.gripper_joint_positions, 0.04, atol=2e-3)
    assert obs.joint_positions.shape == obs.joint_velocities.shape == (2, 7)
    assert obs.instructions == tuple(runner.task.descriptions(v)[0] for v in (0, 1))
    world = obs.world(0)
    assert world["front_rgb"].shape == (SIZE, SIZE, 3) and "wrist_mask" in world
    assert world["misc"]["front_camera_far"] == 4.5


class TwoCameraPolicy(Policy):
    """A VLA-style plug-in: front and wrist RGB + point clouds at 128 x 128."""

    name = "two-camera"
    observation_spec = ob.ObservationSpec(cameras=("front", "wrist"), height=128, width=128,
                                          modalities=("rgb", "point_cloud"), renderer="cpu")

    def __init__(self) -> None:
        self.seen: list[ob.RLBenchObservation] = []

    def reset(self, view) -> None:
        self.seen.clear()

    def act(self, view):
        from agnostos_mjx.policies.base import no_actions

        self.seen.append(view.observation)
        return no_actions(view.batch)


def test_policy_gets_exactly_what_it_asks_for() -> None:
    from agnostos_mjx.evaluation.config import EvalConfig
    from agnostos_mjx.evaluation.rollout import run_task
    policy = TwoCameraPolicy()
    cfg = EvalConfig.of(batch=2, episodes=2, seeds=[0], backend="native")
    records = run_task(get_task("close_jar"), policy, [(0, 0), (0, 1)], cfg,
                       lambda r: None)
    assert [r["outcome"] for r in records] == ["no_action", "no_action"]
    (obs,) = policy.seen
    assert tuple(obs.cameras) == ("front", "wrist")
    for cam in obs.cameras.values():
        assert cam.rgb.shape == (2, 128, 128, 3) and cam.rgb.dtype == np.uint8
        assert cam.point_cloud.shape == (2, 128, 128, 3) and cam.point_cloud.dtype == np.float32
        assert cam.depth is None and cam.segmentation is None
        assert cam.intrinsics.shape == (3, 3) and cam.extrinsics.shape == (2, 4, 4)
    assert obs.gripper_pose.shape == (2, 7) and len(obs.instructions) == 2


def test_spec_validation() -> None:
    with pytest.raises(ValueError, match="modalities"):
        ob.ObservationSpec(modalities=("rgb", "normals"))
    with pytest.raises(ValueError, match="distinct"):
        ob.ObservationSpec(cameras=("front", "front"))
    # a name the scene has no camera for is refused at load, with the valid names
    with pytest.raises(ValueError, match="unknown cameras 'top'; the scene's cameras are "
                                         "front, left_shoulder, right_shoulder, overhead, wrist"):
        ob.ObservationSpec(cameras=("front", "top"))
    assert ob.ObservationSpec(modalities=("point_cloud",)).needs_depth


def test_fixed_camlight_equals_mujoco_camlight() -> None:
    """The closed-form camera and light poses the warp observation uses (instead of a full
    forward) equal mj_forward's, for a moved arm and a batch of worlds in JAX."""
    import jax.numpy as jnp

    from agnostos_mjx.render import FixedCamLight

    model = build_scene(get_task("close_jar")).model
    rng = np.random.default_rng(0)
    datas = []
    for _ in range(3):
        d = mujoco.MjData(model)
        d.qpos[:] = model.qpos0 + 0.3 * rng.standard_normal(model.nq)
        mujoco.mj_forward(model, d)
        datas.append(d)
    camlight = FixedCamLight(model)
    xpos = jnp.asarray(np.stack([d.xpos for d in datas]))
    xmat = jnp.asarray(np.stack([d.xmat.reshape(-1, 3, 3) for d in datas]))
    got = camlight(xpos, xmat, jnp)
    want = [np.stack([getattr(d, f) for d in datas]) for f in
            ("cam_xpos", "cam_xmat", "light_xpos", "light_xdir")]
    want[1] = want[1].reshape(3, -1, 3, 3)
    assert want[0].std(axis=0).max() > 0.01  # the wrist camera moved between worlds
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(np.asarray(g), w, atol=1e-5)
    tracking = copy.copy(model)  # scenes are cached: never edit a shared model
    tracking.cam_mode[0] = mujoco.mjtCamLight.mjCAMLIGHT_TRACK
    assert not FixedCamLight.supports(tracking) and FixedCamLight.supports(model)
    with pytest.raises(ValueError, match="not fixed"):
        FixedCamLight(tracking)


@pytest.mark.slow
def test_warp_matches_cpu(scene) -> None:
    """MJX-Warp's observation agrees with the CPU renderer's on the same state (GPU: seconds;
    Warp's CPU backend: minutes of kernel builds).  Prints the pixel-difference figures."""
    from agnostos_mjx.physics import warp_available

    if not warp_available():
        pytest.skip("needs warp-lang and a CUDA GPU")
    runner, env, cpu = scene
    spec = ob.ObservationSpec(cameras=ob.CAMERAS, height=SIZE, width=SIZE,
                              modalities=ob.MODALITIES, renderer="warp")
    gpu = runner.observe(env, spec)
    for name in ob.CAMERAS:
        a, b = cpu.cameras[name], gpu.cameras[name]
        np.testing.assert_allclose(a.extrinsics, b.extrinsics, atol=1e-4)
        same_geom = np.mean(a.segmentation == b.segmentation)
        rgb_diff = np.abs(a.rgb.astype(int) - b.rgb.astype(int)).mean()
        both = (a.segmentation >= 0) & (a.segmentation == b.segmentation)
        depth_diff = np.median(np.abs(a.depth - b.depth)[both])
        print(f"{name}: same segment {same_geom:.3f}, mean |RGB diff| {rgb_diff:.1f}/255, "
              f"median |depth diff| {1000 * depth_diff:.2f} mm")
        assert same_geom > 0.95 and depth_diff < 2e-3 and rgb_diff < 40


def test_segmented_object_text_close_to_ground_truth(scene) -> None:
    """X-ICM's object voxels from segmented point clouds (the original's way) differ from
    the ground-truth frame voxels by a few 1 cm voxels at most (visible surface vs centre)."""
    from agnostos_mjx.xicm.scene_text import object_voxels, segmented_object_voxels

    runner, env, obs = scene
    truth = object_voxels(runner.task, env.obs)
    seg = segmented_object_voxels(obs)
    for t, s in zip(truth, seg):
        assert list(s) == list(t)  # every object is seen, in the declared order
        diff = np.abs(np.subtract([s[n] for n in s], [t[n] for n in s]))
        assert diff.max() <= 4, (t, s)


def test_readme_plugin_runs(tmp_path) -> None:
    """examples/vla_policy.py (the README's plug-in) runs through the evaluator."""
    from pathlib import Path

    from agnostos_mjx.evaluation.config import EvalConfig
    from agnostos_mjx.evaluation.run import evaluate

    plugin = Path(__file__).resolve().parents[1] / "examples" / "vla_policy.py"
    cfg = EvalConfig.of(policy=f"{plugin}:GreenSeeker", tasks="lamp_on", seeds=[0], episodes=2,
                        batch=2, backend="native", out=str(tmp_path), quiet=True)
    results = evaluate(cfg)
    assert len(results["episodes"]) == 2
    assert all(r["outcome"] != "policy_error" for r in results["episodes"])


def test_object_text_report_counts(tmp_path) -> None:
    """The segmented-vs-ground-truth text report counts differing indices, omitted objects
    and differing query lines; it runs end to end on a task and rejects unknown tasks."""
    import json

    from agnostos_mjx.bench import object_text as rep

    truth = [{"a": [1, 2, 3], "b": [4, 5, 6]}, {"a": [1, 1, 1], "b": [2, 2, 2]}]
    seg = [{"a": [1, 2, 3], "b": [4, 7, 6]}, {"a": [1, 1, 1]}]
    got = rep.compare_texts(truth, seg)
    assert got == {"worlds": 2, "objects": 4, "omitted_objects": 1, "indices": 9,
                   "indices_differing": 1, "max_index_difference": 2,
                   "mean_abs_difference_where_differing": 2.0, "queries_differing": 2}
    assert rep.main(["--tasks", "lamp_on", "--seeds", "0", "--episodes", "2",
                     "--out", str(tmp_path)]) == 0
    row = json.loads((tmp_path / "object_text.json").read_text())["rows"][0]
    assert row["task"] == "lamp_on" and row["worlds"] == 2
    assert row["indices"] == 3 * (row["objects"] - row["omitted_objects"]) > 0
    assert "| **all** |" in (tmp_path / "object_text.md").read_text()
    assert rep.main(["--tasks", "no_such_task"]) == 2


def test_frames_of_a_subset_of_worlds_equal_those_of_the_whole_batch(scene) -> None:
    """Planning policies render only the worlds they replan: the same pixels."""
    runner, env, _ = scene
    whole = runner.render(env, "front", SIZE, SIZE)
    assert whole.shape == (2, SIZE, SIZE, 3)
    for worlds in ([1], [0, 1], [1, 0]):
        part = runner.render(env, "front", SIZE, SIZE, worlds=np.array(worlds))
        assert np.array_equal(part, whole[worlds])
