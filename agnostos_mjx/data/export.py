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
observations), data/export_config.py (``ExportConfig`` and the estimate), data/
export_demos.py (one task's demos), data/export_run.py (the whole run: workers, manifest,
LeRobot assembly); this module: the command.

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
import sys
from collections.abc import Sequence
from pathlib import Path

from agnostos_mjx.data.episode_files import read_episode, verify_episode, write_episode
from agnostos_mjx.data.export_config import (
    FORMATS,
    ExportConfig,
    estimate,
    frames_per_demo,
)
from agnostos_mjx.data.export_demos import export_task
from agnostos_mjx.data.export_run import export
from agnostos_mjx.data.lerobot_layout import STATE_LAYOUTS
from agnostos_mjx.data.rlbench_format import RLBENCH_CAMERAS, episode_dir, is_complete
from agnostos_mjx.data.rotations import ROTATIONS
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.physics import RENDERERS, resolve_renderer

# The export's API and the episode format's, importable from here as before the splits
# (README, reports):
__all__ = ["ExportConfig", "RLBENCH_CAMERAS", "episode_dir", "estimate",
           "export", "export_task", "frames_per_demo", "is_complete", "main", "read_episode",
           "verify_episode", "write_episode"]

DEFAULT_SIZE = {"rlbench": 128, "lerobot": 224}


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
    p.add_argument("--renderer", choices=RENDERERS, default="auto",
                   help="where the images render: warp = MJX-Warp's batch ray tracer on the "
                        "GPU (auto wherever JAX has a CUDA GPU and warp-lang is installed, as "
                        "the evaluator's --renderer), cpu = MuJoCo's OpenGL (auto elsewhere); "
                        "the two look slightly different, so the dataset records which")
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
                           video=a.video, staging=None if a.staging is None else Path(a.staging),
                           renderer=resolve_renderer(a.renderer))
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
