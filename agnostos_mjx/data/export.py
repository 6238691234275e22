"""Seen-task demos with observations as VLA training data: ``python -m agnostos_mjx.data.export``.

Format: RLBench's per-episode folders, as PerAct, RVT and RVT-2 read them (LeRobot's format
is not written: ``lerobot`` pulls in torch and could not be checked here)::

    <out>/<task>/all_variations/episodes/episode<i>/
        <camera>_rgb/<k>.png      RGB
        <camera>_depth/<k>.png    depth, RLBench's encoding: (d - near) / (far - near) as a
                                  24-bit integer in R (low byte), G, B (high byte)
        <camera>_mask/<k>.png     segmentation, geom id + 1 as a 24-bit integer the same way
                                  (0: nothing), RLBench's handle encoding
        low_dim_obs.npz           per frame k: gripper_pose (x y z qx qy qz qw),
                                  gripper_open, joint_positions, joint_velocities,
                                  gripper_joint_positions, <camera>_camera_{intrinsics,
                                  extrinsics,near,far}, key_action (the action after frame k:
                                  the next frame's gripper pose and open flag)
        variation_descriptions.pkl, variation_number.pkl   as RLBench (plain pickles)
        SHA256SUMS                checksums of the files above (written last: the marker
                                  that the episode is complete)
    <out>/manifest.json           settings, segmentation names per task, episode counts

Frames are the keyframes: the scene after reset and after every expert key action (our
experts act in RLBench's waypoints, which PerAct's keyframe discovery recovers).  RLBench
pickles ``low_dim_obs.pkl`` as rlbench ``Demo`` objects; without rlbench we store the same
fields as npz, and :func:`read_episode` reads an episode back (a converter to rlbench's
pickle is a few lines with rlbench installed: build ``Observation``s from these arrays).

Demos are the demo bank's (same keys: ``generate.demo_keys``, variation ``i % n``), re-run
with observations.  Resumable: complete episodes are skipped, an interrupted one is redone.
A size and time estimate is printed before work starts.

Examples::

    python -m agnostos_mjx.data.export --out data/peract --tasks seen --demos 200
    python -m agnostos_mjx.data.export --out /tmp/x --tasks open_drawer --demos 2 --size 64
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import pickle
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger("agnostos_mjx.data.export")
PERACT_CAMERAS = ("front", "left_shoulder", "right_shoulder", "wrist")
DEPTH_SCALE = 2**24 - 1  # RLBench's DEPTH_SCALE
SUMS = "SHA256SUMS"
# Measured (open_drawer, stack_blocks at 128 px): bytes per camera-frame of the 3 PNGs.
BYTES_PER_CAMERA_FRAME_128 = 30_000
CPU_CAMERA_FRAMES_PER_S = 15.0  # export incl. physics, 2 shared cores (8 demos: 10/s at batch 4)


@dataclass(frozen=True)
class ExportConfig:
    out: Path
    tasks: tuple[str, ...]
    demos: int = 200
    seed: int = 0
    cameras: tuple[str, ...] = PERACT_CAMERAS
    size: int = 128
    batch: int = 25
    max_attempts: int = 10


# ---- RLBench image encodings (pure) --------------------------------------------------------
def int_to_rgb(values: np.ndarray) -> np.ndarray:
    """Non-negative integers < 2^24 -> uint8 RGB (R low byte), RLBench's encoding."""
    v = np.asarray(values, np.int64)
    return np.stack([v & 255, (v >> 8) & 255, (v >> 16) & 255], -1).astype(np.uint8)


def rgb_to_int(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, np.int64)
    return rgb[..., 0] | (rgb[..., 1] << 8) | (rgb[..., 2] << 16)


def encode_depth(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """Metres -> RLBench depth PNG pixels."""
    unit = np.clip((np.asarray(depth, np.float64) - near) / (far - near), 0.0, 1.0)
    return int_to_rgb(np.round(unit * DEPTH_SCALE))


def decode_depth(rgb: np.ndarray, near: float, far: float) -> np.ndarray:
    """RLBench depth PNG pixels -> metres."""
    return (near + rgb_to_int(rgb) / DEPTH_SCALE * (far - near)).astype(np.float32)


# ---- writing ---------------------------------------------------------------------------------
def _png(path: Path, img: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(img)).save(path, compress_level=1)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def episode_dir(out: Path, task: str, index: int) -> Path:
    return out / task / "all_variations" / "episodes" / f"episode{index}"


def is_complete(path: Path) -> bool:
    return (path / SUMS).exists()


def write_episode(path: Path, frames: list[dict], description: list[str], variation: int) -> None:
    """One demo's frames (RLBenchObservation.world dicts) -> an episode folder, atomically."""
    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    cameras = [k[: -len("_camera_near")] for k in frames[0]["misc"] if k.endswith("_camera_near")]
    low: dict[str, list] = {}
    for k, f in enumerate(frames):
        for cam in cameras:
            near, far = f["misc"][f"{cam}_camera_near"], f["misc"][f"{cam}_camera_far"]
            images = {"rgb": f.get(f"{cam}_rgb")}
            if f.get(f"{cam}_depth") is not None:
                images["depth"] = encode_depth(f[f"{cam}_depth"], near, far)
            if f.get(f"{cam}_mask") is not None:
                images["mask"] = int_to_rgb(f[f"{cam}_mask"] + 1)
            for kind, img in images.items():
                if img is not None:
                    (tmp / f"{cam}_{kind}").mkdir(exist_ok=True)
                    _png(tmp / f"{cam}_{kind}" / f"{k}.png", img)
            for key in ("intrinsics", "extrinsics", "near", "far"):
                low.setdefault(f"{cam}_camera_{key}", []).append(f["misc"][f"{cam}_camera_{key}"])
        for key in ("gripper_pose", "gripper_open", "joint_positions", "joint_velocities",
                    "gripper_joint_positions"):
            low.setdefault(key, []).append(f[key])
    arrays = {k: np.asarray(v) for k, v in low.items()}
    nxt = np.concatenate([arrays["gripper_pose"][1:], arrays["gripper_pose"][-1:]])
    opened = np.concatenate([arrays["gripper_open"][1:], arrays["gripper_open"][-1:]])
    arrays["key_action"] = np.concatenate([nxt, opened[:, None]], 1).astype(np.float32)
    np.savez_compressed(tmp / "low_dim_obs.npz", **arrays)
    (tmp / "variation_descriptions.pkl").write_bytes(pickle.dumps(list(description)))
    (tmp / "variation_number.pkl").write_bytes(pickle.dumps(int(variation)))
    files = sorted(p for p in tmp.rglob("*") if p.is_file())
    sums = "".join(f"{_sha256(p)}  {p.relative_to(tmp)}\n" for p in files)
    (tmp / SUMS).write_text(sums)
    shutil.rmtree(path, ignore_errors=True)
    tmp.rename(path)


def verify_episode(path: Path) -> None:
    """Raise ValueError naming the first file whose checksum does not match."""
    for line in (path / SUMS).read_text().splitlines():
        digest, name = line.split("  ", 1)
        if _sha256(path / name) != digest:
            raise ValueError(f"checksum mismatch: {path / name}")


def read_episode(path: Path, verify: bool = True) -> dict:
    """An exported episode -> {"low_dim": {...}, "<cam>_rgb"/"_depth" (metres)/"_mask"
    (geom id, -1 none): (T, H, W[, 3]) arrays, "descriptions", "variation"}."""
    from PIL import Image

    path = Path(path)
    if verify:
        verify_episode(path)
    low = dict(np.load(path / "low_dim_obs.npz"))
    out: dict = {"low_dim": low,
                 "descriptions": pickle.loads((path / "variation_descriptions.pkl").read_bytes()),
                 "variation": pickle.loads((path / "variation_number.pkl").read_bytes())}
    n = len(low["gripper_pose"])
    for folder in sorted(p for p in path.iterdir() if p.is_dir()):
        cam, kind = folder.name.rsplit("_", 1)
        imgs = np.stack([np.asarray(Image.open(folder / f"{k}.png")) for k in range(n)])
        if kind == "depth":
            imgs = np.stack([decode_depth(im, float(low[f"{cam}_camera_near"][k]),
                                          float(low[f"{cam}_camera_far"][k]))
                             for k, im in enumerate(imgs)])
        elif kind == "mask":
            imgs = (rgb_to_int(imgs) - 1).astype(np.int32)
        out[folder.name] = imgs
    return out


# ---- running the experts ---------------------------------------------------------------------
def keyframe_observations(episodes, env, spec) -> tuple[object, list[list[dict]]]:
    """Run the expert; per world the observation after reset and after each key action."""
    from agnostos_mjx.observation import observe

    frames: list[list[dict]] = [[] for _ in range(len(env.variation))]

    def snap(obs, worlds):
        for w in worlds:
            frames[w].append(obs.world(int(w)))

    snap(observe(episodes, env, spec), range(len(frames)))
    import jax

    actions = episodes.expert_actions(env)
    for k in range(actions.pos.shape[1]):
        step = jax.tree.map(lambda x, k=k: x[:, k], actions)
        running = ~env.done & np.asarray(step.valid, bool)
        if not running.any():
            break
        env, _ = episodes.step(env, step)
        snap(observe(episodes, env, spec), np.nonzero(running)[0])
    return env, frames


def export_task(cfg: ExportConfig, task_name: str) -> dict:
    """Export one task's missing demos; returns counts."""
    from agnostos_mjx.data.generate import demo_keys
    from agnostos_mjx.episode import Episodes, Outcome
    from agnostos_mjx.observation import MODALITIES, ObservationSpec, scene_labels
    from agnostos_mjx.tasks import get_task

    task = get_task(task_name)
    todo = [i for i in range(cfg.demos) if not is_complete(episode_dir(cfg.out, task.name, i))]
    stats = {"task": task.name, "skipped": cfg.demos - len(todo), "written": 0, "failed": 0}
    if not todo:
        return stats
    episodes = Episodes(task, "native")
    spec = ObservationSpec(cameras=cfg.cameras, height=cfg.size, width=cfg.size,
                           modalities=MODALITIES, renderer="cpu")
    stats["labels"] = {"geom_names": list(scene_labels(episodes.scene).geom_names),
                       "objects": {k: list(v) for k, v in
                                   scene_labels(episodes.scene).objects.items()}}
    attempts = {i: 0 for i in todo}
    while todo:
        batch = np.array(todo[: cfg.batch])
        keys = demo_keys(cfg.seed, task.name, batch, np.array([attempts[i] for i in batch]))
        variations = (batch % task.num_variations).astype(np.int32)
        env = episodes.reset(keys, variations, stop_at_success=False)
        env, frames = keyframe_observations(episodes, env, spec)
        for w, index in enumerate(batch):
            index = int(index)
            if env.outcome[w] == Outcome.SUCCESS:
                v = int(variations[w])
                write_episode(episode_dir(cfg.out, task.name, index), frames[w],
                              task.descriptions(v), v)
                stats["written"] += 1
                todo.remove(index)
            else:
                attempts[index] += 1
                stats["failed"] += 1
                if attempts[index] >= cfg.max_attempts:
                    log.warning("%s: demo %d failed %d attempts; skipped", task.name, index,
                                attempts[index])
                    todo.remove(index)
    return stats


def estimate(cfg: ExportConfig, frames_per_demo: float = 11.0) -> tuple[float, float]:
    """(bytes, seconds) to expect: a rough guide printed before starting."""
    camera_frames = len(cfg.tasks) * cfg.demos * frames_per_demo * len(cfg.cameras)
    size = camera_frames * BYTES_PER_CAMERA_FRAME_128 * (cfg.size / 128) ** 2
    return size, camera_frames / CPU_CAMERA_FRAMES_PER_S * (cfg.size / 128) ** 2


def export(cfg: ExportConfig) -> dict:
    cfg.out.mkdir(parents=True, exist_ok=True)
    size, seconds = estimate(cfg)
    print(f"export: {len(cfg.tasks)} tasks x {cfg.demos} demos, cameras {','.join(cfg.cameras)}"
          f" at {cfg.size}px: about {size / 1e9:.2f} GB and {seconds / 60:.0f} min on 2 CPU "
          f"cores (rough; complete episodes in {cfg.out} are skipped)", flush=True)
    t0 = time.perf_counter()
    manifest_path = cfg.out / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.exists() else {}
    # Settings that change what an episode holds must match between runs.
    config = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()
              if k in ("seed", "cameras", "size")}
    if manifest.get("config", config) != config:
        raise ValueError(f"{cfg.out} was exported with {manifest['config']}, not {config}")
    manifest["config"] = config
    manifest.setdefault("tasks", {})
    for name in cfg.tasks:
        stats = export_task(cfg, name)
        entry = manifest["tasks"].setdefault(name, {})
        entry.update({k: v for k, v in stats.items() if k == "labels"})
        entry["episodes"] = sum(is_complete(episode_dir(cfg.out, name, i))
                                for i in range(cfg.demos))
        log.info("%s: %d written, %d skipped, %d failed attempts", name, stats["written"],
                 stats["skipped"], stats["failed"])
        manifest_path.write_text(json.dumps(manifest, indent=1) + "\n")
    manifest["wall_s"] = round(time.perf_counter() - t0, 1)
    manifest_path.write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


def main(argv: Sequence[str] | None = None) -> int:
    from agnostos_mjx.cli import HelpFormatter, setup_logging
    from agnostos_mjx.tasks import parse_tasks

    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.data.export",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--tasks", default="seen", help="task names and/or split names")
    p.add_argument("--demos", type=int, default=200, help="demos per task")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cameras", default=",".join(PERACT_CAMERAS))
    p.add_argument("--size", type=int, default=128, help="image height and width")
    p.add_argument("--batch", type=int, default=25, help="worlds simulated at once")
    p.add_argument("--quiet", action="store_true")
    a = p.parse_args(argv)
    setup_logging(a.quiet)
    cfg = ExportConfig(out=Path(a.out), tasks=tuple(t.name for t in parse_tasks(a.tasks)),
                       demos=a.demos, seed=a.seed, cameras=tuple(a.cameras.split(",")),
                       size=a.size, batch=a.batch)
    manifest = export(cfg)
    print(f"done in {manifest['wall_s']:.0f} s: {cfg.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
