"""A whole export (data/export.py, the command): its tasks in this process or in spawned
workers, the manifest (settings that must match a rerun's, the look, per-task counts,
failures) written after every task, and the LeRobot dataset assembled from the staged
demos at the end."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

from agnostos_mjx.data.export_config import (
    ExportConfig,
    estimate,
    frames_per_demo,
    parallel_tasks,
)
from agnostos_mjx.data.export_demos import export_task
from agnostos_mjx.data.look import LOOK_KEY
from agnostos_mjx.data.rlbench_format import FORMAT, RLBENCH_CAMERAS
from agnostos_mjx.infra.settings import configure_jax, usable_cores
from agnostos_mjx.physics.capabilities import RENDER_ROUTES

log = logging.getLogger("agnostos_mjx.data.export")


def _every_text(every: int | str | None) -> str:
    if every is None:
        return ", keyframes only"
    return ", RLBench's 20 Hz frames" if every == "rlbench" else f", frames every {every} steps"


def _look(cfg: ExportConfig, manifest: dict, home: Path) -> dict:
    """This run's look record; one that differs in renderer or scene version from the
    record of the episodes already in `home` is a ValueError, as other settings are: the
    episodes of one export look alike."""
    from agnostos_mjx.data.look import look_record

    look = look_record(cfg.renderer)
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
def _worker_env(threads: int, renderer: str) -> Iterator[None]:  # renderer: a route's name
    """Settings for spawned workers (inherited at spawn; the parent renders nothing while
    they run): thread caps for llvmpipe's render threads and OpenMP/BLAS pools, and JAX on
    the CPU when they render there (a worker simulates with native MuJoCo) or, rendering on
    the GPU, taking its memory as needed: N processes each pre-allocating most of one GPU's
    memory would fail (seen on a GPU host with 16 workers).  Values the user set are kept."""
    values = {k: str(threads) for k in ("LP_NUM_THREADS", "OMP_NUM_THREADS",
                                         "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    if not RENDER_ROUTES[renderer].on_device:
        values["JAX_PLATFORMS"] = "cpu"
    else:
        values["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
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
    manifest[LOOK_KEY] = _look(cfg, manifest, home)
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
        with _worker_env(threads, cfg.renderer):
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

