"""Seen-task demos as a LeRobot dataset (``python -m agnostos_mjx.data.export --format
lerobot``), written with pyarrow, pandas and Pillow (no torch, no lerobot): images as PNG
inside the parquet files (lossless, no codec; ``--video``: MP4 files instead, lossy),
``observation.images.<camera>``, ``observation.state``, ``action``, the episode's
instruction as its task, ``robot_type`` "panda".

Two layouts (``--lerobot-version``), the same data columns in both:

v3.0 (lerobot >= 0.4; checked against huggingface/lerobot 7427f31:
src/lerobot/datasets/utils.py (paths, DatasetInfo), feature_utils.py
(get_hf_features_from_features, create_empty_dataset_info), dataset_metadata.py
(save_episode, _save_episode_metadata: the episodes parquet's columns), dataset_writer.py
(_save_episode_data, _save_episode_video), io_utils.py (write_tasks, load_nested_dataset,
write_table_one_row_group_per_episode), compute_stats.py (DEFAULT_QUANTILES), dataset_reader.py
(the ``index`` / ``dataset_from_index`` lookups), src/lerobot/utils/constants.py
(DEFAULT_FEATURES))::

    meta/info.json                codebase_version "v3.0", fps, features, totals, chunks_size
                                  1000, data_files_size_in_mb 100, video_files_size_in_mb 200,
                                  data_path, video_path (null without --video), robot_type,
                                  splits {"train": "0:N"}, and ours: "agnostos", the
                                  renderer and scene version of the images (data/look.py;
                                  lerobot >= 0.6 ignores the key with one logged warning,
                                  "Unknown fields in DatasetInfo", and drops it on a rewrite)
    meta/stats.json               per feature: min max mean std count q01 q10 q50 q90 q99
    meta/tasks.parquet            index "task" (the instruction), column task_index
    meta/episodes/chunk-000/file-000.parquet
                                  a row per episode: episode_index, tasks [str], length,
                                  data/chunk_index, data/file_index, dataset_from_index,
                                  dataset_to_index, [videos/<key>/{chunk_index, file_index,
                                  from_timestamp, to_timestamp}], stats/<feature>/<stat>,
                                  meta/episodes/chunk_index, meta/episodes/file_index
    meta/agnostos_mjx.json        ours (LeRobot ignores it): layouts, frames, per episode the
                                  task, demo, variation and keyframe indices
    data/chunk-000/file-000.parquet
                                  episodes in order, one row group each, a new file past
                                  100 MB (1000 files per chunk directory)
    videos/<key>/chunk-000/file-000.mp4   (--video) one episode per file

v2.1 (what openpi reads: lerobot 0cf8648 (v0.3.3's format), lerobot/common/datasets/utils.py
(paths, create_empty_dataset_info, write_episode, write_episode_stats, write_task),
lerobot_dataset.py (LeRobotDatasetMetadata.save_episode, load_hf_dataset: ``load_dataset(
"parquet", data_dir=<root>/data)``, check_timestamps_sync), compute_stats.py)::

    meta/info.json                codebase_version "v2.1", robot_type, totals, total_videos,
                                  total_chunks, chunks_size 1000, fps, splits, data_path
                                  data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet,
                                  video_path, features, "agnostos" (as v3.0's)
    meta/episodes.jsonl           {"episode_index", "tasks": [str], "length"}
    meta/tasks.jsonl              {"task_index", "task"}
    meta/episodes_stats.jsonl     {"episode_index", "stats": {feature: {min,max,mean,std,count,
                                  q01..q99}}} (lerobot v2.1 aggregates the first five and
                                  ignores the quantiles; its v2.1 -> v3.0 converter keeps them)
    meta/stats.json               as v3.0's (lerobot v2.1 itself aggregates episodes_stats)
    meta/agnostos_mjx.json        as above
    data/chunk-000/episode_000000.parquet                 one file per episode
    videos/chunk-000/<key>/episode_000000.mp4             (--video)

Read back as written by LeRobot's own ``LeRobotDataset``: lerobot 0.4.4 (v3.0; and its
``convert_dataset_v21_to_v30`` turns our v2.1 export into our v3.0 one) and lerobot 0.3.3
(v2.1) with datasets 3.6.0 (openpi's) return our reader's images bit for bit, states,
action chunks with their padding and tasks (tests/test_lerobot_export.py, opt-in
``test_real_lerobot_reads_both_versions``); ``datasets`` 3.6.0 and 5.2.0 decode the
images from the schema metadata alone.

Data columns, in info.json's feature order: ``observation.images.<camera>`` (struct
{bytes: PNG, path: null}, HF ``Image``), ``observation.state`` and ``action`` (fixed-size
float32 lists), ``timestamp`` (float32, frame_index / fps), ``frame_index``,
``episode_index``, ``index`` (the row's position in the dataset), ``task_index`` (int64).
Each data parquet carries the Hugging Face ``datasets`` schema metadata (key
``huggingface``; data/lerobot_layout.py: hf_features), so ``load_dataset("parquet")``
decodes its images without being told the features.  State and action layouts, names and
statistics: data/lerobot_layout.py.

Frames and actions: keyframes (default): the scene after reset and after every expert key
action; frame t's action is key action t (its tip target and the gripper's open amount as
the expert commands it, e.g. 0.1 to press a button with closed fingers) and the last
frame's repeats the last key action (already reached: a hold).  fps is nominal (10; only
``delta_timestamps`` use it).  Dense (``--every K|rlbench``): frame t's action is frame
t+1's gripper pose and gripper_open (1/0), the last frame's its own; fps = 1 / (K x the
physics timestep), rounded (20 for rlbench).  ``meta/agnostos_mjx.json`` lists each
episode's keyframe indices.

Writing: each demo is rendered once into a staging file, ``<staging>/<task>/episode<i>.parquet``
(default staging directory: ``<out>.staging``, next to the dataset so that pushing the
dataset does not upload it): the PNGs and the raw poses, written to a temporary name and
renamed, so a file there is complete.  A rerun skips staged demos (resumable; layouts,
rotations and versions can change between runs without rendering again).  The dataset is
then assembled from the staged files in ``<out>/.build`` and moved into place; its
``meta/info.json`` is removed first and written last, so an interrupted assembly never
leaves a dataset that looks complete, and the next run assembles again.  An unchanged
selection and layout are not assembled twice.
"""

from __future__ import annotations

import io
import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from agnostos_mjx.data.expert_frames import next_frame_actions
from agnostos_mjx.data.lerobot_layout import (
    IMAGE_PREFIX,
    ROTATION_DOCS,
    STAT_KEYS,
    STATE_DOCS,
    action_vector,
    check_state,
    features,
    hf_features,
    histogram_stats,
    image_histogram,
    jsonable,
    state_vector,
    vector_stats,
)
from agnostos_mjx.data.lerobot_read import LeRobotFormatError, read_lerobot
from agnostos_mjx.data.lerobot_video import (
    decode_png_column,
    encode_video,
    require_av,
    video_info,
)
from agnostos_mjx.data.look import LOOK_KEY
from agnostos_mjx.data.rotations import check_rotation

__all__ = ["Layout", "LeRobotFormatError", "assemble", "read_lerobot", "stage_episode",
           "staged_path", "staging_dir"]

VERSIONS = ("v3.0", "v2.1")
ROBOT_TYPE = "panda"
KEYFRAME_FPS = 10
CHUNKS_SIZE = 1000
DATA_FILE_MB = 100
VIDEO_FILE_MB = 200
PNG_COMPRESS_LEVEL = 1  # as the RLBench export; lossless at any level
STAGING_VERSION = 1
META_KEY = b"agnostos_mjx"
PROVENANCE = "meta/agnostos_mjx.json"
V30_DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
V30_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
V30_EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
V21_DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
V21_VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"


@dataclass(frozen=True)
class Layout:
    """The dataset's form, chosen at assembly (staged demos serve every layout)."""

    version: str = "v3.0"
    rotation: str = "quat"
    state: str = "rlbench"
    video: bool = False

    def __post_init__(self) -> None:
        if self.version not in VERSIONS:
            raise ValueError(f"unknown LeRobot version {self.version!r}; choose from "
                             f"{', '.join(VERSIONS)}")
        check_rotation(self.rotation)
        check_state(self.state)
        if self.video:
            require_av()


def require_libraries() -> None:
    """pyarrow, pandas and Pillow, or an ImportError saying how to install them."""
    missing = []
    for name in ("pyarrow", "pandas", "PIL"):
        try:
            __import__(name)
        except ImportError:
            missing.append("pillow" if name == "PIL" else name)
    if missing:
        raise ImportError(f"--format lerobot needs {', '.join(missing)}: "
                          f"pip install 'agnostos-mjx[lerobot]'")


def staging_dir(out: Path) -> Path:
    out = Path(out)
    return out.with_name(out.name + ".staging")


def staged_path(staging: Path, task: str, index: int) -> Path:
    return Path(staging) / task / f"episode{index}.parquet"


def is_staged(path: Path) -> bool:
    return Path(path).is_file()


def _png(img: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img, np.uint8)).save(buf, format="PNG",
                                                             compress_level=PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def _vectors(rows: np.ndarray, dtype):
    import pyarrow as pa

    rows = np.ascontiguousarray(rows, dtype)
    values = pa.array(rows.reshape(-1))
    # pa.list_'s child name "item", as `datasets` writes (from_arrays alone says "element")
    return pa.FixedSizeListArray.from_arrays(values, type=pa.list_(values.type, rows.shape[1]))


def _image_column(pngs: Sequence[bytes]):
    import pyarrow as pa

    return pa.StructArray.from_arrays(
        [pa.array(list(pngs), pa.binary()), pa.array([None] * len(pngs), pa.string())],
        names=["bytes", "path"])


def atomic_parquet(table, path: Path) -> None:
    """Write `table` to a temporary name next to `path` and rename it: `path` is either
    absent or complete; the temporary file is removed if writing fails."""
    import pyarrow.parquet as pq

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial{os.getpid()}")
    try:
        pq.write_table(table, tmp, compression="snappy")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def stage_episode(path: Path, frames: list[dict], keyframes: Sequence[int], key_pos: np.ndarray,
                  key_quat: np.ndarray, key_gripper: np.ndarray, info: dict,
                  dense: bool) -> None:
    """One demo's frames (RLBenchObservation.world dicts) -> its staging parquet.

    `key_pos` (K, 3), `key_quat` (K, 4, w first), `key_gripper` (K,): the expert's key
    actions, of which the first len(frames) - 1 ran (keyframes only) or len(keyframes) - 1
    (dense).  Columns: ``observation.images.<camera>`` (PNG), ``gripper_pose`` (7, x y z qx
    qy qz qw), ``gripper_open``, ``gripper_joint_positions`` (2), ``joint_positions`` (7),
    ``target_pose`` (7, float64) and ``target_gripper``: each frame's action before the
    layout is applied; `info` (task, demo, variation, instruction, frame_period_s, ...) and
    the per-camera pixel histograms go to the schema metadata."""
    import pyarrow as pa

    n = len(frames)
    pose = np.stack([np.asarray(f["gripper_pose"], np.float32) for f in frames])
    grip = np.array([f["gripper_open"] for f in frames], np.float32)
    if dense:
        target, target_grip = next_frame_actions(frames)
    else:
        ran = n - 1
        if ran > len(key_pos):
            raise ValueError(f"{n} keyframes but {len(key_pos)} key actions")
        if ran == 0:  # nothing ran: hold where the gripper is
            target, target_grip = pose.astype(np.float64), grip
        else:
            quat = np.asarray(key_quat, np.float64)[:ran][:, [1, 2, 3, 0]]
            target = np.concatenate([np.asarray(key_pos, np.float64)[:ran], quat], 1)
            target = np.concatenate([target, target[-1:]])
            target_grip = np.asarray(key_gripper, np.float32)[:ran]
            target_grip = np.concatenate([target_grip, target_grip[-1:]])
    columns, hist = {}, {}
    for cam in info["cameras"]:
        images = np.stack([np.asarray(f[f"{cam}_rgb"], np.uint8) for f in frames])
        columns[IMAGE_PREFIX + cam] = _image_column([_png(im) for im in images])
        hist[cam] = image_histogram(images).tolist()
    columns["gripper_pose"] = _vectors(pose, np.float32)
    columns["gripper_open"] = pa.array(grip, pa.float32())
    columns["gripper_joint_positions"] = _vectors(
        np.stack([np.asarray(f["gripper_joint_positions"], np.float32) for f in frames]),
        np.float32)
    columns["joint_positions"] = _vectors(
        np.stack([np.asarray(f["joint_positions"], np.float32) for f in frames]), np.float32)
    columns["target_pose"] = _vectors(target, np.float64)
    columns["target_gripper"] = pa.array(np.asarray(target_grip, np.float32), pa.float32())
    meta = {**info, "staging_version": STAGING_VERSION, "frames": n,
            "keyframes": [int(k) for k in keyframes], "histograms": hist}
    table = pa.table(columns).replace_schema_metadata({META_KEY: json.dumps(meta)})
    atomic_parquet(table, Path(path))


def staged_info(path: Path) -> dict:
    import pyarrow.parquet as pq

    return json.loads(pq.read_schema(path).metadata[META_KEY])


# ---- assembly ----------------------------------------------------------------------------------
def _write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=4, ensure_ascii=False) + "\n")


def _write_jsonl(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r, ensure_ascii=False) + "\n" for r in rows))


def _fps(infos: list[dict]) -> int:
    periods = {i.get("frame_period_s") for i in infos}
    if len(periods) != 1:
        raise ValueError(f"staged demos mix frame periods {sorted(map(str, periods))}")
    period = periods.pop()
    return KEYFRAME_FPS if period is None else max(1, round(1.0 / period))


def _episode_table(staged, feats: dict, layout: Layout, first_index: int, episode: int,
                   task_index: int, fps: int):
    """A staged table -> the dataset's columns (feature order, HF schema metadata), and
    the numeric columns as arrays (for the statistics)."""
    import pyarrow as pa

    n = staged.num_rows
    col = lambda name: np.stack(staged.column(name).to_numpy(zero_copy_only=False))  # noqa: E731
    pose = col("gripper_pose")
    grip = staged.column("gripper_open").to_numpy()
    state = state_vector(layout.state, pose, grip, col("gripper_joint_positions"))
    action = action_vector(layout.rotation, col("target_pose"),
                           staged.column("target_gripper").to_numpy())
    frame = np.arange(n, dtype=np.int64)
    numeric = {"observation.state": state, "action": action,
               "timestamp": (frame / fps).astype(np.float32), "frame_index": frame,
               "episode_index": np.full(n, episode, np.int64),
               "index": first_index + frame, "task_index": np.full(n, task_index, np.int64)}
    columns = {}
    for key, ft in feats.items():
        if ft["dtype"] == "image":
            columns[key] = staged.column(key).combine_chunks()
        elif ft["dtype"] == "video":
            continue
        elif key in ("observation.state", "action"):
            columns[key] = _vectors(numeric[key], np.float32)
        else:
            columns[key] = pa.array(numeric[key])
    meta = {b"huggingface": json.dumps({"info": {"features": hf_features(feats)}})}
    return pa.table(columns).replace_schema_metadata(meta), numeric


def select_staged(staging: Path, tasks: Sequence[str], demos: int) -> list[tuple[str, int, Path]]:
    """The staged demos of the selection, in dataset order (tasks' order, then demo)."""
    return [(t, i, staged_path(staging, t, i)) for t in tasks for i in range(demos)
            if is_staged(staged_path(staging, t, i))]


def _fingerprint(chosen, layout: Layout, look: dict | None = None) -> dict:
    eps = []
    for task, i, path in chosen:
        st = path.stat()
        eps.append([task, i, st.st_size, st.st_mtime_ns])
    return {"layout": asdict(layout), "episodes": eps, **({"look": look} if look else {})}


def check_out(out: Path) -> None:
    """Refuse to replace a directory that is not one of our datasets."""
    if not out.exists():
        return
    ours = (out / PROVENANCE).exists() or (out / ".old" / PROVENANCE).exists()
    names = {p.name for p in out.iterdir()} - {".build", ".old"}
    if names and not ours:
        raise ValueError(f"{out} is not empty and not an agnostos_mjx LeRobot export "
                         f"(no {PROVENANCE}); choose another --out")


def assemble(out: Path, staging: Path, tasks: Sequence[str], demos: int,
             layout: Layout, look: dict | None = None) -> dict:
    """Write the LeRobot dataset `out` from the staged demos of `tasks` x `demos`; returns
    {"episodes", "frames", "tasks", "skipped": True when already assembled as asked}.
    `look`: the staged images' renderer and scene version (data/look.py), recorded in
    info.json under "agnostos"."""
    import pyarrow.parquet as pq

    out, staging = Path(out), Path(staging)
    chosen = select_staged(staging, tasks, demos)
    if not chosen:
        raise ValueError(f"no staged demos of {', '.join(tasks)} in {staging}")
    fingerprint = _fingerprint(chosen, layout, look)
    prov = out / PROVENANCE
    if (out / "meta/info.json").exists() and prov.exists():
        old = json.loads(prov.read_text())
        if old.get("fingerprint") == fingerprint:
            return {"episodes": len(chosen), "frames": old.get("total_frames"),
                    "tasks": old.get("total_tasks"), "skipped": True}
    check_out(out)
    infos = [staged_info(p) for _, _, p in chosen]
    cameras, size = infos[0]["cameras"], infos[0]["size"]
    for (task, i, _), info in zip(chosen, infos):
        if info["cameras"] != cameras or info["size"] != size:
            raise ValueError(f"{task} demo {i} was staged with cameras {info['cameras']} at "
                             f"{info['size']} px, not {cameras} at {size} px")
    fps = _fps(infos)
    build = out / ".build"
    shutil.rmtree(build, ignore_errors=True)
    build.mkdir(parents=True)
    videos: dict = {}  # per camera: its video info (info.json)
    feats = features(cameras, size, size, layout.state, layout.rotation,
                     video_info={"pending": True} if layout.video else None)
    instructions = list(dict.fromkeys(i["instruction"] for i in infos))
    task_index = {s: k for k, s in enumerate(instructions)}
    v30 = layout.version == "v3.0"
    writer, chunk, file_index, file_bytes = None, 0, 0, 0
    episodes, ep_stats, numeric_all = [], [], {}
    hist_all = {cam: np.zeros((3, 256), np.int64) for cam in cameras}
    total = 0
    try:
        for ep, ((task, demo, path), info) in enumerate(zip(chosen, infos)):
            staged = pq.read_table(path)
            n = staged.num_rows
            table, numeric = _episode_table(staged, feats, layout, total, ep,
                                            task_index[info["instruction"]], fps)
            row = {"episode_index": ep, "tasks": [info["instruction"]], "length": n}
            if v30:
                if writer is not None and file_bytes + table.nbytes > DATA_FILE_MB * 2**20:
                    writer.close()
                    writer, file_bytes = None, 0
                    chunk, file_index = ((chunk + 1, 0) if file_index == CHUNKS_SIZE - 1
                                         else (chunk, file_index + 1))
                if writer is None:
                    dest = build / V30_DATA_PATH.format(chunk_index=chunk, file_index=file_index)
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    writer = pq.ParquetWriter(dest, table.schema, compression="snappy")
                writer.write_table(table)  # one row group per episode
                file_bytes += table.nbytes
                row.update({"data/chunk_index": chunk, "data/file_index": file_index,
                            "dataset_from_index": total, "dataset_to_index": total + n})
            else:
                dest = build / V21_DATA_PATH.format(episode_chunk=ep // CHUNKS_SIZE,
                                                    episode_index=ep)
                dest.parent.mkdir(parents=True, exist_ok=True)
                pq.write_table(table, dest, compression="snappy")
            stats = {}
            for cam in cameras:
                key = IMAGE_PREFIX + cam
                hist = np.asarray(info["histograms"][cam], np.int64)
                hist_all[cam] += hist
                stats[key] = histogram_stats(hist, n)
                if layout.video:
                    vpath = (build / V30_VIDEO_PATH.format(video_key=key, chunk_index=ep // CHUNKS_SIZE,
                                                           file_index=ep % CHUNKS_SIZE)
                             if v30 else build / V21_VIDEO_PATH.format(
                                 episode_chunk=ep // CHUNKS_SIZE, video_key=key, episode_index=ep))
                    encode_video(vpath, decode_png_column(staged.column(key)), fps)
                    videos.setdefault(key, video_info(vpath, fps, layout.version))
                    if v30:
                        row.update({f"videos/{key}/chunk_index": ep // CHUNKS_SIZE,
                                    f"videos/{key}/file_index": ep % CHUNKS_SIZE,
                                    f"videos/{key}/from_timestamp": 0.0,
                                    f"videos/{key}/to_timestamp": n / fps})
            for key, values in numeric.items():
                stats[key] = vector_stats(values)
                numeric_all.setdefault(key, []).append(values)
            stats = {k: stats[k] for k in feats}  # feature order
            ep_stats.append(stats)
            episodes.append({**row, "task": task, "demo": demo})
            total += n
    finally:
        if writer is not None:
            writer.close()
    for key, value in videos.items():
        feats[key]["info"] = value
    stats = {}
    for key in feats:
        if key.startswith(IMAGE_PREFIX):
            stats[key] = histogram_stats(hist_all[key[len(IMAGE_PREFIX):]], total)
        else:
            stats[key] = vector_stats(np.concatenate(numeric_all[key]))
    meta = build / "meta"
    _write_json(meta / "stats.json", jsonable(stats))
    if v30:
        _write_v30_meta(build, episodes, ep_stats, instructions)
        info = {"codebase_version": "v3.0", "fps": fps, "features": feats,
                "total_episodes": len(episodes), "total_frames": total,
                "total_tasks": len(instructions), "chunks_size": CHUNKS_SIZE,
                "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB,
                "data_path": V30_DATA_PATH, "video_path": V30_VIDEO_PATH if layout.video else None,
                "robot_type": ROBOT_TYPE, "splits": {"train": f"0:{len(episodes)}"}}
    else:
        _write_jsonl(meta / "episodes.jsonl", [{k: e[k] for k in ("episode_index", "tasks", "length")}
                                               for e in episodes])
        _write_jsonl(meta / "tasks.jsonl", [{"task_index": k, "task": s}
                                            for k, s in enumerate(instructions)])
        _write_jsonl(meta / "episodes_stats.jsonl", [
            {"episode_index": e["episode_index"],
             "stats": jsonable(s)}
            for e, s in zip(episodes, ep_stats)])
        info = {"codebase_version": "v2.1", "robot_type": ROBOT_TYPE,
                "total_episodes": len(episodes), "total_frames": total,
                "total_tasks": len(instructions),
                "total_videos": len(episodes) * len(cameras) if layout.video else 0,
                "total_chunks": -(-len(episodes) // CHUNKS_SIZE), "chunks_size": CHUNKS_SIZE,
                "fps": fps, "splits": {"train": f"0:{len(episodes)}"},
                "data_path": V21_DATA_PATH, "video_path": V21_VIDEO_PATH if layout.video else None,
                "features": feats}
    if look:
        info[LOOK_KEY] = look
    frames_doc = ("keyframes" if infos[0].get("frame_period_s") is None else
                  f"dense: every {infos[0].get('every_steps')} physics steps")
    _write_json(build / PROVENANCE, {
        "generator": "python -m agnostos_mjx.data.export --format lerobot",
        "fingerprint": fingerprint, "total_frames": total, "total_tasks": len(instructions),
        "layout": asdict(layout), "state": STATE_DOCS[layout.state],
        "action": f"x y z (world frame, m) + {ROTATION_DOCS[layout.rotation]} + gripper "
                  f"open amount in [0, 1]",
        "frames": frames_doc, "fps": fps, "cameras": cameras, "size": size,
        "episodes": [{"episode_index": e["episode_index"], "task": e["task"], "demo": e["demo"],
                      "variation": i["variation"], "instruction": i["instruction"],
                      "keyframes": i["keyframes"]} for e, i in zip(episodes, infos)]})
    info_text = json.dumps(info, indent=4, ensure_ascii=False) + "\n"
    _swap_in(out, build, info_text)
    return {"episodes": len(episodes), "frames": total, "tasks": len(instructions),
            "skipped": False}


def _write_v30_meta(build: Path, episodes: list[dict], ep_stats: list[dict],
                    instructions: list[str]) -> None:
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    tasks = pd.DataFrame({"task_index": np.arange(len(instructions), dtype=np.int64)},
                         index=pd.Index(instructions, name="task"))
    tasks.to_parquet(build / "meta/tasks.parquet")
    rows = []
    for e, stats in zip(episodes, ep_stats):
        row = {k: v for k, v in e.items() if k not in ("task", "demo")}
        for f, s in stats.items():
            row.update({f"stats/{f}/{k}": np.asarray(s[k]).tolist() for k in STAT_KEYS})
        row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
        rows.append(row)
    dest = build / V30_EPISODES_PATH.format(chunk_index=0, file_index=0)
    dest.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(rows), dest, compression="snappy")


def _swap_in(out: Path, build: Path, info_text: str) -> None:
    """Move the built data/, videos/ and meta/ into `out`; out's meta/info.json goes
    first and comes back last, so a dataset interrupted here is never taken as whole."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "meta/info.json").unlink(missing_ok=True)
    old = out / ".old"
    shutil.rmtree(old, ignore_errors=True)
    old.mkdir()
    for name in ("data", "videos", "meta"):
        if (out / name).exists():
            (out / name).rename(old / name)
        if (build / name).exists():
            (build / name).rename(out / name)
    tmp = out / "meta" / ".info.json.partial"
    tmp.write_text(info_text)
    os.replace(tmp, out / "meta/info.json")
    shutil.rmtree(old, ignore_errors=True)
    shutil.rmtree(build, ignore_errors=True)
