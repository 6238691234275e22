"""Keyframe training data for the reference VLA: ``python -m agnostos_mjx.train.vla_data``.

The same demos as the export (``data.export``: the demo bank's keys, variation ``i % n``,
failed placements re-sampled) run through the same expert loop with observations
(``data.expert_frames.episode_observations``), but kept as arrays instead of RLBench's PNG
folders: the model reads RGB and world-frame point clouds of a few cameras, and decoding
tens of thousands of PNGs would cost more than rendering them.  Work is split into chunks
of demos (not whole tasks, as the export's ``--workers``), so 16 processes finish together
even though place_cups and stack_blocks take 3x as long per demo as the rest.

One ``<task>_<first demo>.npz`` per chunk; per sample (the scene before the expert's k-th
key action of a successful demo): ``rgb`` (N, C, H, W, 3) uint8, ``points`` (N, C, H, W, 3)
float16 (world frame, metres), ``gripper_pose`` (N, 7: x y z qx qy qz qw), ``gripper_open``
(N,), ``step`` (N,) the key-action index k, ``demo`` and ``variation`` (N,), the targets
``target_pos`` (N, 3), ``target_quat`` (N, 4, w first) and ``target_gripper`` (N,): the
expert's k-th key action as the evaluator executes it; and the chunk's ``task``, ``cameras``
and ``descriptions`` (JSON: variation -> the task's instructions).  ``manifest.json`` holds
the settings; a rerun with the same settings skips finished chunks.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from agnostos_mjx.infra.settings import configure_jax

DEFAULT_CAMERAS = ("front", "left_shoulder", "right_shoulder", "wrist")
FORMAT = "agnostos-vla-keyframes-1"


@dataclass(frozen=True)
class DataConfig:
    out: Path
    tasks: tuple[str, ...]
    demos: int = 100
    cameras: tuple[str, ...] = DEFAULT_CAMERAS
    size: int = 96
    seed: int = 0
    chunk: int = 25  # demos per job (and per batch of worlds)
    max_attempts: int = 10

    def __post_init__(self) -> None:
        from agnostos_mjx.runtime.observation import CAMERAS

        bad = [c for c in self.cameras if c not in CAMERAS]
        if bad or not self.cameras:
            raise ValueError(f"unknown cameras {bad}; choose from {', '.join(CAMERAS)}")
        if self.demos < 1 or self.size < 8 or self.chunk < 1:
            raise ValueError("demos and chunk must be >= 1 and size >= 8")

    def settings(self) -> dict:
        d = asdict(self)
        d.pop("out")
        d.pop("tasks")
        return {**{k: list(v) if isinstance(v, tuple) else v for k, v in d.items()},
                "format": FORMAT}

    def jobs(self) -> list[tuple[str, int, int]]:
        """(task, first demo, end demo) chunks, longest tasks' chunks first."""
        return [(t, s, min(s + self.chunk, self.demos)) for t in self.tasks
                for s in range(0, self.demos, self.chunk)]

    def chunk_path(self, task: str, start: int) -> Path:
        return self.out / f"{task}_{start:05d}.npz"


_RUNNER: dict = {}  # this process's runner: {(task, threads): Episodes}, one at a time


def _episodes(task_name: str, threads: int | None):
    """This process's native runner for `task_name`: a worker that gets several chunks of a
    task in a row builds its scene and compiles once.  When the worker moves to another
    task the old runner is closed first, so a process holds one renderer (GL context) at a
    time: on a GPU host's NVIDIA EGL a worker's second live renderer failed to get a
    framebuffer ("Offscreen framebuffer is not complete", 16 workers)."""
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    key = (task_name, threads)
    if key not in _RUNNER:
        for old in _RUNNER.values():
            old.close()
        _RUNNER.clear()
        _RUNNER[key] = Episodes(get_task(task_name), "native", threads=threads)
    return _RUNNER[key]


def generate_chunk(cfg: DataConfig, task_name: str, start: int, stop: int,
                   threads: int | None = None) -> dict:
    """Run the expert on demos start..stop-1 of one task and save their keyframe samples."""
    from agnostos_mjx.data.expert_frames import episode_observations
    from agnostos_mjx.data.generate import demo_keys
    from agnostos_mjx.runtime.observation import ObservationSpec
    from agnostos_mjx.runtime.outcome import Outcome

    t0 = time.perf_counter()
    path = cfg.chunk_path(task_name, start)
    if path.exists():
        return {"task": task_name, "start": start, "skipped": True, "seconds": 0.0}
    episodes = _episodes(task_name, threads)
    task = episodes.task
    spec = ObservationSpec(cameras=cfg.cameras, height=cfg.size, width=cfg.size,
                           modalities=("rgb", "point_cloud"), renderer="cpu")
    todo = list(range(start, stop))
    attempts = {i: 0 for i in todo}
    samples: dict[str, list] = {k: [] for k in (
        "rgb", "points", "gripper_pose", "gripper_open", "step", "demo", "variation",
        "target_pos", "target_quat", "target_gripper")}
    failed = 0
    while todo:
        batch = np.array(todo)
        keys = demo_keys(cfg.seed, task.name, batch, np.array([attempts[i] for i in batch]))
        variations = (batch % task.num_variations).astype(np.int32)
        env = episodes.reset(keys, variations, stop_at_success=False)
        actions = episodes.expert_actions(env)
        env, frames, _ = episode_observations(episodes, env, spec)
        for w, index in enumerate(batch.tolist()):
            if env.outcome[w] != Outcome.SUCCESS:
                attempts[index] += 1
                failed += 1
                if attempts[index] >= cfg.max_attempts:
                    todo.remove(index)
                continue
            todo.remove(index)
            for k, frame in enumerate(frames[w][:-1]):  # the last frame has no next action
                samples["rgb"].append(np.stack([frame[f"{c}_rgb"] for c in cfg.cameras]))
                samples["points"].append(np.stack(
                    [frame[f"{c}_point_cloud"] for c in cfg.cameras]).astype(np.float16))
                samples["gripper_pose"].append(np.asarray(frame["gripper_pose"], np.float32))
                samples["gripper_open"].append(np.float32(frame["gripper_open"]))
                samples["step"].append(k)
                samples["demo"].append(index)
                samples["variation"].append(int(variations[w]))
                samples["target_pos"].append(np.asarray(actions.pos[w, k], np.float32))
                samples["target_quat"].append(np.asarray(actions.quat[w, k], np.float32))
                samples["target_gripper"].append(np.float32(actions.gripper[w, k]))
    if not samples["step"]:
        raise RuntimeError(f"{task_name}: no successful demo among {start}..{stop - 1}")
    arrays = {k: np.stack(v) if k in ("rgb", "points", "gripper_pose", "target_pos",
                                      "target_quat") else np.asarray(v)
              for k, v in samples.items()}
    descriptions = {v: task.descriptions(v) for v in range(task.num_variations)}
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **arrays, task=task_name, cameras=np.array(cfg.cameras),
             descriptions=json.dumps(descriptions))
    tmp.replace(path)
    return {"task": task_name, "start": start, "samples": len(arrays["step"]),
            "failed": failed, "skipped": False, "seconds": time.perf_counter() - t0}


def generate(cfg: DataConfig, workers: int = 1) -> dict:
    """Every chunk of `cfg`, `workers` at once (spawned processes, as the export's)."""
    from agnostos_mjx.data.export_run import _worker_env, _worker_init
    from agnostos_mjx.infra.settings import usable_cores

    cfg.out.mkdir(parents=True, exist_ok=True)
    manifest_path = cfg.out / "manifest.json"
    if manifest_path.exists():
        old = json.loads(manifest_path.read_text())["settings"]
        if old != cfg.settings():
            raise ValueError(f"{cfg.out} holds data made with {old}, not {cfg.settings()}")
    manifest_path.write_text(json.dumps({"settings": cfg.settings(),
                                         "tasks": list(cfg.tasks)}, indent=1) + "\n")
    jobs = cfg.jobs()
    t0 = time.perf_counter()
    done: list[dict] = []

    def report(stats: dict) -> None:
        done.append(stats)
        if not stats["skipped"]:
            print(f"vla_data: {stats['task']} demos {stats['start']}+: {stats['samples']} "
                  f"samples in {stats['seconds']:.1f} s [{len(done)}/{len(jobs)}]", flush=True)

    workers = max(1, min(int(workers), len(jobs), usable_cores()))
    if workers == 1:
        for job in jobs:
            report(generate_chunk(cfg, *job))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        threads = max(1, usable_cores() // workers)
        # Long tasks first, so that the pool does not end waiting on one of them.
        order = sorted(jobs, key=lambda j: j[0] not in ("place_cups", "stack_blocks",
                                                        "put_item_in_drawer", "stack_cups"))
        with _worker_env(threads, "cpu"), ProcessPoolExecutor(
                workers, multiprocessing.get_context("spawn"), initializer=_worker_init) as pool:
            futures = [pool.submit(generate_chunk, cfg, *job, threads) for job in order]
            for fut in as_completed(futures):
                report(fut.result())
    wall = time.perf_counter() - t0
    samples = sum(s.get("samples", 0) for s in done if not s["skipped"])
    print(f"vla_data: {len(jobs)} chunks ({samples} new samples) in {wall:.1f} s -> {cfg.out}",
          flush=True)
    return {"chunks": len(jobs), "new_samples": samples, "seconds": wall}


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    from agnostos_mjx.tasks import parse_tasks

    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.train.vla_data",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="data directory (chunks + manifest)")
    p.add_argument("--tasks", default="seen", help="task names and/or split names")
    p.add_argument("--demos", type=int, default=100, help="demos per task")
    p.add_argument("--cameras", default=",".join(DEFAULT_CAMERAS))
    p.add_argument("--size", type=int, default=96, help="image side in pixels")
    p.add_argument("--seed", type=int, default=0, help="demo seed (the bank's and export's)")
    p.add_argument("--chunk", type=int, default=25, help="demos per job")
    p.add_argument("--workers", type=int, default=1, help="processes")
    args = p.parse_args(argv)
    try:
        tasks = tuple(t.name for t in parse_tasks(args.tasks))
        cfg = DataConfig(args.out, tasks, args.demos, tuple(args.cameras.split(",")),
                         args.size, args.seed, args.chunk)
    except (KeyError, ValueError) as err:
        p.error(str(err))
    try:
        generate(cfg, args.workers)
    except ValueError as err:
        print(f"vla_data: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
