"""One task's demos exported (data/export.py, the command): the demo bank's scenes re-run
with observations, each successful demo written as an RLBench episode folder or staged for
the LeRobot dataset; failed attempts retried with fresh keys."""

from __future__ import annotations

import logging

import numpy as np

from agnostos_mjx.data.episode_files import write_episode
from agnostos_mjx.data.expert_frames import episode_observations, frame_every
from agnostos_mjx.data.export_config import ExportConfig
from agnostos_mjx.data.rlbench_format import episode_dir

log = logging.getLogger("agnostos_mjx.data.export")


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
                           renderer=cfg.renderer)
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

