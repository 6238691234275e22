"""Episode videos for a chosen subset of an evaluation: ``eval --video first:3``.

One frame per key action (the scene after reset, then after every key action of the
episode), the requested cameras side by side, written as H.264 MP4 with PyAV (extra
``video``).  A video of an episode with K key actions therefore has K + 1 frames and lasts
(K + 1) / fps seconds.  Files: ``<out>/videos/<task>_s<seed>_e<episode>_<outcome>.mp4``,
next to it ``.json`` (the episode record) and, for X-ICM, ``.llm.txt`` with every prompt
and the LLM's answer.

Selection (``--video``): ``first:N`` records episodes 0..N-1 of every task and seed;
``failures`` every episode that does not succeed; ``failures:N`` the failures among the
first N.  Only selected worlds are rendered (CPU renderer, anti-aliased); with the flag
off nothing is rendered or stored.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from agnostos_mjx.evaluation.config import RunConfig
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.state import EnvState

DEFAULT_CAMERAS = ("front", "overhead", "wrist")


@dataclass(frozen=True)
class VideoSpec:
    """Which episodes to film and how."""

    first: int | None = None  # episodes 0..first-1 of each task and seed (None: all)
    failures_only: bool = False
    cameras: tuple[str, ...] = DEFAULT_CAMERAS
    size: int = 256
    fps: float = 2.0

    @classmethod
    def parse(cls, text: str, cameras: str | None = None, size: int = 256) -> VideoSpec:
        """'first:N', 'failures' or 'failures:N' (see the module docs)."""
        kind, _, n = text.partition(":")
        if kind not in ("first", "failures") or (kind == "first" and not n.isdigit()) \
                or (n and not n.isdigit()):
            raise ValueError(f"--video expects first:N, failures or failures:N, got {text!r}")
        cams = tuple(cameras.split(",")) if cameras else DEFAULT_CAMERAS
        return cls(first=int(n) if n else None, failures_only=kind == "failures",
                   cameras=cams, size=size)

    def wants_episode(self, episode: int) -> bool:
        return self.first is None or episode < self.first


def episode_stem(task: str, seed: int, episode: int, outcome: str) -> str:
    return f"{task}_s{seed}_e{episode:03d}_{outcome}"


def write_mp4(path: Path, frames: list[np.ndarray] | np.ndarray, fps: float) -> None:
    """uint8 (T, H, W, 3) frames -> H.264 MP4 (PyAV); written to a temporary name first."""
    try:
        import av
    except ImportError as err:
        raise RuntimeError("episode videos need PyAV: pip install 'agnostos-mjx[video]'") from err
    from fractions import Fraction

    frames = [np.ascontiguousarray(f) for f in frames]
    h, w = frames[0].shape[:2]
    tmp = path.with_name(path.name + ".tmp.mp4")
    with av.open(str(tmp), "w") as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
        stream.width, stream.height = w + w % 2, h + h % 2  # yuv420p needs even sizes
        stream.pix_fmt = "yuv420p"
        for img in frames:
            img = np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)))
            container.mux(stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")))
        container.mux(stream.encode())
    tmp.replace(path)


def _llm_text(info: Any) -> str | None:
    """X-ICM's prompts and answers from an episode's policy_info, if it has any."""
    plans = info.get("plans", []) if isinstance(info, dict) else []
    parts = [f"### plan {k}\nPROMPT:\n{p['prompt']}\n\nANSWER:\n{p.get('response')}\n"
             for k, p in enumerate(plans) if isinstance(p, dict) and "prompt" in p]
    return "\n".join(parts) if parts else None


class EpisodeVideos:
    """Collects frames of the selected worlds of one task's batches and writes them.

    The evaluator calls ``start`` after reset, ``capture`` after every key action and
    ``write`` with the batch's episode records; a disabled instance does nothing."""

    def __init__(self, spec: VideoSpec | None, runner: Episodes | None, out: Path | None):
        self.spec, self.runner = spec, runner
        self.out = None if out is None else Path(out) / "videos"
        self._renderer: Any = None
        self._worlds = np.zeros(0, int)
        self._frames: list[list[np.ndarray]] = []

    @classmethod
    def for_task(cls, run: RunConfig, runner: Episodes) -> EpisodeVideos:
        """The videos of a run's options (--video, --video-cameras, --out) for one task."""
        if not run.video:
            return cls(None, None, None)
        return cls(VideoSpec.parse(run.video, run.video_cameras), runner, Path(run.out or "."))

    @property
    def enabled(self) -> bool:
        return self.spec is not None

    def _render(self, env: EnvState, worlds: np.ndarray) -> np.ndarray:
        """(len(worlds), H, ncam * W, 3): the cameras side by side."""
        from agnostos_mjx.render import CpuRenderer

        if self._renderer is None:
            self._renderer = CpuRenderer(self.runner.scene.model, self.spec.size, self.spec.size)
        p = env.physics
        views = self._renderer.render_views(
            np.asarray(p.qpos)[worlds], np.asarray(p.mocap_pos)[worlds],
            np.asarray(p.mocap_quat)[worlds], self.spec.cameras,
            np.asarray(env.geom_rgba)[worlds])
        return np.concatenate([views[c].rgb for c in self.spec.cameras], axis=2)

    def start(self, env: EnvState, episodes: list[tuple[int, int]]) -> None:
        """A new batch: world i runs (seed, episode) = episodes[i] (padding worlds beyond)."""
        if not self.enabled:
            return
        self._worlds = np.array([i for i, (_, e) in enumerate(episodes)
                                 if self.spec.wants_episode(e)], int)
        self._frames = [[] for _ in self._worlds]
        self._running = np.ones(len(self._worlds), bool)
        self.capture(env)

    def capture(self, env: EnvState) -> None:
        """One frame of every selected world that was still running before this step."""
        if not self.enabled or not self._running.any():
            return
        live = self._worlds[self._running]
        for k, img in zip(np.nonzero(self._running)[0], self._render(env, live)):
            self._frames[k].append(img)
        self._running &= ~np.asarray(env.done)[self._worlds]

    def write(self, records: list[dict]) -> list[Path]:
        """Encode the selected episodes of the batch whose records are `records`."""
        if not self.enabled:
            return []
        self.out.mkdir(parents=True, exist_ok=True)
        written = []
        for k, w in enumerate(self._worlds):
            rec = records[w]
            if self.spec.failures_only and rec["success"]:
                continue
            stem = episode_stem(rec["task"], rec["seed"], rec["episode"], rec["outcome"])
            write_mp4(self.out / f"{stem}.mp4", self._frames[k], self.spec.fps)
            (self.out / f"{stem}.json").write_text(json.dumps(rec, indent=1) + "\n")
            text = _llm_text(rec.get("policy_info"))
            if text:
                (self.out / f"{stem}.llm.txt").write_text(text)
            written.append(self.out / f"{stem}.mp4")
        self._frames = []
        return written

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
