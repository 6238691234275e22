"""Do the two renderers show policies the same images?  MuJoCo's OpenGL renderer (the CPU
route, what exports are rendered with) and MJX-Warp's ray tracer (the GPU route, what
evaluations on a GPU render with) render the reset states of tasks, same state and size;
per task and camera this compares RGB, segmentation and depth.

    python tools/renderer_parity.py                     # all 41 tasks, 128 px, 2 worlds
    python tools/renderer_parity.py --quick             # 2 tasks, 64 px, 1 world (CPU)
    python tools/renderer_parity.py --tasks lamp_on,stack_blocks --json parity.json

Metrics (issue 51's bounds, exit status 1 when any is broken):

* ``rgb``: mean absolute RGB difference over all pixels and channels, in 1/255 (<= 2);
  ``p99``: the 99th percentile of a pixel's largest channel difference (not bounded);
* ``seg``: fraction of pixels labelled alike (>= 0.999): the same geom, both nothing, or two
  geoms of one body seen at the same depth (within `TIE_MM`): coplanar faces of one object,
  which OpenGL's depth test and Warp's nearest hit each resolve their own way, so neither
  label is wrong; ``seg_raw`` counts only equal labels (not bounded);
* ``depth_mm``: mean depth difference where both see the same geom, millimetres (<= 1);
  ``depth_max_mm`` the largest (not bounded): OpenGL draws spheres, capsules and cylinders
  as polygons, Warp traces the true surface, so their silhouettes part by millimetres.

Warp runs through warp-lang's CPU backend where JAX has no GPU (slow: the first call builds
the kernels), so ``--quick`` keeps the CPU check short.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

CAMERAS = ("front", "left_shoulder", "right_shoulder", "overhead", "wrist")
QUICK_TASKS = ("lamp_on", "stack_blocks")
MAX_RGB = 2.0  # mean |RGB difference|, 1/255
MIN_SEG = 0.999  # fraction of pixels labelled alike
MAX_DEPTH_MM = 1.0  # mean, where both see the same geom
TIE_MM = 0.1  # two geoms of one body this close in depth: the same surface


@dataclass(frozen=True)
class Parity:
    """One task's camera: how far Warp's images are from the CPU's."""

    task: str
    camera: str
    rgb: float  # mean |difference| over pixels and channels, 1/255
    rgb_p99: float  # 99th percentile of the per-pixel largest channel difference, 1/255
    seg: float  # fraction of pixels labelled alike, coplanar ties of one body included
    seg_raw: float  # fraction of pixels with the same geom id (-1: none)
    depth_mm: float  # mean |depth difference| where the geom is the same, millimetres
    depth_max_mm: float  # the largest of those

    def broken(self, max_rgb: float = MAX_RGB, min_seg: float = MIN_SEG,
               max_depth_mm: float = MAX_DEPTH_MM) -> list[str]:
        """The bounds this camera breaks, as words (empty: within all)."""
        out = []
        if not self.rgb <= max_rgb:
            out.append(f"rgb {self.rgb:.2f} > {max_rgb}")
        if not self.seg >= min_seg:
            out.append(f"seg {self.seg:.4f} < {min_seg}")
        if not self.depth_mm <= max_depth_mm:
            out.append(f"depth {self.depth_mm:.3f} mm > {max_depth_mm}")
        return out


def compare(task: str, camera: str, cpu: Any, warp: Any,
            geom_body: np.ndarray | None = None) -> Parity:
    """Metrics of one camera's images (`CameraImages`-like: rgb, segmentation, depth of
    B worlds, numpy or JAX) from the two renderers; `geom_body` (the model's geom_bodyid)
    lets coplanar faces of one body count as alike."""
    a_rgb, b_rgb = (np.asarray(x.rgb, np.int16) for x in (cpu, warp))
    diff = np.abs(a_rgb - b_rgb)
    a_seg, b_seg = np.asarray(cpu.segmentation), np.asarray(warp.segmentation)
    depth = np.abs(np.asarray(cpu.depth, np.float64) - np.asarray(warp.depth, np.float64))
    same = a_seg == b_seg
    alike = same
    if geom_body is not None:
        body = np.append(np.asarray(geom_body), -1)  # index -1 (no geom) -> -1
        tie = (a_seg >= 0) & (b_seg >= 0) & (body[a_seg] == body[b_seg])
        alike = same | (tie & (depth <= TIE_MM / 1000.0))
    hit = same & (a_seg >= 0)
    hit_depth = 1000.0 * depth[hit] if hit.any() else np.zeros(1)
    return Parity(task=task, camera=camera, rgb=float(diff.mean()),
                  rgb_p99=float(np.percentile(diff.max(axis=-1), 99)),
                  seg=float(alike.mean()), seg_raw=float(same.mean()),
                  depth_mm=float(hit_depth.mean()), depth_max_mm=float(hit_depth.max()))


def render_both(task_name: str, size: int, worlds: int, cameras: Sequence[str],
                seed: int = 0) -> tuple[dict[str, Any], dict[str, Any], np.ndarray]:
    """The reset state's images of `cameras` from the CPU and from Warp (camera -> images)
    and the scene's geom_bodyid."""
    import jax

    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.observation import ObservationSpec
    from agnostos_mjx.tasks import get_task

    runner = Episodes(get_task(task_name), "native")
    try:
        keys = jax.random.split(jax.random.PRNGKey(seed), worlds)
        env = runner.reset(keys, np.arange(worlds, dtype=np.int32) % runner.task.num_variations)
        views = {}
        for kind in ("cpu", "warp"):
            spec = ObservationSpec(cameras=tuple(cameras), height=size, width=size,
                                   modalities=("rgb", "depth", "segmentation"), renderer=kind)
            # Host copies before the renderers close: Warp's images are computed
            # asynchronously and need their render context until they are done.
            views[kind] = {name: jax.tree.map(np.asarray, images) for name, images
                           in runner.observer.render_views(env, spec).items()}
        return views["cpu"], views["warp"], np.asarray(runner.scene.model.geom_bodyid)
    finally:
        runner.observer.close()


def check_task(task_name: str, size: int, worlds: int, cameras: Sequence[str],
               seed: int = 0) -> list[Parity]:
    """Every camera's metrics on one task's reset state."""
    cpu, warp, geom_body = render_both(task_name, size, worlds, cameras, seed)
    return [compare(task_name, c, cpu[c], warp[c], geom_body) for c in cameras]


def summary(rows: Sequence[Parity]) -> dict[str, dict[str, float]]:
    """Per camera, the worst over tasks of each metric."""
    out: dict[str, dict[str, float]] = {}
    for r in rows:
        row = asdict(r)
        s = out.setdefault(r.camera, {k: row[k] for k in ("rgb", "rgb_p99", "seg", "seg_raw",
                                                           "depth_mm", "depth_max_mm")})
        for k in s:
            s[k] = min(s[k], row[k]) if k.startswith("seg") else max(s[k], row[k])
    return out


def table(rows: Sequence[Parity], bounds: dict[str, float]) -> str:
    """Rows as a text table, a '!' after each broken bound, then the worst per camera."""
    lines = [f"{'task':<34}{'camera':<16}{'rgb/255':>8} {'p99':>4}{'seg':>9} {'seg_raw':>8}"
             f"{'depth mm':>10} {'max mm':>7}"]

    def line(task: str, camera: str, r: dict[str, float]) -> str:
        mark = lambda bad: "!" if bad else " "  # noqa: E731
        return (f"{task:<34}{camera:<16}{r['rgb']:>7.2f}{mark(r['rgb'] > bounds['max_rgb'])}"
                f"{r['rgb_p99']:>5.0f}{r['seg']:>9.4f}{mark(r['seg'] < bounds['min_seg'])}"
                f"{r['seg_raw']:>8.4f}{r['depth_mm']:>9.4f}"
                f"{mark(r['depth_mm'] > bounds['max_depth_mm'])}{r['depth_max_mm']:>7.2f}")

    lines += [line(r.task, r.camera, asdict(r)) for r in rows]
    lines.append("worst over tasks:")
    lines += [line("", camera, s) for camera, s in summary(rows).items()]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    from agnostos_mjx.infra.cli import HelpFormatter

    p = argparse.ArgumentParser(
        prog="python tools/renderer_parity.py", description=__doc__.split("\n\n")[0],
        epilog="Exit status: 0 when every camera of every task is within the bounds, 1 when "
               "one is not, 2 on bad arguments.",
        formatter_class=HelpFormatter)
    p.add_argument("--tasks", default="all",
                   help="comma-separated task names, or a split ('all', 'seen', 'unseen', ...)")
    p.add_argument("--size", type=int, default=128, help="image height and width, pixels")
    p.add_argument("--worlds", type=int, default=2,
                   help="worlds per task (reset keys split from --seed; variations 0, 1, ... "
                        "modulo the task's count)")
    p.add_argument("--cameras", default=",".join(CAMERAS),
                   help="comma-separated cameras; the first one's headlight lights them all "
                        "on both renderers, so keep 'front' first to check what exports show")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of the reset keys")
    p.add_argument("--quick", action="store_true",
                   help=f"a short check for a CPU: tasks {','.join(QUICK_TASKS)} (unless "
                        "--tasks is given), 64 px, 1 world")
    p.add_argument("--json", metavar="F", help="also write the rows and bounds to this file")
    p.add_argument("--max-rgb", type=float, default=MAX_RGB,
                   help="bound on the mean absolute RGB difference, in 1/255")
    p.add_argument("--min-seg", type=float, default=MIN_SEG,
                   help="bound on the fraction of pixels with the same segmentation label")
    p.add_argument("--max-depth-mm", type=float, default=MAX_DEPTH_MM,
                   help="bound on the mean depth difference where both see the same geom, mm")
    return p


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Arguments with --quick applied and the task list resolved to names."""
    p = build_parser()
    a = p.parse_args(argv)
    explicit = {x.split("=")[0] for x in (argv if argv is not None else sys.argv[1:])}
    if a.quick:
        if "--tasks" not in explicit:
            a.tasks = ",".join(QUICK_TASKS)
        if "--size" not in explicit:
            a.size = 64
        if "--worlds" not in explicit:
            a.worlds = 1
    from agnostos_mjx.tasks import parse_task_names

    try:
        a.task_names = parse_task_names(a.tasks)
    except (KeyError, ValueError) as err:
        p.error(f"--tasks: {err}")
    a.camera_names = tuple(c for c in a.cameras.split(",") if c)
    if not a.camera_names:
        p.error("--cameras: none given")
    if a.size < 1 or a.worlds < 1:
        p.error("--size and --worlds must be positive")
    return a


def main(argv: Sequence[str] | None = None) -> int:
    a = parse_args(argv)
    from agnostos_mjx.infra.settings import configure_jax

    configure_jax()
    import jax

    bounds = {"max_rgb": a.max_rgb, "min_seg": a.min_seg, "max_depth_mm": a.max_depth_mm}
    rows: list[Parity] = []
    t0 = time.perf_counter()
    for name in a.task_names:
        rows += check_task(name, a.size, a.worlds, a.camera_names, a.seed)
        print(f"{name}: " + ", ".join(f"{r.camera} {r.rgb:.2f}" for r in rows[-len(a.camera_names):]),
              file=sys.stderr, flush=True)
    broken = [f"{r.task}/{r.camera}: {'; '.join(b)}" for r in rows if (b := r.broken(**bounds))]
    print(table(rows, bounds))
    print(f"{len(broken)} of {len(rows)} task cameras out of bounds" if broken
          else f"all {len(rows)} task cameras within bounds")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({
            "size": a.size, "worlds": a.worlds, "seed": a.seed, "cameras": list(a.camera_names),
            "device": str(jax.devices()[0]), "bounds": bounds, "broken": broken,
            "worst": summary(rows), "rows": [asdict(r) for r in rows],
            "seconds": round(time.perf_counter() - t0, 1)}, indent=1) + "\n")
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
