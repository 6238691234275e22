"""Reading a LeRobot dataset (v3.0 or v2.1, as data/lerobot.py writes them) with pyarrow,
pandas and Pillow (PyAV for video features): :func:`read_lerobot`.  Checks as it reads
that the parquet columns are info.json's features (dtypes, shapes), that the rows are in
dataset order and that the metadata files agree with the data."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from agnostos_mjx.data.lerobot_layout import DEFAULT_FEATURES
from agnostos_mjx.data.lerobot_video import decode_video

_ARROW_DTYPES = {"float32": "float", "float64": "double", "int64": "int64", "bool": "bool"}


class LeRobotFormatError(ValueError):
    """The dataset does not match its own metadata."""


def _decode_png(value: dict) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(value["bytes"])).convert("RGB"))


def _check_column(key: str, ft: dict, column) -> None:
    import pyarrow as pa

    t = column.type
    if ft["dtype"] == "image":
        ok = pa.types.is_struct(t) and {t.field(i).name for i in range(t.num_fields)} == {
            "bytes", "path"}
    elif list(ft["shape"]) == [1]:
        ok = str(t) == _ARROW_DTYPES.get(ft["dtype"], ft["dtype"])
    else:  # fixed-size lists as we write them; LeRobot's v2.1->v3.0 converter writes
        # variable-length lists (their lengths are checked row by row below)
        ok = ((pa.types.is_fixed_size_list(t) and t.list_size == ft["shape"][0])
              or pa.types.is_list(t) or pa.types.is_large_list(t)) \
            and str(t.value_type) == _ARROW_DTYPES.get(ft["dtype"], ft["dtype"])
    if not ok:
        raise LeRobotFormatError(f"column {key!r} has type {t}, not the feature {ft}")
    names = ft.get("names")
    if ft["dtype"] not in ("image", "video") and names is not None and len(names) != ft["shape"][0]:
        raise LeRobotFormatError(f"feature {key!r}: {len(names)} names for shape {ft['shape']}")


def _data_files(root: Path, info: dict) -> list[Path]:
    files = sorted((root / "data").glob("*/*.parquet"))
    if not files:
        raise LeRobotFormatError(f"no parquet files under {root / 'data'}")
    return files


def _meta(root: Path, info: dict) -> tuple[list[str], list[dict]]:
    """(tasks by task_index, episode rows) from either version's metadata."""
    if info["codebase_version"] == "v3.0":
        import pandas as pd
        import pyarrow.parquet as pq

        tasks_df = pd.read_parquet(root / "meta/tasks.parquet")
        tasks = [None] * len(tasks_df)
        for task, idx in zip(tasks_df.index, tasks_df["task_index"]):
            tasks[int(idx)] = str(task)
        files = sorted((root / "meta/episodes").glob("*/*.parquet"))
        rows = [r for f in files for r in pq.read_table(f).to_pylist()]
        episodes = [{k: v for k, v in r.items() if not k.startswith("stats/")} for r in rows]
        for e, r in zip(episodes, rows):
            e["stats"] = {}
            for k, v in r.items():
                if k.startswith("stats/"):
                    feat, stat = k[len("stats/"):].rsplit("/", 1)
                    e["stats"].setdefault(feat, {})[stat] = np.asarray(v)
        return tasks, episodes
    lines = lambda name: [json.loads(x) for x in (root / "meta" / name).read_text()  # noqa: E731
                          .splitlines() if x.strip()]
    tasks = [t["task"] for t in sorted(lines("tasks.jsonl"), key=lambda t: t["task_index"])]
    episodes = sorted(lines("episodes.jsonl"), key=lambda e: e["episode_index"])
    stats = {s["episode_index"]: s["stats"] for s in lines("episodes_stats.jsonl")}
    for e in episodes:
        e["stats"] = {f: {k: np.asarray(v) for k, v in s.items()}
                      for f, s in stats[e["episode_index"]].items()}
    return tasks, episodes


def read_lerobot(root: Path, decode: bool = True) -> dict:
    """A LeRobot dataset -> {"info", "stats", "tasks" (by task_index), "episodes" (metadata
    rows, with their "stats"), "frames"}: one dict per row in dataset order with every
    feature (images uint8 (H, W, 3) when `decode`, from PNG or the episode's MP4;
    vectors float32 arrays; scalars Python numbers) and "task" (the string).  Raises
    LeRobotFormatError where data and metadata disagree."""
    import pyarrow.parquet as pq

    root = Path(root)
    info = json.loads((root / "meta/info.json").read_text())
    version = info.get("codebase_version")
    if version not in ("v3.0", "v2.1"):
        raise LeRobotFormatError(f"codebase_version {version!r}: only v3.0 and v2.1 are read")
    feats = info["features"]
    for key, ft in DEFAULT_FEATURES.items():
        # Keys beyond LeRobot's own (the converter adds a per-feature "fps") are ignored.
        if {k: v for k, v in feats.get(key, {}).items() if k in ft} != ft:
            raise LeRobotFormatError(f"feature {key!r} is {feats.get(key)}, not LeRobot's {ft}")
    stats = json.loads((root / "meta/stats.json").read_text())
    tasks, episodes = _meta(root, info)
    columns = [k for k, ft in feats.items() if ft["dtype"] != "video"]
    frames: list[dict] = []
    for path in _data_files(root, info):
        table = pq.read_table(path)
        if table.column_names != columns:
            raise LeRobotFormatError(f"{path}: columns {table.column_names}, features {columns}")
        if b"huggingface" not in (table.schema.metadata or {}):
            raise LeRobotFormatError(f"{path}: no Hugging Face schema metadata")
        for key in columns:
            _check_column(key, feats[key], table.column(key))
        for row in table.to_pylist():
            for key in columns:
                ft = feats[key]
                if ft["dtype"] == "image":
                    row[key] = _decode_png(row[key]) if decode else row[key]["bytes"]
                elif list(ft["shape"]) != [1]:
                    row[key] = np.asarray(row[key], ft["dtype"])
                    if row[key].shape != tuple(ft["shape"]):
                        raise LeRobotFormatError(f"{path}: {key} of shape {row[key].shape}, "
                                                 f"not the feature's {ft['shape']}")
            row["task"] = tasks[row["task_index"]]
            frames.append(row)
    if [f["index"] for f in frames] != list(range(len(frames))):
        raise LeRobotFormatError("data rows are not in dataset order (index 0..N-1)")
    start = 0
    for e in episodes:
        rows = frames[start: start + e["length"]]
        if ({f["episode_index"] for f in rows} != {e["episode_index"]}
                or [f["frame_index"] for f in rows] != list(range(e["length"]))
                or [f["task"] for f in rows][:1] != list(e["tasks"])[:1]):
            raise LeRobotFormatError(f"episode {e['episode_index']}: rows disagree with "
                                     f"the episode metadata")
        if version == "v3.0" and (e["dataset_from_index"], e["dataset_to_index"]) != (
                start, start + e["length"]):
            raise LeRobotFormatError(f"episode {e['episode_index']}: dataset_from/to_index")
        start += e["length"]
    if start != len(frames) or len(frames) != info["total_frames"] or len(episodes) != info[
            "total_episodes"] or len(tasks) != info["total_tasks"]:
        raise LeRobotFormatError("info.json totals disagree with the data")
    videos = [k for k, ft in feats.items() if ft["dtype"] == "video"]
    if videos and decode:
        start = 0
        for e in episodes:
            ep = e["episode_index"]
            for key in videos:
                if version == "v3.0":
                    rel = info["video_path"].format(video_key=key,
                                                    chunk_index=e[f"videos/{key}/chunk_index"],
                                                    file_index=e[f"videos/{key}/file_index"])
                else:
                    rel = info["video_path"].format(episode_chunk=ep // info["chunks_size"],
                                                    video_key=key, episode_index=ep)
                images = decode_video(root / rel)
                if len(images) != e["length"]:
                    raise LeRobotFormatError(f"{rel}: {len(images)} frames, episode has "
                                             f"{e['length']}")
                for f, im in zip(frames[start: start + e["length"]], images):
                    f[key] = im
            start += e["length"]
    return {"info": info, "stats": stats, "tasks": tasks, "episodes": episodes,
            "frames": frames}
