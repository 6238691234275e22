"""Observation throughput: ``python -m agnostos_mjx.bench.observation``.

Camera-frames/s of the full RLBench observation (RGB uint8, depth, world point cloud,
segmentation; `--cameras` at `--size` px) per task and batch, for

* ``cpu``: MuJoCo's OpenGL renderer over all worlds (what a CPU machine evaluates with),
  observations as numpy arrays; the worlds split over ``render.render_threads()`` threads,
  or over each count of ``--render-threads`` in turn (timed alternately, one row each);
* ``warp``: MJX-Warp's batch ray tracer, observations kept on the device (JAX arrays),
  from host state as the evaluator has it;
* ``warp-bare``: the bare MJX-Warp renderer (pose, ``refit_bvh`` and ``render``, without
  unpacking the images) from the same state, the ceiling the observation is compared with
  (``warp / warp-bare``).

The warp rows run only where a CUDA GPU and warp-lang are present.  Each figure is the best
of `--repeats` timed calls after one warm-up call.  A benchmark, not a test.

Examples::

    python -m agnostos_mjx.bench.observation --quick          # CPU, batch 75, one task
    python -m agnostos_mjx.bench.observation --quick --render-threads 1,2 --repeats 10
    python -m agnostos_mjx.bench.observation --out observation_bench.json
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import platform
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agnostos_mjx.infra.settings import configure_jax

log = logging.getLogger("agnostos_mjx.bench.observation")
PERACT_CAMERAS = ("front", "left_shoulder", "right_shoulder", "wrist")
TASKS = ("lamp_on", "stack_blocks", "close_fridge")


def build_parser() -> argparse.ArgumentParser:
    from agnostos_mjx.bench.backends import _int_list
    from agnostos_mjx.infra.cli import HelpFormatter

    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.bench.observation",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--tasks", default=",".join(TASKS), help="comma-separated task names")
    p.add_argument("--batches", type=_int_list, default="75,1024", help="worlds per call")
    p.add_argument("--cameras", default=",".join(PERACT_CAMERAS), help="comma-separated")
    p.add_argument("--size", type=int, default=128, help="image height and width, pixels")
    p.add_argument("--renderers", default=None,
                   help="comma-separated among cpu, warp (default: warp on a GPU, else cpu)")
    p.add_argument("--repeats", type=int, default=None,
                   help="timed calls (best is reported; default 3, --quick 2)")
    p.add_argument("--render-threads", type=_int_list, default=None,
                   help="cpu: thread counts to compare, timed alternately in this process "
                        "(default: AGNOSTOS_RENDER_THREADS or the usable cores, up to 8)")
    p.add_argument("--quick", action="store_true",
                   help="CPU smoke run: first task, batch 75, 2 repeats")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    return p


def _arrays(result: Any) -> list:
    """The arrays of a result, observations included (a dataclass is not a pytree, and
    ``block_until_ready`` on it would return before the device has finished)."""
    import jax

    if hasattr(result, "cameras"):
        return [v for cam in result.cameras.values() for v in vars(cam).values()
                if hasattr(v, "shape")]
    return jax.tree.leaves(result)


def _best(fn: Callable[[], Any], repeats: int) -> float:
    """Best wall time of `repeats` calls after one warm-up (results are waited for)."""
    import jax

    jax.block_until_ready(_arrays(fn()))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(_arrays(fn()))
        times.append(time.perf_counter() - t)
    return min(times)


def _alternate(fns: Sequence[Callable[[], Any]], repeats: int) -> list[list[float]]:
    """Wall times of `repeats` rounds calling each of `fns` in turn (one warm-up each), so
    that load from elsewhere on the machine hits every variant alike."""
    for fn in fns:
        fn()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for i, fn in enumerate(fns):
            t = time.perf_counter()
            fn()
            times[i].append(time.perf_counter() - t)
    return times


def _with_threads(n: int, fn: Callable[[], Any]) -> Any:
    """Run `fn` with AGNOSTOS_RENDER_THREADS=n (the observation caches one renderer per n)."""
    import os

    from agnostos_mjx.render import RENDER_THREADS_ENV

    old = os.environ.get(RENDER_THREADS_ENV)
    os.environ[RENDER_THREADS_ENV] = str(n)
    try:
        return fn()
    finally:
        if old is None:
            os.environ.pop(RENDER_THREADS_ENV)
        else:
            os.environ[RENDER_THREADS_ENV] = old


def _row(task: str, batch: int, renderer: str, ncam: int, seconds: float) -> dict:
    frames = batch * ncam
    return {"task": task, "batch": batch, "renderer": renderer, "cameras": ncam,
            "seconds_per_call": round(seconds, 5), "camera_frames_per_s": round(frames / seconds, 1)}


def bench_task(task_name: str, batch: int, renderers: Sequence[str], cameras: tuple[str, ...],
               size: int, repeats: int, render_threads: Sequence[int] | None = None
               ) -> list[dict]:
    """Rows for one task and batch: reset `batch` worlds, then time each renderer."""
    import jax

    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.observation import MODALITIES, ObservationSpec
    from agnostos_mjx.tasks import get_task

    task = get_task(task_name)
    runner = Episodes(task, "native")
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    env = runner.reset(keys, np.zeros(batch, np.int32))
    rows = []
    for kind in renderers:
        spec = ObservationSpec(cameras=cameras, height=size, width=size, modalities=MODALITIES,
                               renderer=kind, numpy=kind == "cpu")
        if kind == "cpu" and render_threads:
            fns = [functools.partial(_with_threads, n, lambda spec=spec: runner.observe(env, spec))
                   for n in render_threads]
            for n, times in zip(render_threads, _alternate(fns, repeats), strict=True):
                rows.append(_row(task_name, batch, kind, len(cameras), min(times)))
                rows[-1].update(render_threads=n, median_seconds=round(float(np.median(times)), 5),
                                all_seconds=[round(t, 4) for t in times])
                log.info("%s", rows[-1])
            continue
        seconds = _best(lambda spec=spec: runner.observe(env, spec), repeats)
        rows.append(_row(task_name, batch, kind, len(cameras), seconds))
        if kind == "warp":
            renderer = runner.observer.warp_renderer(spec, batch)
            p = env.physics
            rgba = jax.numpy.asarray(env.geom_rgba, jax.numpy.float32)
            bare = _best(functools.partial(renderer.state_buffers, p.qpos, p.mocap_pos,
                                           p.mocap_quat, rgba), repeats)
            rows.append(_row(task_name, batch, "warp-bare", len(cameras), bare))
            rows[-2]["fraction_of_bare"] = round(bare / seconds, 3)
        log.info("%s", rows[-1])
    return rows


def _gpu() -> bool:
    from agnostos_mjx.physics import warp_available

    return warp_available()


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    from agnostos_mjx.infra.cli import setup_logging, versions

    a = build_parser().parse_args(argv)
    setup_logging(False)
    tasks = a.tasks.split(",")
    batches, repeats = a.batches, a.repeats
    if a.quick:
        tasks, batches = tasks[:1], [75]
    if repeats is None:
        repeats = 2 if a.quick else 3
    renderers = a.renderers.split(",") if a.renderers else (["warp"] if _gpu() else ["cpu"])
    cameras = tuple(a.cameras.split(","))
    rows = [row for t in tasks for b in batches
            for row in bench_task(t, b, renderers, cameras, a.size, repeats, a.render_threads)]
    import jax

    result = {"benchmark": "observation", "size": a.size, "cameras": list(cameras),
              "modalities": ["rgb", "depth", "point_cloud", "segmentation"],
              "device": str(jax.devices()[0]), "machine": platform.processor() or platform.machine(),
              "versions": versions(), "rows": rows}
    print(f"{'task':<16}{'batch':>6}  {'renderer':<10}{'s/call':>9}{'cam-frames/s':>14}")
    for r in rows:
        name = r["renderer"] + (f" x{r['render_threads']}" if "render_threads" in r else "")
        print(f"{r['task']:<16}{r['batch']:>6}  {name:<10}{r['seconds_per_call']:>9.3f}"
              f"{r['camera_frames_per_s']:>14.0f}"
              + (f"  ({100 * r['fraction_of_bare']:.0f}% of bare)" if "fraction_of_bare" in r else "")
              + (f"  median {r['median_seconds']:.3f}" if "median_seconds" in r else ""))
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
