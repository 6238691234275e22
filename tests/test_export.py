"""Training-data export: 2 seen tasks x 2 demos in RLBench's episode folders, read back."""

from __future__ import annotations

import json
import pickle
import pickletools

import numpy as np
import pytest

from agnostos_mjx.data import export as ex
from agnostos_mjx.data import rlbench_demo
from agnostos_mjx.data import rlbench_format as fmt
from agnostos_mjx.data.expert_frames import frame_every
from agnostos_mjx.data.look import look_record
from agnostos_mjx.infra.settings import usable_cores


def test_encodings_round_trip() -> None:
    depth = np.linspace(0.01, 4.5, 100).reshape(10, 10)
    rgb = fmt.encode_depth(depth, 0.01, 4.5)
    np.testing.assert_allclose(fmt.decode_depth(rgb, 0.01, 4.5), depth, atol=1e-6)
    # RLBench's image_to_float_array(img, DEPTH_SCALE): R is the high byte for depth ...
    unit = np.sum(rgb.astype(np.int64) * [65536, 256, 1], axis=2) / fmt.DEPTH_SCALE
    np.testing.assert_allclose(0.01 + unit * (4.5 - 0.01), depth, atol=1e-6)
    ids = np.arange(-1, 99).reshape(10, 10)
    assert np.array_equal(fmt.rgb_to_int(fmt.int_to_rgb(ids + 1)) - 1, ids)
    # ... and the low byte for masks (rgb_handles_to_mask: R + 256 G + 65536 B).
    mask = fmt.int_to_rgb(np.array([[70000]])).astype(np.int64)
    assert mask[0, 0, 0] + 256 * mask[0, 0, 1] + 65536 * mask[0, 0, 2] == 70000


def _frame(cameras=("front", "wrist")) -> dict:
    misc = {}
    for cam in cameras:
        misc.update({f"{cam}_camera_extrinsics": np.eye(4, dtype=np.float32),
                     f"{cam}_camera_intrinsics": np.eye(3, dtype=np.float32),
                     f"{cam}_camera_near": 0.01, f"{cam}_camera_far": 3.5})
    return {"gripper_pose": np.array([0.3, 0.0, 1.2, 0.0, 1.0, 0.0, 0.0], np.float32),
            "gripper_open": 1.0, "joint_positions": np.zeros(7, np.float32),
            "joint_velocities": np.zeros(7, np.float32),
            "gripper_joint_positions": np.full(2, 0.04, np.float32),
            "task_low_dim_state": np.arange(8, dtype=np.float32), "misc": misc}


def check_rlbench_fields(obs, cameras=("front", "wrist")) -> None:
    """The types RLBench's own pickles hold (peract_colab's sample data)."""
    assert set(vars(obs)) == set(rlbench_demo.OBSERVATION_FIELDS)
    for name in rlbench_demo.OBSERVATION_FIELDS:
        if name.endswith(("_rgb", "_depth", "_mask", "_point_cloud")):
            assert getattr(obs, name) is None, name
    shapes = {"joint_velocities": (7,), "joint_positions": (7,), "joint_forces": (7,),
              "gripper_pose": (7,), "gripper_matrix": (4, 4), "gripper_joint_positions": (2,),
              "gripper_touch_forces": (6,), "ignore_collisions": ()}
    for name, shape in shapes.items():
        value = getattr(obs, name)
        assert isinstance(value, np.ndarray) and value.dtype == np.float64, name
        assert value.shape == shape, name
    assert obs.task_low_dim_state.dtype == np.float64 and obs.task_low_dim_state.ndim == 1
    assert type(obs.gripper_open) is float and obs.gripper_open in (0.0, 1.0)
    np.testing.assert_allclose(obs.gripper_matrix[:3, 3], obs.gripper_pose[:3])
    assert list(obs.misc) == [f"{cam}_camera_{k}" for cam in cameras
                              for k in ("extrinsics", "intrinsics", "near", "far")]
    for cam in cameras:
        assert obs.misc[f"{cam}_camera_extrinsics"].shape == (4, 4)
        assert obs.misc[f"{cam}_camera_intrinsics"].dtype == np.float64
        assert type(obs.misc[f"{cam}_camera_near"]) is float


def test_low_dim_pickle_names_rlbench_classes() -> None:
    demo = rlbench_demo.Demo([fmt.rlbench_observation(_frame(), ["wrist", "front"])] * 2, None, 3)
    data = rlbench_demo.dumps(demo)
    strings = {arg for op, arg, _ in pickletools.genops(data) if isinstance(arg, str)}
    assert {"rlbench.demo", "Demo", "rlbench.backend.observation", "Observation"} <= strings
    # numpy 1.x's module path (PerAct's and RVT's environments), never numpy 2's or ours.
    assert "numpy.core.multiarray" in strings
    assert not any(s.startswith(("numpy._core", "agnostos")) for s in strings)
    assert data[:2] == b"\x80\x04"  # protocol 4, as RLBench's pickles
    with pytest.raises(ModuleNotFoundError, match="rlbench"):
        pickle.loads(data)  # a plain unpickler looks for rlbench itself
    back = rlbench_demo.loads(data)
    assert isinstance(back, rlbench_demo.Demo) and len(back) == 2 and back.variation_number == 3
    check_rlbench_fields(back[0])  # misc in RLBench's camera order: front before wrist
    with pytest.raises(pickle.UnpicklingError):
        rlbench_demo.loads(pickle.dumps(json.dumps))  # only RLBench's classes and numpy arrays


class _RunsShell:
    """Unpickling this calls os.system (what a hostile episode could hold)."""

    def __init__(self, command: str):
        self.command = command

    def __reduce__(self):
        import os

        return os.system, (self.command,)


def _resign(path) -> None:
    """Rewrite SHA256SUMS as a sender of a hostile episode would (it passes verification)."""
    import hashlib

    files = sorted(p for p in path.rglob("*") if p.is_file() and p.name != "SHA256SUMS")
    (path / "SHA256SUMS").write_text("".join(
        f"{hashlib.sha256(p.read_bytes()).hexdigest()}  {p.relative_to(path)}\n" for p in files))


@pytest.mark.parametrize("name", ["variation_number.pkl", "variation_descriptions.pkl",
                                  "low_dim_obs.pkl"])
def test_read_episode_refuses_code_in_pickles(tmp_path, name) -> None:
    """Every pickle of an episode goes through the restricted unpickler: one whose reduce
    calls os.system is refused with an error naming the file, and nothing runs; our own
    episodes still read."""
    path = tmp_path / "episode0"
    ex.write_episode(path, [_frame(), _frame()], ["open the drawer", "pull the drawer"], 2)
    ep = ex.read_episode(path)
    assert ep["descriptions"] == ["open the drawer", "pull the drawer"] and ep["variation"] == 2
    assert len(ep["demo"]) == 2 and ep["keyframes"] == [0, 1]
    check_rlbench_fields(ep["demo"][0])

    marker = tmp_path / "ran"
    (path / name).write_bytes(pickle.dumps(_RunsShell(f"touch {marker}")))
    _resign(path)
    with pytest.raises(pickle.UnpicklingError, match=rf"{path / name}.*system"):
        ex.read_episode(path)
    assert not marker.exists()
    # A harmless but wrong global (json.dumps) and a wrong type are refused as well.
    (path / name).write_bytes(pickle.dumps(json.dumps))
    _resign(path)
    with pytest.raises(pickle.UnpicklingError, match=str(path / name)):
        ex.read_episode(path)
    (path / name).write_bytes(pickle.dumps({"not": "expected"}))
    _resign(path)
    with pytest.raises(ValueError, match=str(path / name)):
        ex.read_episode(path)


def test_export_two_tasks_two_demos(tmp_path, capsys) -> None:
    cfg = ex.ExportConfig(out=tmp_path, tasks=("open_drawer", "push_buttons"), demos=2,
                          cameras=("front", "wrist"), size=32, batch=2)
    manifest = ex.export(cfg)
    assert "GB" in capsys.readouterr().out  # the estimate comes first
    assert manifest["agnostos"] == look_record("cpu")  # what rendered the images
    for task in cfg.tasks:
        assert manifest["tasks"][task]["episodes"] == 2
        assert manifest["tasks"][task]["labels"]["objects"]
        for i in range(2):
            path = ex.episode_dir(tmp_path, task, i)
            sums = [line.split("  ", 1)[1] for line in (path / "SHA256SUMS").read_text()
                    .splitlines()]
            assert "low_dim_obs.pkl" in sums and "front_rgb/0.png" in sums
            ep = ex.read_episode(path)
            n = len(ep["demo"])
            assert n >= 3  # reset + key actions
            for obs in ep["demo"]:
                check_rlbench_fields(obs)
            assert ep["demo"].variation_number == ep["variation"]
            assert ep["front_rgb"].shape == (n, 32, 32, 3) and ep["front_rgb"].dtype == np.uint8
            assert ep["wrist_depth"].shape == (n, 32, 32) and ep["wrist_mask"].dtype == np.int32
            assert 0.1 < np.median(ep["front_depth"]) < 4.5
            assert ep["low_dim"]["front_camera_extrinsics"].shape == (n, 4, 4)
            assert ep["low_dim"]["task_low_dim_state"].shape[1] >= 7
            assert set(np.unique(ep["low_dim"]["gripper_open"])) <= {0.0, 1.0}
            assert ep["descriptions"] and isinstance(ep["variation"], int)
    # Resumable: a rerun writes nothing; a damaged file is detected by its checksum.
    first = ex.episode_dir(tmp_path, "open_drawer", 0)
    stamp = (first / "SHA256SUMS").stat().st_mtime_ns
    ex.export(cfg)
    assert (first / "SHA256SUMS").stat().st_mtime_ns == stamp
    (first / "front_rgb" / "0.png").write_bytes(b"broken")
    with pytest.raises(ValueError, match="checksum"):
        ex.read_episode(first)
    # A file that SHA256SUMS does not list (here the pickle) is an error too.
    second = ex.episode_dir(tmp_path, "open_drawer", 1)
    sums = second / "SHA256SUMS"
    sums.write_text("".join(line + "\n" for line in sums.read_text().splitlines()
                            if not line.endswith("low_dim_obs.pkl")))
    with pytest.raises(ValueError, match="not in SHA256SUMS"):
        ex.read_episode(second)
    assert json.loads((tmp_path / "manifest.json").read_text())["config"]["size"] == 32


# ---- dense frames (--every) ------------------------------------------------------------------
# PerAct's keypoint heuristic, copied unchanged (logging and the 'random' / 'fixed_interval'
# methods left out) from peract/peract helpers/demo_loading_utils.py at commit
# 02fb87681c5a47be9dbf20141bedb836ee2d3ef9 (RVT uses the same function).
def _is_stopped(demo, i, obs, stopped_buffer, delta=0.1):
    next_is_not_final = i == (len(demo) - 2)
    gripper_state_no_change = (
            i < (len(demo) - 2) and
            (obs.gripper_open == demo[i + 1].gripper_open and
             obs.gripper_open == demo[i - 1].gripper_open and
             demo[i - 2].gripper_open == demo[i - 1].gripper_open))
    small_delta = np.allclose(obs.joint_velocities, 0, atol=delta)
    stopped = (stopped_buffer <= 0 and small_delta and
               (not next_is_not_final) and gripper_state_no_change)
    return stopped


def keypoint_discovery(demo, stopping_delta=0.1):
    episode_keypoints = []
    prev_gripper_open = demo[0].gripper_open
    stopped_buffer = 0
    for i, obs in enumerate(demo):
        stopped = _is_stopped(demo, i, obs, stopped_buffer, stopping_delta)
        stopped_buffer = 4 if stopped else stopped_buffer - 1
        # If change in gripper, or end of episode.
        last = i == (len(demo) - 1)
        if i != 0 and (obs.gripper_open != prev_gripper_open or
                       last or stopped):
            episode_keypoints.append(i)
        prev_gripper_open = obs.gripper_open
    if len(episode_keypoints) > 1 and (episode_keypoints[-1] - 1) == \
            episode_keypoints[-2]:
        episode_keypoints.pop(-2)
    return episode_keypoints


def test_frame_every_and_estimate() -> None:
    assert frame_every(None, 0.005) is None
    assert frame_every("rlbench", 0.005) == 10  # RLBench's 50 ms frames
    assert frame_every("rlbench", 0.002) == 25 and frame_every(3, 0.005) == 3
    with pytest.raises(ValueError):
        frame_every(0, 0.005)
    assert ex._parse_every("rlbench") == "rlbench" and ex._parse_every("7") == 7
    for bad in ("0", "x", "-2"):
        with pytest.raises(Exception, match="positive"):
            ex._parse_every(bad)
    cfg = ex.ExportConfig(out=None, tasks=("open_drawer",), demos=10)
    size, seconds = ex.estimate(cfg)
    dense_size, dense_seconds = ex.estimate(ex.ExportConfig(**{**vars(cfg), "every": "rlbench"}))
    # ~9 s of simulation per demo at 20 Hz: ~190 frames instead of ~8.7 keyframes (images:
    # 22x the bytes; time: the physics and per-task setup stay as they were).
    assert ex.frames_per_demo(None) < 10 and 150 < ex.frames_per_demo("rlbench") < 250
    assert 15 < dense_size / size < 30 and 5 < dense_seconds / seconds < dense_size / size
    assert ex.estimate(ex.ExportConfig(**{**vars(cfg), "every": 5}))[0] > dense_size


@pytest.mark.slow
def test_dense_frames(tmp_path) -> None:
    """--every rlbench on 1 demo of open_drawer: the expected frames, the keyframes among
    them exactly as a keyframes-only export writes them, joint velocities from the physics
    and PerAct's keypoint heuristic finding every key action."""
    import jax

    from agnostos_mjx.data.generate import demo_keys
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    task = "open_drawer"
    keys_cfg = ex.ExportConfig(out=tmp_path / "keys", tasks=(task,), demos=1,
                               cameras=("front",), size=32, batch=1)
    ex.export(keys_cfg)
    manifest = ex.export(ex.ExportConfig(**{**vars(keys_cfg), "out": tmp_path / "dense",
                                            "every": "rlbench"}))
    assert manifest["config"]["every"] == "rlbench"
    assert manifest["tasks"][task]["every_steps"] == 10
    sparse = ex.read_episode(ex.episode_dir(tmp_path / "keys", task, 0))
    dense = ex.read_episode(ex.episode_dir(tmp_path / "dense", task, 0))

    # The physics steps of each key action, from the same demo run again without images.
    episodes = Episodes(get_task(task), "native")
    env = episodes.reset(demo_keys(0, task, np.array([0]), np.array([0])),
                         np.zeros(1, np.int32), stop_at_success=False)
    actions, steps = episodes.expert_actions(env), []
    for k in range(actions.pos.shape[1]):
        if not actions.valid[0, k]:
            break
        before = int(env.sim_steps[0])
        env, _ = episodes.step(env, jax.tree.map(lambda x, k=k: x[:, k], actions))
        steps.append(int(env.sim_steps[0]) - before)
    # The native backend's per-step qpos: that of run()'s final state at each world's end,
    # repeated after it; a world with 0 steps keeps its qpos.
    three = env.physics.rows(np.zeros(3, int))
    ctrl = np.repeat(np.asarray(three.ctrl)[:, None], 20, axis=1)
    ctrl[:, :, 0] += 0.3
    state, sens, qpos = episodes.backend.run_with_qpos(three, ctrl, np.array([0, 7, 20]))
    state2, sens2 = episodes.backend.run(three, ctrl, np.array([0, 7, 20]))
    np.testing.assert_array_equal(sens[1:], sens2[1:])
    np.testing.assert_array_equal(state.qpos, state2.qpos)
    assert qpos.shape == (3, 20, episodes.scene.model.nq)
    np.testing.assert_array_equal(qpos[0], np.repeat(three.qpos[:1], 20, axis=0))
    np.testing.assert_array_equal(qpos[1, 6:], np.repeat(state.qpos[1:2], 14, axis=0))
    np.testing.assert_array_equal(qpos[2, -1], state.qpos[2])
    assert np.all(np.abs(np.diff(qpos[2], axis=0)).max(1) > 0)  # every step its own qpos
    # A key action of S steps: frames after steps 10, 20, ... < S, then its keyframe.
    expected = np.cumsum([0] + [-(-s // 10) for s in steps]).tolist()
    assert dense["keyframes"] == expected and len(dense["demo"]) == expected[-1] + 1
    assert len(sparse["demo"]) == len(steps) + 1 and sparse["keyframes"] == list(range(6))
    assert "keyframes.json" not in (ex.episode_dir(tmp_path / "keys", task, 0) / "SHA256SUMS"
                                    ).read_text()
    kf = np.array(dense["keyframes"])
    for name in fmt.LOW_DIM_FIELDS + ("front_camera_extrinsics",):
        np.testing.assert_array_equal(dense["low_dim"][name][kf], sparse["low_dim"][name],
                                      err_msg=name)
    for name in ("front_rgb", "front_depth", "front_mask"):
        np.testing.assert_array_equal(dense[name][kf], sparse[name], err_msg=name)
    for obs in dense["demo"]:
        check_rlbench_fields(obs, cameras=("front",))

    # Joint velocities: at rest (PerAct's 0.1 rad/s) at every keyframe, moving in between.
    speed = np.abs(dense["low_dim"]["joint_velocities"]).max(1)
    assert np.all(speed[kf] < 0.1), speed[kf]
    for lo, hi in zip(kf[:-1], kf[1:]):
        assert speed[lo + 1: hi].max() > 0.5  # every key action moves the arm
    # Dense frames move the scene: the arm in every frame differs from the one before.
    joints = dense["low_dim"]["joint_positions"]
    assert np.all(np.abs(np.diff(joints, axis=0)).max(1) > 1e-5)
    pose = dense["low_dim"]["gripper_pose"]
    assert np.abs(pose[kf[0] + 20, :3] - pose[kf[0], :3]).max() > 0.01
    images = dense["front_rgb"].reshape(len(joints), -1).astype(int)
    moved = np.abs(np.diff(images[kf[0]: kf[1] + 1], axis=0)).max(1) > 0
    assert moved.mean() > 0.8  # at 32 px the first and last steps may look alike

    # PerAct's heuristic on the dense episode: every key action has a keypoint among its own
    # frames, at its keyframe's gripper state and within 2 mm and 0.1 deg of its gripper
    # pose.  The heuristic marks the first frame of the rest that ends a move (all joints
    # < 0.1 rad/s) and then every 5th frame of it (its stopped_buffer), so the keyframe, the
    # rest's last frame, is found exactly or 1 to 4 frames (<= 0.2 s) early, and long rests
    # give more keypoints than key actions.
    found = keypoint_discovery(dense["demo"])
    grip = dense["low_dim"]["gripper_open"]
    for lo, hi in zip(kf[:-1], kf[1:]):
        near = [k for k in found if lo < k <= hi and grip[k] == grip[hi]
                and np.linalg.norm(pose[k, :3] - pose[hi, :3]) < 0.002
                and abs(np.dot(pose[k, 3:], pose[hi, 3:])) > np.cos(np.deg2rad(0.1) / 2)]
        assert near and hi - max(near) <= 4, (hi, found)
    assert len(found) > len(steps)
    # On the keyframes alone it finds only some (the reason for --every).
    assert len(keypoint_discovery(sparse["demo"])) < len(steps)


# ---- --workers -------------------------------------------------------------------------------
def _tree_sums(root) -> dict[str, str]:
    """SHA256 of every file under root; manifest.json without its wall-time field."""
    import hashlib

    out = {}
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        data = path.read_bytes()
        if path.name == "manifest.json":
            manifest = json.loads(data)
            manifest.pop("wall_s")
            data = json.dumps(manifest, indent=1).encode()
        out[str(path.relative_to(root))] = hashlib.sha256(data).hexdigest()
    return out


@pytest.mark.slow
def test_workers_same_files(tmp_path, capsys) -> None:
    """--workers 2 writes the same bytes as --workers 1; a failing task (an unknown name) is
    reported with its name, the others finish and the exit code is 1."""
    tasks = ("open_drawer", "no_such_task", "push_buttons")
    cfg = ex.ExportConfig(out=tmp_path / "one", tasks=tasks, demos=1, cameras=("front",),
                          size=32, batch=1)
    one = ex.export(cfg)
    assert list(one["failed_tasks"]) == ["no_such_task"]
    assert "KeyError" in one["failed_tasks"]["no_such_task"]
    ex.export(ex.ExportConfig(**{**vars(cfg), "out": tmp_path / "two"}), workers=2)
    captured = capsys.readouterr()
    assert "no_such_task FAILED: KeyError" in captured.err
    for task in ("open_drawer", "push_buttons"):
        assert f"export: {task}: 1/1 episodes" in captured.out
    two = json.loads((tmp_path / "two" / "manifest.json").read_text())
    assert list(two["tasks"]) == ["open_drawer", "push_buttons"] and two["tasks"] == one["tasks"]
    sums = _tree_sums(tmp_path / "one")
    assert sums == _tree_sums(tmp_path / "two")
    assert any(name.endswith("front_rgb/0.png") for name in sums)
    assert not list((tmp_path / "two").glob(".manifest.json.tmp*"))
    # The estimate's time is divided by the tasks run at once.
    assert ex.estimate(cfg, workers=2)[1] == pytest.approx(
        ex.estimate(cfg)[1] / min(2, usable_cores()))



def test_main_exit_code_on_failed_task(tmp_path, monkeypatch) -> None:
    calls = []

    def fake_export(cfg, workers):
        calls.append(workers)
        return {"wall_s": 0.0, "failed_tasks": {"open_drawer": "KeyError: x"}}

    monkeypatch.setattr(ex, "export", fake_export)
    args = ["--out", str(tmp_path), "--tasks", "open_drawer", "--workers", "3", "--quiet"]
    assert ex.main(args) == 1 and calls == [3]
    with pytest.raises(SystemExit):
        ex.main(args[:-2] + ["--workers", "0"])
