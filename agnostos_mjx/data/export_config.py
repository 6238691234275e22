"""What an export is (data/export.py, the command): ``ExportConfig``, where each demo is
written and whether it is done, and the size and time to expect before it starts."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from agnostos_mjx.data.expert_frames import frame_every
from agnostos_mjx.data.rlbench_format import RLBENCH_CAMERAS, episode_dir, is_complete
from agnostos_mjx.infra.settings import usable_cores

# Exports render where the machine's evaluations do (`--renderer auto`, as the evaluator's):
# MJX-Warp on a GPU with warp-lang, MuJoCo's OpenGL elsewhere.  The two renderers' images
# differ slightly (eval/reports/renderer_parity_h200), so the record of the images' look
# (data/look.py) names the one used, for a run rendering otherwise to be told.
FORMATS = ("rlbench", "lerobot")
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
    renderer: str = "cpu"  # the route taken: "cpu" or "warp" (export.py resolves --renderer)

    def __post_init__(self) -> None:
        if self.renderer not in ("cpu", "warp"):
            raise ValueError(f"renderer must be cpu or warp, got {self.renderer!r}")
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


def frames_per_demo(every: int | str | None) -> float:
    """Mean frames of a seen-task demo: 1 + its key actions, and with dense frames every K
    steps about S / K + A / 2 more (each action's ceil(S_a / K))."""
    if every is None:
        return 1 + SEEN_KEY_ACTIONS
    steps = SEEN_DEMO_SECONDS / TIMESTEP
    return 1 + steps / frame_every(every, TIMESTEP) + SEEN_KEY_ACTIONS / 2


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

