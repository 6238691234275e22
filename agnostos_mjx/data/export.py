"""Seen-task demos with observations as VLA training data: ``python -m agnostos_mjx.data.export``.

Formats: ``--format rlbench`` (default, below) and ``--format lerobot``: a LeRobot dataset
(v3.0, or v2.1 for openpi, with ``--lerobot-version``), written with pyarrow, pandas and
Pillow, no torch; its layout, ``--rotation``, ``--state`` and ``--video`` are described in
data/lerobot.py and data/lerobot_layout.py.  Both formats export the same demos, cameras
and sizes (``--size`` defaults to 128 for rlbench, 224 for lerobot).

RLBench: per-episode folders as its dataset generator (PerAct's fork, ``--all_variations``)
writes them, read as they are by ``rlbench.utils.get_stored_demos`` (PerAct, and RVT's
``peract_colab`` loader)::

    <out>/<task>/all_variations/episodes/episode<i>/
        <camera>_rgb/<k>.png      RGB
        <camera>_depth/<k>.png    depth, RLBench's encoding: (d - near) / (far - near) * (2^24 - 1)
                                  as a 24-bit integer, R the high byte, B the low byte
        <camera>_mask/<k>.png     segmentation, geom id + 1 as a 24-bit integer with R the LOW
                                  byte (RLBench's handle encoding; 0: nothing)
        low_dim_obs.pkl           RLBench's pickle: an ``rlbench.demo.Demo`` of
                                  ``rlbench.backend.observation.Observation``s, images None
                                  (written without rlbench: see data/rlbench_demo.py):
                                  gripper_pose (x y z qx qy qz qw), gripper_open (1.0/0.0),
                                  gripper_matrix, joint_positions, joint_velocities,
                                  gripper_joint_positions, task_low_dim_state (poses of the
                                  task's observed frames, then its joint positions),
                                  ignore_collisions (0), joint_forces and
                                  gripper_touch_forces (zeros: not simulated), misc with
                                  <camera>_camera_{extrinsics,intrinsics,near,far}
        variation_descriptions.pkl, variation_number.pkl   as RLBench (plain pickles: a
                                  list of str, an int)
        SHA256SUMS                checksums of every file above (written last: the marker
                                  that the episode is complete)
    <out>/manifest.json           settings, segmentation names per task, episode counts,
                                  and under "agnostos" the renderer and scene version that
                                  made the images (data/look.py)

Cameras: RLBench's five by default; ``get_stored_demos`` lists the rgb and depth folders of
all five even when its ObservationConfig asks for fewer, so a ``--cameras`` subset is only
for readers of our own (:func:`read_episode`, which needs no rlbench).  Upstream RLBench's
``get_stored_demos`` has no ``all_variations`` and reads ``<task>/variation<v>/episodes``:
symlink our episodes there.  Checked with these readers (images, depth, point clouds,
masks, poses against ours): ``python eval/reports/rlbench_reader_check/check.py
--reader-python <numpy 1.x python>``.

Frames: by default the keyframes only, the scene after reset and after every expert key
action (our experts act in RLBench's waypoints).  PerAct's ``keypoint_discovery`` heuristic
(PerAct's and RVT's replay filling: a keypoint where gripper_open changes or all joint
velocities fall below 0.1 rad/s), made for RLBench's dense demos, finds only some of them
(open_drawer: 2 of 5; figures in the reader check): use every frame after the first as a
keypoint, ``list(range(1, len(demo)))``.

``--every K`` adds dense frames as RLBench stores them (every simulation step, 50 ms):
the scene after every K-th physics step of each key action (counted from the action's
start, arm and gripper phases together), then the action's keyframe, so a key action of S
steps gives ceil(S / K) frames and the keyframes stay in the frame list, in order, once each.
``--every rlbench`` is RLBench's 20 Hz (K = 10 at our 5 ms timestep).  Dense frames are the
physics state of their step (no extra simulation: the native backend's rollout returns
every step), with that step's joint velocities, gripper and object poses.  A dense episode
also holds ``keyframes.json``, the indices of its keyframes (``read_episode``'s
"keyframes"; RLBench's readers ignore the file).  Cost: ~190 frames per seen-task demo
instead of ~8.7 (22x the images and bytes, ~10x the time; docs/performance.md).  PerAct's
heuristic on dense episodes (18 seen tasks x 1 demo; tests/test_export.py::test_dense_frames
for open_drawer):
116 of 122 key actions get a keypoint among their own frames, with the keyframe's gripper
state and within 3.3 mm and 0.4 deg of its gripper pose: the heuristic marks the first
frame of the rest that ends a move (all joints < 0.1 rad/s), then every 5th frame of it, so
it lands on the keyframe (29) or 1 to 4 frames before it.  The other 6 moves end with a
joint still above 0.1 rad/s (short holds; a wrist joint capped at 1.2 rad/s by its
actuator).  Long rests add keypoints (328 for 122 key actions).  Using
``keyframes.json`` as the keypoints is exact.

Demos are the demo bank's (same keys: ``generate.demo_keys``, variation ``i % n``), re-run
with observations.  Resumable: complete episodes are skipped, an interrupted one is redone.
A size and time estimate is printed before work starts, and a line per finished task.

``--workers N`` exports N tasks at once, each in its own process (spawned: JAX and the GL
context are created fresh in each), with the native physics' and llvmpipe's threads split
between them (``cores // N`` each); the files are the same as with one worker (every task
is deterministic on its own).  Only the parent writes ``manifest.json`` (atomically).  A task
that fails is reported with its name and the others go on; the exit code is then 1.

Code: data/rlbench_format.py (the folder layout, file names, image encodings), data/
episode_files.py (writing, verifying and reading one episode folder; :func:`read_episode`
reads every pickle with a restricted unpickler, so an episode from elsewhere cannot run
code), data/rlbench_demo.py (the pickles), data/expert_frames.py (running the experts with
observations); this module: the command, the estimate and the task workers.

Examples::

    python -m agnostos_mjx.data.export --out data/peract --tasks seen --demos 200 --workers 16
    python -m agnostos_mjx.data.export --out /tmp/x --tasks open_drawer --demos 2 --size 64
    python -m agnostos_mjx.data.export --format lerobot --out data/agnostos_seen --demos 200 \
        --cameras front,left_shoulder,right_shoulder,wrist --workers 16
    python -m agnostos_mjx.data.export --format lerobot --lerobot-version v2.1 \
        --rotation euler --state xicm --out $HF_LEROBOT_HOME/agnostos/seen --demos 200
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from agnostos_mjx.data.episode_files import read_episode, verify_episode, write_episode
from agnostos_mjx.data.expert_frames import episode_observations, frame_every
from agnostos_mjx.data.lerobot_layout import STATE_LAYOUTS
from agnostos_mjx.data.look import LOOK_KEY
from agnostos_mjx.data.rlbench_format import (
    FORMAT,
    RLBENCH_CAMERAS,
    episode_dir,
    is_complete,
)
from agnostos_mjx.data.rotations import ROTATIONS
from agnostos_mjx.infra.settings import configure_jax, usable_cores

# The episode format's API, importable from here as before the split (README, reports):
__all__ = ["ExportConfig", "RLBENCH_CAMERAS", "episode_dir", "estimate", "export",
           "export_task", "frames_per_demo", "is_complete", "main", "read_episode",
           "verify_episode", "write_episode"]

log = logging.getLogger("agnostos_mjx.data.export")
# Exports render on the CPU (MuJoCo's OpenGL), whatever the machine: the record of the
# images' look (data/look.py) names it, for a run rendering otherwise to be told.
EXPORT_RENDERER = "cpu"
FORMATS = ("rlbench", "lerobot")
DEFAULT_SIZE = {"rlbench": 128, "lerobot": 224}
# A LeRobot export renders RGB only: bytes per camera-frame measured at 224 px (one RGB PNG;
# open_drawer + stack_blocks, 2 demos each, 5 cameras: 10.2 KB) and its share of the RLBench
# export's camera time (rough: one render pass of four; not measured separately).
LEROBOT_BYTES_PER_CAMERA_FRAME_224 = 10_000
LEROBOT_TIME_SHARE = 0.6
# Measured (open_drawer, stack_blocks at 128 px): bytes per camera-frame of the 3 PNGs.
BYTES_PER_CAMERA_FRAME_128 = 30_000
# Seen tasks' expert demos (18 tasks x 12 demos): 7.7 key actions and 9.25 s (1,850 steps)
# of simulation per demo; the scenes' timestep (world.xml) for the estimate.
SEEN_KEY_ACTIONS = 7.7
SEEN_DEMO_SECONDS = 9.25
TIMESTEP = 0.005
# Time on 2 shared CPU cores (docs/performance.md): per task (scene,
# compiles), per demo (reset + expert physics, no images; seen-task mean at batch 4) and
# rendering + PNG writing per camera-frame (4 cameras, rgb, depth, segmentation, 128 px).
CPU_TASK_SETUP_S = 3.0
CPU_PHYSICS_S_PER_DEMO = 0.5
CPU_CAMERA_FRAMES_PER_S = 85.0


@dataclass(frozen=True)
class ExportConfig:
    out: Path
    tasks: tuple[str, ...]
    demos: int = 200
    seed: int = 0
    cameras: tuple[str, ...] = RLBENCH_CAMERAS
    size: int = 128
    batch: int = 25
    max_attempts: int = 10
    every: int | str | None = None  # dense frames: see frame_every
    format: str = "rlbench"
    # --format lerobot only (data/lerobot.py): the layout, and where demos are staged
    # (default: <out>.staging).
    lerobot_version: str = "v3.0"
    rotation: str = "quat"
    state: str = "rlbench"
    video: bool = False
    staging: Path | None = None

    def __post_init__(self) -> None:
        if self.format not in FORMATS:
            raise ValueError(f"unknown format {self.format!r}; choose from {', '.join(FORMATS)}")
        if self.format == "lerobot":
            from agnostos_mjx.data.lerobot import require_libraries

            require_libraries()
            self.layout()  # checks version, rotation, state and --video's PyAV

    def layout(self):
        from agnostos_mjx.data.lerobot import Layout

        return Layout(self.lerobot_version, self.rotation, self.state, self.video)

    def staging_root(self) -> Path:
        from agnostos_mjx.data.lerobot import staging_dir

        return Path(self.staging) if self.staging is not None else staging_dir(self.out)

    def episode_path(self, task: str, index: int) -> Path:
        """Where demo `index` of `task` is written: its RLBench episode folder or its
        LeRobot staging file."""
        if self.format == "lerobot":
            from agnostos_mjx.data.lerobot import staged_path

            return staged_path(self.staging_root(), task, index)
        return episode_dir(self.out, task, index)

    def is_done(self, task: str, index: int) -> bool:
        path = self.episode_path(task, index)
        return path.is_file() if self.format == "lerobot" else is_complete(path)


def _parse_every(text: str) -> int | str:
    if text == "rlbench":
        return text
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"a positive number of physics steps or 'rlbench', "
                                         f"not {text!r}")
    return value


def export_task(cfg: ExportConfig, task_name: str, threads: int | None = None) -> dict:
    """Export one task's missing demos; returns counts.  `threads`: the native physics'
    threads (default: all cores)."""
    from agnostos_mjx.data.generate import demo_keys
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.observation import MODALITIES, ObservationSpec, scene_labels
    from agnostos_mjx.runtime.outcome import Outcome
    from agnostos_mjx.tasks import get_task

    task = get_task(task_name)
    todo = [i for i in range(cfg.demos) if not cfg.is_done(task.name, i)]
    stats = {"task": task.name, "skipped": cfg.demos - len(todo), "written": 0, "failed": 0}
    if not todo:
        return stats
    episodes = Episodes(task, "native", threads=threads)
    every = frame_every(cfg.every, episodes.dt)
    lerobot = cfg.format == "lerobot"
    spec = ObservationSpec(cameras=cfg.cameras, height=cfg.size, width=cfg.size,
                           modalities=("rgb",) if lerobot else MODALITIES,
                           renderer=EXPORT_RENDERER)
    stats["every_steps"] = every
    stats["labels"] = {"geom_names": list(scene_labels(episodes.scene).geom_names),
                       "objects": {k: list(v) for k, v in
                                   scene_labels(episodes.scene).objects.items()}}
    attempts = {i: 0 for i in todo}
    while todo:
        batch = np.array(todo[: cfg.batch])
        keys = demo_keys(cfg.seed, task.name, batch, np.array([attempts[i] for i in batch]))
        variations = (batch % task.num_variations).astype(np.int32)
        env = episodes.reset(keys, variations, stop_at_success=False)
        # The expert's key actions (what episode_observations runs; a pure function of
        # the scene after reset), for the LeRobot actions.
        actions = episodes.expert_actions(env) if lerobot else None
        env, frames, keyframes = episode_observations(episodes, env, spec, every)
        for w, index in enumerate(batch):
            index = int(index)
            if env.outcome[w] == Outcome.SUCCESS:
                v = int(variations[w])
                if lerobot:
                    _stage(cfg, task, index, v, frames[w], keyframes[w], actions, w,
                           every, episodes.dt)
                else:
                    write_episode(episode_dir(cfg.out, task.name, index), frames[w],
                                  task.descriptions(v), v,
                                  None if every is None else keyframes[w])
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


def _stage(cfg: ExportConfig, task, index: int, variation: int, frames: list[dict],
           keyframes: list[int], actions, w: int, every: int | None, dt: float) -> None:
    """One successful demo -> its LeRobot staging file (data/lerobot.py)."""
    from agnostos_mjx.data.lerobot import stage_episode

    info = {"task": task.name, "demo": index, "variation": variation,
            "instruction": task.descriptions(variation)[0], "cameras": list(cfg.cameras),
            "size": cfg.size, "seed": cfg.seed, "every_steps": every,
            "frame_period_s": None if every is None else every * dt}
    stage_episode(cfg.episode_path(task.name, index), frames, keyframes,
                  np.asarray(actions.pos[w]), np.asarray(actions.quat[w]),
                  np.asarray(actions.gripper[w]), info, dense=every is not None)


def frames_per_demo(every: int | str | None) -> float:
    """Mean frames of a seen-task demo: 1 + its key actions, and with dense frames every K
    steps about S / K + A / 2 more (each action's ceil(S_a / K))."""
    if every is None:
        return 1 + SEEN_KEY_ACTIONS
    steps = SEEN_DEMO_SECONDS / TIMESTEP
    return 1 + steps / frame_every(every, TIMESTEP) + SEEN_KEY_ACTIONS / 2


def _every_text(every: int | str | None) -> str:
    if every is None:
        return ", keyframes only"
    return ", RLBench's 20 Hz frames" if every == "rlbench" else f", frames every {every} steps"


def parallel_tasks(cfg: ExportConfig, workers: int) -> int:
    """Tasks exported at once: min(workers, tasks, cores)."""
    return max(1, min(workers, len(cfg.tasks), usable_cores()))


def estimate(cfg: ExportConfig, frames: float | None = None, workers: int = 1
             ) -> tuple[float, float]:
    """(bytes, seconds) to expect: a rough guide printed before starting; `frames` per demo
    defaults to :func:`frames_per_demo`; the time is divided by the tasks run at once
    (:func:`parallel_tasks`)."""
    frames = frames_per_demo(cfg.every) if frames is None else frames
    camera_frames = len(cfg.tasks) * cfg.demos * frames * len(cfg.cameras)
    pixels = (cfg.size / 128) ** 2
    rgb_only = cfg.format == "lerobot"
    size = camera_frames * (LEROBOT_BYTES_PER_CAMERA_FRAME_224 * (cfg.size / 224) ** 2
                            if rgb_only else BYTES_PER_CAMERA_FRAME_128 * pixels)
    seconds = (len(cfg.tasks) * (CPU_TASK_SETUP_S + cfg.demos * CPU_PHYSICS_S_PER_DEMO)
               + camera_frames / CPU_CAMERA_FRAMES_PER_S * pixels
               * (LEROBOT_TIME_SHARE if rgb_only else 1.0))
    return size, seconds / parallel_tasks(cfg, workers)


def _look(manifest: dict, home: Path) -> dict:
    """This run's look record; one that differs in renderer or scene version from the
    record of the episodes already in `home` is a ValueError, as other settings are: the
    episodes of one export look alike."""
    from agnostos_mjx.data.look import look_record

    look = look_record(EXPORT_RENDERER)
    old = manifest.get(LOOK_KEY)
    keys = ("renderer", "scene_version")
    if old and manifest.get("tasks") and any(old.get(k) != look[k] for k in keys):
        raise ValueError(f"{home} was rendered with {', '.join(f'{k} {old.get(k)}' for k in keys)}"
                         f", not {', '.join(f'{k} {look[k]}' for k in keys)}: export to "
                         f"another --out")
    return look


def _run_task(cfg: ExportConfig, name: str, threads: int | None = None) -> dict:
    """export_task, timed (what a worker runs)."""
    t0 = time.perf_counter()
    stats = export_task(cfg, name, threads)
    stats["seconds"] = time.perf_counter() - t0
    return stats


def _worker_init() -> None:
    configure_jax()  # a spawned process sets up its JAX as the command did
    # Ctrl-C is the parent's to handle: it stops the workers itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _worker_env(threads: int) -> Iterator[None]:
    """Settings for spawned workers (inherited at spawn; the parent renders nothing while
    they run): thread caps for llvmpipe's render threads and OpenMP/BLAS pools, and JAX on
    the CPU: a worker simulates with native MuJoCo and renders on the CPU, and N processes
    each pre-allocating most of one GPU's memory would fail (seen on a GPU host with 16
    workers).  Values the user set are kept."""
    values = {k: str(threads) for k in ("LP_NUM_THREADS", "OMP_NUM_THREADS",
                                         "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    values["JAX_PLATFORMS"] = "cpu"
    saved = {k: os.environ.get(k) for k in values}
    for k, v in values.items():
        os.environ.setdefault(k, v)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _one_line(err: BaseException, limit: int = 500) -> str:
    text = " ".join(f"{type(err).__name__}: {err}".split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _stop_workers(pool) -> None:
    """Cancel the queued tasks and end the running workers (Ctrl-C)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())  # before shutdown
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        proc.terminate()
    for proc in processes:
        proc.join(5)


def export(cfg: ExportConfig, workers: int = 1) -> dict:
    """Export `cfg`'s tasks, `workers` at once (each in its own process when more than 1);
    returns the manifest, with "failed_tasks" {task: one-line error} when some failed."""
    lerobot = cfg.format == "lerobot"
    if lerobot:  # refuse a foreign --out before rendering anything
        from agnostos_mjx.data.lerobot import check_out

        check_out(cfg.out)
    # The episodes' home: the RLBench folders, or the LeRobot staging directory.
    home = cfg.staging_root() if lerobot else cfg.out
    home.mkdir(parents=True, exist_ok=True)
    workers = max(1, int(workers))
    size, seconds = estimate(cfg, workers=workers)
    at_once = parallel_tasks(cfg, workers)
    kind = f"LeRobot {cfg.lerobot_version} " if lerobot else ""
    print(f"export: {kind}{len(cfg.tasks)} tasks x {cfg.demos} demos, cameras "
          f"{','.join(cfg.cameras)} at {cfg.size}px{_every_text(cfg.every)}"
          f": {frames_per_demo(cfg.every):.0f} frames per demo, about {size / 1e9:.2f} GB and "
          f"{seconds / 60:.0f} min with {at_once} task(s) at once ({workers} worker(s), "
          f"{usable_cores()} cores; rough: the time per task measured on 2 shared cores; "
          f"complete episodes in {home} are skipped)", flush=True)
    t0 = time.perf_counter()
    manifest_path = home / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.exists() else {}
    # Settings that change what an episode holds must match between runs.
    config = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()
              if k in ("seed", "cameras", "size")}
    if lerobot:
        from agnostos_mjx.data.lerobot import STAGING_VERSION

        config["format"] = f"lerobot-staging-{STAGING_VERSION}"
    else:
        config["format"] = FORMAT
    if cfg.every is not None:  # absent for keyframes only, as in exports made before --every
        config["every"] = cfg.every
    if not lerobot and (missing := [c for c in RLBENCH_CAMERAS if c not in cfg.cameras]):
        log.warning("cameras %s not exported: RLBench's get_stored_demos (PerAct, RVT) needs "
                    "the rgb and depth folders of all five", ",".join(missing))
    if manifest.get("config", config) != config:
        raise ValueError(f"{home} was exported with {manifest['config']}, not {config}")
    manifest["config"] = config
    manifest[LOOK_KEY] = _look(manifest, home)
    manifest.pop("failed_tasks", None)
    manifest.pop("lerobot", None)
    order = list(manifest.get("tasks", {})) + [t for t in cfg.tasks
                                               if t not in manifest.get("tasks", {})]
    failed: dict[str, str] = {}
    done = 0

    def write() -> None:
        from agnostos_mjx.infra.cli import atomic_write

        tasks = manifest.get("tasks", {})
        manifest["tasks"] = {t: tasks[t] for t in order if t in tasks}  # cfg's order
        if failed:
            manifest["failed_tasks"] = {t: failed[t] for t in order if t in failed}
        atomic_write(manifest_path, json.dumps(manifest, indent=1) + "\n")

    def finished(name: str, stats: dict | None, err: BaseException | None) -> None:
        nonlocal done
        done += 1
        if err is not None:
            failed[name] = _one_line(err)
            log.debug("%s failed", name, exc_info=err)
            print(f"export: {name} FAILED: {failed[name]}", file=sys.stderr, flush=True)
            write()
            return
        entry = manifest.setdefault("tasks", {}).setdefault(name, {})
        entry.update({k: v for k, v in stats.items() if k in ("labels", "every_steps")
                      and v is not None})
        entry["episodes"] = sum(cfg.is_done(name, i) for i in range(cfg.demos))
        print(f"export: {name}: {entry['episodes']}/{cfg.demos} episodes ({stats['written']} "
              f"written, {stats['skipped']} skipped, {stats['failed']} failed attempts) in "
              f"{stats['seconds']:.1f} s [{done}/{len(cfg.tasks)} tasks]", flush=True)
        write()

    manifest.setdefault("tasks", {})
    if workers == 1:
        for name in cfg.tasks:
            try:
                stats = _run_task(cfg, name)
            except Exception as err:
                finished(name, None, err)
            else:
                finished(name, stats, None)
    else:
        import multiprocessing
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

        threads = max(1, usable_cores() // at_once)
        with _worker_env(threads):
            pool = ProcessPoolExecutor(at_once, multiprocessing.get_context("spawn"),
                                       initializer=_worker_init)
            try:
                futures = {pool.submit(_run_task, cfg, name, threads): name
                           for name in cfg.tasks}
                pending = set(futures)
                while pending:
                    ready, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in sorted(ready, key=lambda f: cfg.tasks.index(futures[f])):
                        err = fut.exception()
                        finished(futures[fut], None if err else fut.result(), err)
            except BaseException:
                _stop_workers(pool)
                write()
                raise
            pool.shutdown()
    if lerobot:
        if failed:
            print(f"export: {len(failed)} task(s) failed: LeRobot dataset {cfg.out} not "
                  f"assembled (the staged demos in {home} are kept)", file=sys.stderr,
                  flush=True)
        else:
            from agnostos_mjx.data.lerobot import assemble

            t1 = time.perf_counter()
            done_ = assemble(cfg.out, home, cfg.tasks, cfg.demos, cfg.layout(),
                             look=manifest[LOOK_KEY])
            verb = "already assembled" if done_["skipped"] else "assembled"
            print(f"export: LeRobot {cfg.lerobot_version} dataset {cfg.out} {verb}: "
                  f"{done_['episodes']} episodes, {done_['frames']} frames, {done_['tasks']} "
                  f"instructions ({time.perf_counter() - t1:.1f} s); staged demos: {home}",
                  flush=True)
            manifest["lerobot"] = {"out": str(cfg.out), **asdict(cfg.layout()),
                                   **{k: done_[k] for k in ("episodes", "frames", "tasks")}}
    manifest["wall_s"] = round(time.perf_counter() - t0, 1)
    write()
    return manifest


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    from agnostos_mjx.infra.cli import HelpFormatter, prog, setup_logging
    from agnostos_mjx.tasks import parse_tasks

    p = argparse.ArgumentParser(prog=prog("agnostos_mjx.data.export"),
                                description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--tasks", default="seen", help="task names and/or split names")
    p.add_argument("--demos", type=int, default=200, help="demos per task")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cameras", default=",".join(RLBENCH_CAMERAS),
                   help="RLBench's reader needs all five")
    p.add_argument("--size", type=int, default=None,
                   help="image height and width (default: 128 for rlbench, 224 for lerobot)")
    p.add_argument("--batch", type=int, default=25, help="worlds simulated at once")
    p.add_argument("--every", type=_parse_every, default=None, metavar="K|rlbench",
                   help="dense frames: also the scene every K physics steps of each key "
                        "action; 'rlbench': RLBench's 20 Hz (10 steps of 5 ms); default: "
                        "keyframes only")
    p.add_argument("--workers", type=int, default=1,
                   help="tasks exported at once, each in its own process (at most the "
                        "cores; the native physics' threads are split between them)")
    p.add_argument("--format", choices=FORMATS, default="rlbench",
                   help="rlbench: RLBench's episode folders; lerobot: a LeRobot dataset "
                        "(data/lerobot.py; needs pyarrow, pandas, Pillow)")
    p.add_argument("--lerobot-version", default=None, metavar="v3.0|v2.1",
                   help="LeRobot layout: v3.0 (lerobot >= 0.4; default) or v2.1 (openpi)")
    p.add_argument("--rotation", default=None, metavar="|".join(ROTATIONS),
                   help="the action's orientation (lerobot; default quat, qx qy qz qw)")
    p.add_argument("--state", default=None, metavar="|".join(STATE_LAYOUTS),
                   help="observation.state layout (lerobot; default rlbench: gripper_pose + "
                        "gripper_open; libero: xyz + axis-angle + fingers; xicm: xyz + Euler + "
                        "gripper_open)")
    p.add_argument("--video", action="store_true",
                   help="lerobot: cameras as MP4 videos (PyAV; lossy) instead of PNGs in the "
                        "parquet")
    p.add_argument("--staging", default=None,
                   help="lerobot: where each demo is staged before assembly, what a rerun "
                        "resumes from (default: <out>.staging)")
    p.add_argument("--quiet", action="store_true")
    a = p.parse_args(argv)
    if a.workers < 1:
        p.error("--workers: at least 1")
    lerobot_only = {"--lerobot-version": a.lerobot_version, "--rotation": a.rotation,
                    "--state": a.state, "--video": a.video or None, "--staging": a.staging}
    if a.format != "lerobot" and (given := [k for k, v in lerobot_only.items() if v is not None]):
        p.error(f"{', '.join(given)}: only with --format lerobot")
    if a.size is not None and a.size < 1:
        p.error("--size: a positive number of pixels")
    setup_logging(a.quiet)
    try:
        cfg = ExportConfig(out=Path(a.out), tasks=tuple(t.name for t in parse_tasks(a.tasks)),
                           demos=a.demos, seed=a.seed, cameras=tuple(a.cameras.split(",")),
                           size=a.size or DEFAULT_SIZE[a.format], batch=a.batch, every=a.every,
                           format=a.format, lerobot_version=a.lerobot_version or "v3.0",
                           rotation=a.rotation or "quat", state=a.state or "rlbench",
                           video=a.video, staging=None if a.staging is None else Path(a.staging))
    except (ValueError, ImportError) as err:
        p.error(str(err))
    try:
        manifest = export(cfg, a.workers)
    except KeyboardInterrupt:
        where = cfg.staging_root() if cfg.format == "lerobot" else cfg.out
        print(f"interrupted: complete episodes in {where} are kept; run again to resume",
              file=sys.stderr)
        return 130
    except ValueError as err:  # a foreign --out, settings unlike the earlier run's
        print(f"export: {err}", file=sys.stderr)
        return 2
    if failed := manifest.get("failed_tasks"):
        print(f"done in {manifest['wall_s']:.0f} s with {len(failed)} failed task(s) "
              f"({', '.join(failed)}): {cfg.out}", file=sys.stderr)
        return 1
    print(f"done in {manifest['wall_s']:.0f} s: {cfg.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
