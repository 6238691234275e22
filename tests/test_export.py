"""Training-data export: 2 seen tasks x 2 demos in RLBench's episode folders, read back."""

from __future__ import annotations

import json
import pickle
import pickletools

import numpy as np
import pytest

from agnostos_mjx.data import export as ex
from agnostos_mjx.data import rlbench_demo


def test_encodings_round_trip() -> None:
    depth = np.linspace(0.01, 4.5, 100).reshape(10, 10)
    rgb = ex.encode_depth(depth, 0.01, 4.5)
    np.testing.assert_allclose(ex.decode_depth(rgb, 0.01, 4.5), depth, atol=1e-6)
    # RLBench's image_to_float_array(img, DEPTH_SCALE): R is the high byte for depth ...
    unit = np.sum(rgb.astype(np.int64) * [65536, 256, 1], axis=2) / ex.DEPTH_SCALE
    np.testing.assert_allclose(0.01 + unit * (4.5 - 0.01), depth, atol=1e-6)
    ids = np.arange(-1, 99).reshape(10, 10)
    assert np.array_equal(ex.rgb_to_int(ex.int_to_rgb(ids + 1)) - 1, ids)
    # ... and the low byte for masks (rgb_handles_to_mask: R + 256 G + 65536 B).
    mask = ex.int_to_rgb(np.array([[70000]])).astype(np.int64)
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
    demo = rlbench_demo.Demo([ex.rlbench_observation(_frame(), ["wrist", "front"])] * 2, None, 3)
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


def test_export_two_tasks_two_demos(tmp_path, capsys) -> None:
    cfg = ex.ExportConfig(out=tmp_path, tasks=("open_drawer", "push_buttons"), demos=2,
                          cameras=("front", "wrist"), size=32, batch=2)
    manifest = ex.export(cfg)
    assert "GB" in capsys.readouterr().out  # the estimate comes first
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
