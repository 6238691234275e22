"""LeRobot export (--format lerobot): 2 seen tasks x 2 demos rendered once, assembled as
v3.0 and v2.1 and read back bit for bit; layouts, statistics, resuming, interrupted
writes and bad flags on synthetic demos."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyarrow")
pytest.importorskip("pandas")

from agnostos_mjx.data import export as ex  # noqa: E402
from agnostos_mjx.data import export_demos  # noqa: E402
from agnostos_mjx.data import lerobot as lr  # noqa: E402
from agnostos_mjx.data import lerobot_layout as lay  # noqa: E402
from agnostos_mjx.data import rotations as rot  # noqa: E402
from agnostos_mjx.data.look import LOOK_KEY, look_record  # noqa: E402

TASKS = ("open_drawer", "push_buttons")


# ---- rotations and layouts ----------------------------------------------------------------------
def _quats(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_rotations_round_trip_and_conventions() -> None:
    q = _quats(500)
    for name in rot.ROTATIONS:
        values = rot.from_quat(q, name)
        assert values.shape == (500, len(rot.ROTATION_NAMES[name]))
        back = rot.to_quat(values, name)
        np.testing.assert_allclose(np.abs(np.sum(back * q, 1)), 1.0, atol=1e-12)
        assert np.all(back[:, 3] >= 0)
    with pytest.raises(ValueError, match="unknown rotation"):
        rot.from_quat(q, "matrix")
    # Our Euler angles are scipy's extrinsic 'xyz', our axis-angle its rotvec.
    scipy_rot = pytest.importorskip("scipy.spatial.transform").Rotation
    np.testing.assert_allclose(rot.quat_to_euler(q), scipy_rot.from_quat(q).as_euler("xyz"),
                               atol=1e-10)
    np.testing.assert_allclose(rot.quat_to_axis_angle(q), scipy_rot.from_quat(q).as_rotvec(),
                               atol=1e-10)
    m = scipy_rot.from_quat(q).as_matrix()
    np.testing.assert_allclose(rot.quat_to_rot6d(q), np.concatenate([m[:, :, 0], m[:, :, 1]], 1),
                               atol=1e-12)


def test_state_layouts_match_the_evaluator() -> None:
    """libero = the adapter's libero_state bit for bit; rlbench = gripper_pose +
    gripper_open as observed; xicm = xyz + Euler + gripper_open."""
    from agnostos_mjx.remote.adapter import lowdim

    pose = np.concatenate([np.random.default_rng(1).normal(size=(20, 3)), _quats(20, 2)],
                          1).astype(np.float32)
    grip = (np.arange(20) % 2).astype(np.float32)
    fingers = np.random.default_rng(3).uniform(0, 0.04, (20, 2)).astype(np.float32)
    libero = lowdim({"gripper_pose": pose, "gripper_open": grip,
                     "gripper_joint_positions": fingers})["libero_state"]
    np.testing.assert_array_equal(lay.state_vector("libero", pose, grip, fingers), libero)
    rl = lay.state_vector("rlbench", pose, grip, fingers)
    np.testing.assert_array_equal(rl, np.concatenate([pose, grip[:, None]], 1))
    xicm = lay.state_vector("xicm", pose, grip, fingers)
    assert xicm.shape == (20, 7) and xicm.dtype == np.float32
    np.testing.assert_allclose(xicm[:, 3:6], rot.quat_to_euler(pose[:, 3:].astype(np.float64)),
                               atol=1e-6)
    for layout in lay.STATE_LAYOUTS:
        feats = lay.features(["front"], 8, 8, layout, "rot6d")
        assert len(feats["observation.state"]["names"]) == \
            lay.state_vector(layout, pose, grip, fingers).shape[1]
        assert feats["action"]["names"][3:9] == list(rot.ROTATION_NAMES["rot6d"])
    with pytest.raises(ValueError, match="unknown state"):
        lay.check_state("joints")


def test_statistics() -> None:
    images = np.random.default_rng(4).integers(0, 256, (5, 6, 7, 3), dtype=np.uint8)
    stats = lay.histogram_stats(lay.image_histogram(images), len(images))
    assert list(stats) == list(lay.STAT_KEYS) and stats["count"].tolist() == [5]
    px = images.reshape(-1, 3) / 255.0
    for key, want in (("min", px.min(0)), ("max", px.max(0)), ("mean", px.mean(0)),
                      ("std", px.std(0))):
        assert stats[key].shape == (3, 1, 1)
        np.testing.assert_allclose(stats[key][:, 0, 0], want, atol=1e-12)
    np.testing.assert_allclose(stats["q50"][:, 0, 0],
                               np.quantile(px, 0.5, axis=0, method="inverted_cdf"))
    v = lay.vector_stats(np.random.default_rng(5).normal(size=(50, 4)))
    order = np.stack([v[k] for k in ("min",) + lay.QUANTILE_KEYS + ("max",)])
    assert np.all(np.diff(order, axis=0) >= 0)


# ---- synthetic demos: staging, assembly, reading ------------------------------------------------
CAMS = ("front", "wrist")


def _frames(n: int, seed: int, size: int = 8) -> list[dict]:
    rng = np.random.default_rng(seed)
    quats = _quats(n, seed)
    quats[0] = -np.abs(quats[0])  # a scalar-last quaternion with qw < 0, as observed
    return [{**{f"{c}_rgb": rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for c in CAMS},
             "gripper_pose": np.concatenate([rng.normal(size=3), quats[k]]).astype(np.float32),
             "gripper_open": float(k % 2), "joint_positions": rng.normal(size=7).astype(np.float32),
             "gripper_joint_positions": rng.uniform(0, 0.04, 2).astype(np.float32)}
            for k in range(n)]


def _stage(staging: Path, task: str, demo: int, n: int, dense: bool = False) -> dict:
    frames = _frames(n, seed=10 * demo + len(task))
    rng = np.random.default_rng(demo)
    pos, quat = rng.normal(size=(n + 2, 3)), _quats(n + 2, demo + 7)  # padded past n - 1
    grip = rng.uniform(0, 1, n + 2).astype(np.float32)
    info = {"task": task, "demo": demo, "variation": demo, "instruction": f"{task} #{demo % 2}",
            "cameras": list(CAMS), "size": 8, "seed": 0, "every_steps": 3 if dense else None,
            "frame_period_s": 0.05 if dense else None}
    keyframes = [0, 2, n - 1] if dense else list(range(n))
    lr.stage_episode(lr.staged_path(staging, task, demo), frames, keyframes, pos, quat, grip,
                     info, dense=dense)
    return {"frames": frames, "pos": pos, "quat": quat, "grip": grip, "info": info}


def _check_dataset(root: Path, staged: list[dict], layout: lr.Layout) -> dict:
    """Read `root` back and compare every row with what was staged."""
    data = lr.read_lerobot(root)
    info = data["info"]
    assert info["codebase_version"] == layout.version and info["robot_type"] == "panda"
    feats = info["features"]
    assert list(feats) == [f"observation.images.{c}" for c in CAMS] + [
        "observation.state", "action", "timestamp", "frame_index", "episode_index", "index",
        "task_index"]
    assert feats["observation.state"]["names"] == list(lay.STATE_NAMES[layout.state])
    assert feats["action"]["names"] == list(lay.action_names(layout.rotation))
    frames = data["frames"]
    assert len(data["episodes"]) == len(staged) and info["total_frames"] == len(frames)
    start = 0
    for ep, s in enumerate(staged):
        rows = frames[start: start + len(s["frames"])]
        dense = s["info"]["frame_period_s"] is not None
        for t, (row, f) in enumerate(zip(rows, s["frames"])):
            assert row["episode_index"] == ep and row["frame_index"] == t
            assert row["task"] == s["info"]["instruction"]
            for cam in CAMS:
                assert row[f"observation.images.{cam}"].dtype == np.uint8
                np.testing.assert_array_equal(row[f"observation.images.{cam}"], f[f"{cam}_rgb"])
            want = lay.state_vector(layout.state, f["gripper_pose"][None],
                                    np.array([f["gripper_open"]]),
                                    f["gripper_joint_positions"][None])[0]
            np.testing.assert_array_equal(row["observation.state"], want)
            if dense:  # the next frame's pose and gripper state, the last frame's own
                nxt = s["frames"][min(t + 1, len(rows) - 1)]
                target = np.concatenate([nxt["gripper_pose"].astype(np.float64),
                                         [nxt["gripper_open"]]])
            else:  # key action t, the last frame's repeating the last
                k = min(t, len(rows) - 2)
                target = np.concatenate([s["pos"][k], s["quat"][k][[1, 2, 3, 0]], [s["grip"][k]]])
            want = lay.action_vector(layout.rotation, target[None, :7], target[None, 7:])[0]
            np.testing.assert_array_equal(row["action"], want)
            np.testing.assert_allclose(
                rot.to_quat(row["action"][3:-1].astype(np.float64), layout.rotation)
                @ rot.canonical_quat(target[3:7]), 1.0, atol=1e-5)  # the same orientation
        start += len(rows)
    assert info["fps"] == (20 if staged[0]["info"]["frame_period_s"] else lr.KEYFRAME_FPS)
    assert [f["index"] for f in frames] == list(range(len(frames)))
    np.testing.assert_allclose([f["timestamp"] for f in frames],
                               np.float32([f["frame_index"] / info["fps"] for f in frames]))
    _check_stats(data)
    return data


def _check_stats(data: dict) -> None:
    feats = data["info"]["features"]
    assert set(data["stats"]) == set(feats)
    for key, s in data["stats"].items():
        assert list(s) == list(lay.STAT_KEYS), key
        assert s["count"] == ([len(data["frames"])])
        order = np.stack([np.asarray(s[k], np.float64) for k in
                          ("min",) + lay.QUANTILE_KEYS + ("max",)])
        assert np.all(np.diff(order, axis=0) >= -1e-9), key
        shape = (3, 1, 1) if feats[key]["dtype"] in ("image", "video") else tuple(feats[key]["shape"])
        assert np.asarray(s["mean"]).shape == shape, key
        if feats[key]["dtype"] == "image":
            assert 0 <= np.min(s["min"]) and np.max(s["max"]) <= 1
    for e in data["episodes"]:  # per-episode stats (v3.0: stats/ columns; v2.1: jsonl)
        assert set(e["stats"]) == set(feats)
        assert e["stats"]["action"]["count"].tolist() == [e["length"]]


@pytest.mark.parametrize("version", lr.VERSIONS)
def test_assemble_synthetic(tmp_path, version) -> None:
    staging = tmp_path / "staging"
    staged = [_stage(staging, "open_drawer", i, n) for i, n in ((0, 4), (1, 2))]
    staged.append(_stage(staging, "push_buttons", 0, 3))
    out = tmp_path / "ds"
    for layout in (lr.Layout(version), lr.Layout(version, "euler", "xicm"),
                   lr.Layout(version, "axis_angle", "libero"), lr.Layout(version, "rot6d")):
        done = lr.assemble(out, staging, TASKS, 2, layout)
        assert done == {"episodes": 3, "frames": 9, "tasks": 3, "skipped": False}
        data = _check_dataset(out, staged, layout)
        assert data["tasks"] == ["open_drawer #0", "open_drawer #1", "push_buttons #0"]
    assert sorted(p.name for p in out.iterdir()) == ["data", "meta"]  # no build leftovers
    prov = json.loads((out / lr.PROVENANCE).read_text())
    assert [(e["task"], e["demo"]) for e in prov["episodes"]] == [
        ("open_drawer", 0), ("open_drawer", 1), ("push_buttons", 0)]
    # Unchanged selection and layout: nothing is rewritten.
    stamp = (out / "meta/info.json").stat().st_mtime_ns
    assert lr.assemble(out, staging, TASKS, 2, lr.Layout(version, "rot6d"))["skipped"]
    assert (out / "meta/info.json").stat().st_mtime_ns == stamp
    # Fewer demos than staged: only the selection is assembled.
    assert lr.assemble(out, staging, TASKS, 1, lr.Layout(version))["episodes"] == 2
    _check_dataset(out, [staged[0], staged[2]], lr.Layout(version))


@pytest.mark.parametrize("version", lr.VERSIONS)
def test_many_files_and_chunks(tmp_path, monkeypatch, version) -> None:
    """Past the file size (v3.0) and the files per chunk directory, episodes spread over
    files and chunks in dataset order; a feature that disagrees with its column is caught."""
    staging = tmp_path / "staging"
    staged = [_stage(staging, t, i, 2 + i) for t in TASKS for i in range(2)]
    monkeypatch.setattr(lr, "DATA_FILE_MB", 1e-9)  # v3.0: a new file per episode
    monkeypatch.setattr(lr, "CHUNKS_SIZE", 3)
    out = tmp_path / "ds"
    lr.assemble(out, staging, TASKS, 2, lr.Layout(version))
    data = _check_dataset(out, staged, lr.Layout(version))
    files = sorted(str(p.relative_to(out)) for p in (out / "data").rglob("*.parquet"))
    if version == "v3.0":
        assert files == ["data/chunk-000/file-000.parquet", "data/chunk-000/file-001.parquet",
                         "data/chunk-000/file-002.parquet", "data/chunk-001/file-000.parquet"]
        assert [(e["data/chunk_index"], e["data/file_index"]) for e in data["episodes"]] == [
            (0, 0), (0, 1), (0, 2), (1, 0)]
    else:
        assert files[-1] == "data/chunk-001/episode_000003.parquet"
        assert data["info"]["total_chunks"] == 2
    info = json.loads((out / "meta/info.json").read_text())
    info["features"]["action"]["shape"] = [7]
    (out / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(lr.LeRobotFormatError, match="action"):
        lr.read_lerobot(out)


def test_dense_actions_and_fps(tmp_path) -> None:
    staging = tmp_path / "staging"
    staged = [_stage(staging, "open_drawer", 0, 5, dense=True)]
    lr.assemble(tmp_path / "ds", staging, TASKS, 1, lr.Layout())
    data = _check_dataset(tmp_path / "ds", staged, lr.Layout())
    assert data["info"]["fps"] == 20
    prov = json.loads((tmp_path / "ds" / lr.PROVENANCE).read_text())
    assert prov["episodes"][0]["keyframes"] == [0, 2, 4] and prov["frames"].startswith("dense")
    # Staged demos of different frame rates are not mixed.
    _stage(staging, "push_buttons", 0, 3)
    with pytest.raises(ValueError, match="frame periods"):
        lr.assemble(tmp_path / "ds", staging, TASKS, 1, lr.Layout())


@pytest.mark.parametrize("version", lr.VERSIONS)
def test_info_json_records_the_look(tmp_path, version) -> None:
    """The images' renderer and scene version go into info.json under "agnostos" (a key
    LeRobot ignores); another record assembles again, the same one does not."""
    from agnostos_mjx.data.look import check_look

    staging = tmp_path / "staging"
    staged = [_stage(staging, "open_drawer", 0, 3)]
    out = tmp_path / "ds"
    look = look_record("cpu")
    assert not lr.assemble(out, staging, TASKS, 1, lr.Layout(version), look=look)["skipped"]
    data = _check_dataset(out, staged, lr.Layout(version))  # our reader takes the key
    assert data["info"][LOOK_KEY] == look and check_look(data["info"], "cpu") is None
    assert lr.assemble(out, staging, TASKS, 1, lr.Layout(version), look=look)["skipped"]
    other = {**look, "scene_version": "0123456789ab"}
    assert not lr.assemble(out, staging, TASKS, 1, lr.Layout(version), look=other)["skipped"]
    info = json.loads((out / "meta/info.json").read_text())
    assert info[LOOK_KEY] == other and "scene version 0123456789ab" in check_look(info, "cpu")


def test_interrupted_writes_leave_no_partial_files(tmp_path, monkeypatch) -> None:
    import pyarrow.parquet as pq

    staging = tmp_path / "staging"
    real = pq.write_table

    def dies(table, where, **kw):  # half a file, then the interruption
        Path(where).write_bytes(b"PAR1 half")
        raise KeyboardInterrupt

    monkeypatch.setattr(pq, "write_table", dies)
    with pytest.raises(KeyboardInterrupt):
        _stage(staging, "open_drawer", 0, 3)
    monkeypatch.setattr(pq, "write_table", real)
    assert list(staging.rglob("*")) == [staging / "open_drawer"]  # nothing, not even a temp
    assert not lr.is_staged(lr.staged_path(staging, "open_drawer", 0))
    staged = [_stage(staging, "open_drawer", 0, 3)]
    out = tmp_path / "ds"
    lr.assemble(out, staging, TASKS, 1, lr.Layout())
    # Interrupted while building the next layout: the previous dataset stays whole.
    monkeypatch.setattr(lr, "_write_v30_meta", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
        lr.assemble(out, staging, TASKS, 1, lr.Layout(rotation="euler"))
    _check_dataset(out, staged, lr.Layout())
    monkeypatch.undo()
    # Interrupted while moving it into place: no info.json, so no dataset that looks whole;
    # the next run assembles again.
    monkeypatch.setattr(lr.os, "replace", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
        lr.assemble(out, staging, TASKS, 1, lr.Layout(rotation="euler"))
    monkeypatch.undo()
    assert not (out / "meta/info.json").exists()
    with pytest.raises(FileNotFoundError):
        lr.read_lerobot(out)
    assert not lr.assemble(out, staging, TASKS, 1, lr.Layout(rotation="euler"))["skipped"]
    _check_dataset(out, staged, lr.Layout(rotation="euler"))
    # A directory that is not ours is never replaced.
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(ValueError, match="not an agnostos_mjx LeRobot export"):
        lr.assemble(tmp_path / "mine", staging, TASKS, 1, lr.Layout())


def test_video_features(tmp_path) -> None:
    pytest.importorskip("av")
    staging = tmp_path / "staging"
    _stage(staging, "open_drawer", 0, 3)
    _stage(staging, "push_buttons", 0, 2)
    for version in lr.VERSIONS:
        out = tmp_path / version
        lr.assemble(out, staging, TASKS, 1, lr.Layout(version, video=True))
        data = lr.read_lerobot(out)
        feats = data["info"]["features"]
        assert feats["observation.images.front"]["dtype"] == "video"
        assert feats["observation.images.front"]["info"]["video.height"] == 8
        assert data["info"]["video_path"] and len(list(out.rglob("*.mp4"))) == 4
        assert data["frames"][0]["observation.images.wrist"].shape == (8, 8, 3)  # lossy
        _check_stats(data)


def test_flags(tmp_path, monkeypatch, capsys) -> None:
    def fails(args, match):
        with pytest.raises(SystemExit):
            ex.main(["--out", str(tmp_path / "x"), "--tasks", "open_drawer", *args])
        assert match in capsys.readouterr().err

    fails(["--format", "lerobot", "--rotation", "matrix"], "unknown rotation 'matrix'")
    fails(["--format", "lerobot", "--state", "joints"], "unknown state layout 'joints'")
    fails(["--format", "lerobot", "--lerobot-version", "v2.0"], "unknown LeRobot version")
    fails(["--rotation", "euler", "--video"], "--rotation, --video: only with --format lerobot")
    fails(["--format", "parquet"], "invalid choice")
    import builtins

    real_import = builtins.__import__

    def no_av(name, *args, **kw):
        if name == "av":
            raise ImportError("No module named 'av'")
        return real_import(name, *args, **kw)

    monkeypatch.setattr(builtins, "__import__", no_av)
    fails(["--format", "lerobot", "--video"], "--video needs PyAV")
    monkeypatch.undo()
    assert not (tmp_path / "x").exists()  # nothing written for bad flags
    with pytest.raises(ValueError, match="unknown format"):
        ex.ExportConfig(out=tmp_path, tasks=("open_drawer",), format="hdf5")


# ---- the real export: 2 seen tasks x 2 demos ----------------------------------------------------
def test_export_two_tasks_two_demos(tmp_path, monkeypatch, capsys) -> None:
    """Rendered once (32 px, front + wrist), assembled as v3.0 then v2.1 from the same
    staged demos; the reader returns exactly the rendered pixels, the observed states and
    the expert's key actions; a rerun renders nothing."""
    captured: dict = {}
    stage = lr.stage_episode

    def capture(path, frames, keyframes, pos, quat, grip, info, dense):
        captured[(info["task"], info["demo"])] = {"frames": frames, "pos": pos, "quat": quat,
                                                  "grip": grip, "info": info}
        stage(path, frames, keyframes, pos, quat, grip, info, dense)

    monkeypatch.setattr(lr, "stage_episode", capture)
    out = tmp_path / "agnostos"
    cfg = ex.ExportConfig(out=out, tasks=TASKS, demos=2, cameras=CAMS, size=32, batch=2,
                          format="lerobot")
    manifest = ex.export(cfg)
    assert manifest["lerobot"]["episodes"] == 4 and "GB" in capsys.readouterr().out
    look = look_record("cpu")  # what rendered the images, in info.json and the staging's manifest
    assert manifest[LOOK_KEY] == look
    assert json.loads((out / "meta/info.json").read_text())[LOOK_KEY] == look
    staged = [captured[(t, i)] for t in TASKS for i in range(2)]
    for s in staged:
        assert s["info"]["instruction"] and s["frames"][0]["front_rgb"].shape == (32, 32, 3)
    data = _check_dataset(out, staged, lr.Layout())
    # The key action's target is where the next keyframe finds the gripper (1 cm: buttons
    # are pressed beyond their travel).
    frames = data["frames"]
    for a, b in zip(frames[:-1], frames[1:]):
        if a["episode_index"] == b["episode_index"]:
            assert np.abs(a["action"][:3] - b["observation.state"][:3]).max() < 0.015
            assert abs(a["action"][3:7] @ b["observation.state"][3:7]) > 0.999
    # A rerun as v2.1 renders nothing (no expert runs) and replaces the v3.0 layout.
    monkeypatch.setattr(export_demos, "episode_observations",
                        lambda *a, **k: pytest.fail("rendered"))
    stamp = lr.staged_path(cfg.staging_root(), "open_drawer", 0).stat().st_mtime_ns
    ex.export(ex.ExportConfig(**{**vars(cfg), "lerobot_version": "v2.1", "state": "libero"}))
    assert lr.staged_path(cfg.staging_root(), "open_drawer", 0).stat().st_mtime_ns == stamp
    _check_dataset(out, staged, lr.Layout("v2.1", state="libero"))
    assert sorted(p.name for p in (out / "meta").iterdir()) == [
        "agnostos_mjx.json", "episodes.jsonl", "episodes_stats.jsonl", "info.json",
        "stats.json", "tasks.jsonl"]
    assert len(list((out / "data/chunk-000").glob("episode_*.parquet"))) == 4
    _read_with_datasets(out)


def _read_with_datasets(root: Path) -> None:
    """The Hugging Face `datasets` reads as LeRobot v2.1 does (when installed)."""
    try:
        import datasets
    except ImportError:
        return
    ds = datasets.load_dataset("parquet", data_dir=str(root / "data"), split="train")
    assert isinstance(ds.features["observation.images.front"], datasets.Image)
    assert np.asarray(ds[0]["observation.images.front"]).shape == (32, 32, 3)


# ---- opt-in: the real LeRobot reads both versions -------------------------------------------------
LEROBOT_SIDE = r'''
import sys
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

root, out, mode = sys.argv[1:4]
if mode == "convert":  # LeRobot's own v2.1 -> v3.0 converter, in place (root/<repo_id>)
    from pathlib import Path
    try:  # lerobot >= 0.5: root is the dataset's folder
        from lerobot.scripts.convert_dataset_v21_to_v30 import convert_dataset
        where = Path(root)
    except ImportError:  # lerobot 0.4: root holds <repo_id>/
        from lerobot.datasets.v30.convert_dataset_v21_to_v30 import convert_dataset
        where = Path(root).parent.parent
    convert_dataset(repo_id="local/agnostos", root=str(where), push_to_hub=False)
meta = LeRobotDatasetMetadata("local/agnostos", root=root)
ds = LeRobotDataset("local/agnostos", root=root,
                    delta_timestamps={"action": [k / meta.fps for k in range(3)]})
dump = {}
for i in range(len(ds)):
    for k, v in ds[i].items():
        dump.setdefault(k, []).append(v if k == "task" else np.asarray(v))
np.savez(out, **{k: np.array(v) if k == "task" else np.stack(v) for k, v in dump.items()},
         stats=np.array([f"{f}/{s}" for f in meta.stats for s in meta.stats[f]]))
'''


@pytest.mark.parametrize("variable", ["AGNOSTOS_LEROBOT_PYTHON", "AGNOSTOS_LEROBOT21_PYTHON"])
def test_real_lerobot_reads_both_versions(tmp_path, variable) -> None:
    """Opt-in, with a command running a Python that has lerobot (e.g. "env PYTHONPATH=/x
    /venv/bin/python"): AGNOSTOS_LEROBOT_PYTHON, lerobot >= 0.4 (v3.0): LeRobotDataset reads
    our v3.0 export, and LeRobot's v2.1 -> v3.0 converter turns our v2.1 export into the
    same data; AGNOSTOS_LEROBOT21_PYTHON, lerobot 0.3.3 (v2.1, openpi's format):
    LeRobotDataset reads our v2.1 export.  Every image, state, action chunk (with its
    padding) and task as our reader's."""
    import os
    import shlex
    import shutil
    import subprocess

    command = os.environ.get(variable)
    if not command:
        pytest.skip(f"set {variable} to a Python with lerobot installed")
    staging = tmp_path / "staging"
    _stage(staging, "open_drawer", 0, 4)
    _stage(staging, "push_buttons", 0, 3)
    (tmp_path / "side.py").write_text(LEROBOT_SIDE)
    lr.assemble(tmp_path / "v30", staging, TASKS, 1, lr.Layout("v3.0", "euler", "xicm"))
    lr.assemble(tmp_path / "v21", staging, TASKS, 1, lr.Layout("v2.1", "euler", "xicm"))
    converted = tmp_path / "conv" / "local" / "agnostos"
    shutil.copytree(tmp_path / "v21", converted)
    ours = lr.read_lerobot(tmp_path / "v30")["frames"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    runs = (((tmp_path / "v30", "read"), (converted, "convert"))
            if variable == "AGNOSTOS_LEROBOT_PYTHON" else ((tmp_path / "v21", "read"),))
    for root, mode in runs:
        dump = tmp_path / f"{mode}.npz"
        subprocess.run([*shlex.split(command), str(tmp_path / "side.py"), str(root), str(dump),
                        mode], check=True, env=env, timeout=600)
        d = np.load(dump)
        assert len(d["index"]) == len(ours)
        for cam in CAMS:
            key = f"observation.images.{cam}"
            img = np.round(d[key] * 255).astype(np.uint8).transpose(0, 2, 3, 1)
            np.testing.assert_array_equal(img, np.stack([f[key] for f in ours]))
        for key in ("observation.state", "frame_index", "episode_index", "index", "task_index",
                    "timestamp"):
            np.testing.assert_array_equal(d[key], np.stack([np.asarray(f[key]) for f in ours]))
        assert list(d["task"]) == [f["task"] for f in ours]
        ep = np.array([f["episode_index"] for f in ours])
        for i in range(len(ours)):
            for k in range(3):
                pad = i + k >= len(ours) or ep[i + k] != ep[i]
                assert bool(d["action_is_pad"][i, k]) == pad
                if not pad:
                    np.testing.assert_array_equal(d["action"][i, k], ours[i + k]["action"])
        assert {f"action/{q}" for q in lay.QUANTILE_KEYS} <= set(d["stats"]) or \
            variable == "AGNOSTOS_LEROBOT21_PYTHON"  # v2.1 aggregates min..count only


def test_reader_takes_lerobots_converted_layout(tmp_path) -> None:
    """What LeRobot's v2.1->v3.0 converter writes (a per-feature "fps" in info.json,
    variable-length lists for vectors; eval/reports/lerobot_interop) reads as our own
    v3.0 export does; a vector of the wrong length is refused."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from agnostos_mjx.data.lerobot_read import LeRobotFormatError, read_lerobot

    staging = tmp_path / "staging"
    _stage(staging, "open_drawer", 0, 3)
    out = tmp_path / "ds"
    lr.assemble(out, staging, TASKS, 1, lr.Layout("v3.0"))
    ours = read_lerobot(out)
    info_path = out / "meta/info.json"
    info = json.loads(info_path.read_text())
    for ft in info["features"].values():
        ft["fps"] = info["fps"]
    info_path.write_text(json.dumps(info))
    data = next((out / "data").glob("*/*.parquet"))
    table = pq.read_table(data)
    for key in ("observation.state", "action"):
        i = table.column_names.index(key)
        table = table.set_column(i, key, table.column(key).cast(pa.list_(pa.float32())))
    pq.write_table(table, data)
    converted = read_lerobot(out)
    assert len(ours["frames"]) == len(converted["frames"]) == 3
    for a, b in zip(ours["frames"], converted["frames"]):
        np.testing.assert_array_equal(a["observation.state"], b["observation.state"])
        np.testing.assert_array_equal(a["action"], b["action"])
    rows = table.column("action").to_pylist()
    rows[0] = rows[0][:-1]
    i = table.column_names.index("action")
    pq.write_table(table.set_column(i, "action", pa.array(rows, pa.list_(pa.float32()))), data)
    with pytest.raises(LeRobotFormatError, match="action of shape"):
        read_lerobot(out)
