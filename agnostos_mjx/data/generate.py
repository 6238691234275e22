"""Generate the seen-task demonstration bank: ``python -m agnostos_mjx.data.generate``.

The experts run in batches; only successful episodes are kept, a failed
one is re-sampled (a new scene from the next attempt key) and counted.  Demo
`i` of a task uses variation ``i % num_variations`` (so demos spread evenly
over the variations) and the scene key
``fold_in(fold_in(fold_in(PRNGKey(seed), crc32(task)), i), attempt)``, so a
bank is reproducible from its seed and independent of batching.

Recording follows RLBench: an observation every 0.05 s (every 10th physics
step); key actions are the PerAct keyframes of that recording (gripper
changes and arm stops), in continuous form and as X-ICM's 7 integers.

Work is split into chunks of demo indices (`--chunk`, default `--batch`); with the
native backend, `--workers` processes run chunks in parallel (one per core by
default: the experts' control loop is serial Python, so processes scale where
MuJoCo's threads alone do not).  Scene keys depend only on (seed, task, index,
attempt), and the bank does not depend on the number of workers, nor on --batch and
--chunk: every world runs its own timeline (Episodes.step), so a demo is the same alone
or in a batch, up to floating-point rounding that differs with the batch shape.  (Banks
made before this, including the one behind the shipped memory, moved a batch's worlds in
lockstep: a world was recorded holding still until its batch's slowest move ended.)

Interrupting is safe: each finished chunk rewrites its task's archive and then
the manifest (which records the index intervals run) atomically, and a rerun
with the same --out runs only what is missing (settings must match; a
mismatch is an error, not a mix).

Examples::

    python -m agnostos_mjx.data.generate --out data/seen_bank             # 18 seen x 200
    python -m agnostos_mjx.data.generate --out /tmp/bank --tasks open_drawer --demos 4
"""

from __future__ import annotations

import argparse
import concurrent.futures
import itertools
import json
import logging
import multiprocessing
import sys
import time
import zlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from datetime import datetime
from pathlib import Path

import jax
import numpy as np

from agnostos_mjx.data.bank import (
    FORMAT_VERSION,
    MANIFEST,
    MAX_KEYS,
    TRAJ_FIELDS,
    BankError,
    read_manifest,
    read_shard,
    write_manifest,
    write_shard,
)
from agnostos_mjx.infra.cli import (
    HelpFormatter,
    check_writable_dir,
    progress_bar,
    setup_logging,
    versions,
)
from agnostos_mjx.infra.settings import configure_jax, usable_cores
from agnostos_mjx.physics import BACKENDS
from agnostos_mjx.sim.keyframes import discover_keyframes, merge_repeated_keyframes
from agnostos_mjx.sim.textualise import encode_action

log = logging.getLogger("agnostos_mjx.data")

FRAME_DT = 0.05  # RLBench records one observation per 50 ms simulation step
# Settings that must agree between a bank and a run that extends it.
COMPATIBLE = ("seed", "image_size", "cameras", "frame_dt", "max_attempts")


@dataclass(frozen=True)
class GenerateConfig:
    out: Path
    tasks: tuple[str, ...]
    demos: int = 200
    seed: int = 0
    backend: str = "auto"
    batch: int = 100
    image_size: int = 128
    cameras: tuple[str, ...] = ("front",)
    max_attempts: int = 10
    frame_dt: float = FRAME_DT
    quiet: bool = False
    workers: int = 1  # processes (native backend); 0: one per core
    chunk: int = 0  # demos per unit of work (0: --batch)


def demo_keys(seed: int, task: str, indices: np.ndarray, attempts: np.ndarray) -> jax.Array:
    base = jax.random.fold_in(jax.random.PRNGKey(seed), zlib.crc32(task.encode()) & 0x7FFFFFFF)
    fold = lambda i, a: jax.random.fold_in(jax.random.fold_in(base, i), a)  # noqa: E731
    return jax.vmap(fold)(np.asarray(indices, np.uint32), np.asarray(attempts, np.uint32))


def _recorded_frames(episodes, initial: np.ndarray, record, world: int, stride: int) -> np.ndarray:
    """One world's sensordata at RLBench's observation rate (first and last frame kept)."""
    rows = [initial[world][None]] + [r.sensordata[world][r.valid[world]] for r in record]
    full = np.concatenate(rows)
    keep = np.arange(0, len(full), stride)
    if keep[-1] != len(full) - 1:
        keep = np.append(keep, len(full) - 1)
    return full[keep]


def _padded(a: np.ndarray, value=0) -> np.ndarray:
    """Pad the leading axis to MAX_KEYS."""
    return np.concatenate([a, np.full((MAX_KEYS - len(a), *a.shape[1:]), value, a.dtype)])


def _demo_arrays(episodes, env, record, frames: dict, indices, attempts, ok, stride):
    """Arrays (see bank.py) of the successful worlds of one batch."""
    from agnostos_mjx.sim.world import FINGER_OPEN

    task, layout = episodes.task, episodes.scene.layout
    names = list(task.objects)
    out: dict[str, list] = {k: [] for k in (
        "index", "attempt", "variation", "sim_steps", "n_keys", "instruction", "descriptions",
        "objects", "keyframes", "key_pos", "key_quat", "key_open", "key_ints", "traj")}
    for c in frames:
        out[f"rgb_{c}_first"], out[f"rgb_{c}_last"] = [], []
    initial = np.asarray(env.initial_obs.data)
    for w in np.nonzero(ok)[0]:
        traj = _recorded_frames(episodes, initial, record, w, stride)
        tip_p, tip_q = traj[:, layout.slice("tip.pos")], traj[:, layout.slice("tip.quat")]
        open_flag = (traj[:, layout.slice("finger_q")][:, 0] / FINGER_OPEN) > 0.95
        keys = discover_keyframes(open_flag.astype(np.float32), traj[:, layout.slice("arm_qd")])
        keys = np.asarray(merge_repeated_keyframes(keys, tip_p, tip_q, open_flag), np.int64)
        if not 1 <= len(keys) <= MAX_KEYS:
            log.warning("%s: a demo with %d keyframes (storage holds %d) is re-sampled",
                        task.name, len(keys), MAX_KEYS)
            ok[w] = False
            continue
        ints = np.asarray(encode_action(tip_p[keys], tip_q[keys], open_flag[keys]), np.int32)
        v = int(env.variation[w])
        out["index"].append(indices[w])
        out["attempt"].append(attempts[w])
        out["variation"].append(v)
        out["sim_steps"].append(int(env.sim_steps[w]))
        out["n_keys"].append(len(keys))
        descriptions = task.descriptions(v)
        out["instruction"].append(descriptions[0])
        out["descriptions"].append(json.dumps(descriptions))
        out["objects"].append(np.stack([np.asarray(env.initial_obs.pos(task.objects[n]))[w]
                                        for n in names]) if names else np.zeros((0, 3)))
        out["keyframes"].append(_padded(keys, -1))
        out["key_pos"].append(_padded(tip_p[keys].astype(np.float32)))
        out["key_quat"].append(_padded(tip_q[keys].astype(np.float32)))
        out["key_open"].append(_padded(open_flag[keys].astype(np.float32)))
        out["key_ints"].append(_padded(ints))
        out["traj"].append(np.concatenate([tip_p, tip_q, open_flag[:, None]], 1).astype(np.float32))
        for c, (first, last) in frames.items():
            out[f"rgb_{c}_first"].append(first[w])
            out[f"rgb_{c}_last"].append(last[w])
    return out


def _merge(old: dict[str, np.ndarray] | None, new: dict[str, list], meta: dict,
           object_names: list[str]) -> dict[str, np.ndarray]:
    """Old archive + new demos -> archive arrays, ordered by demo index."""
    trajs = list(new.pop("traj"))
    if old is not None:
        off = old["traj_offsets"]
        trajs = [old["traj"][off[i]:off[i + 1]] for i in range(len(off) - 1)] + trajs
    merged: dict[str, np.ndarray] = {}
    for k, rows in new.items():
        arr = np.asarray(rows) if rows else None
        if old is not None:
            arr = old[k] if arr is None else np.concatenate([old[k], arr])
        merged[k] = arr
    # Keep one row per demo index: a chunk rerun after an interruption between the
    # archive write and the manifest write regenerates demos the archive already has.
    _, order = np.unique(merged["index"], return_index=True)
    merged = {k: v[order] for k, v in merged.items()}
    trajs = [trajs[i] for i in order]
    merged["traj"] = np.concatenate(trajs) if trajs else np.zeros((0, 8), np.float32)
    merged["traj_offsets"] = np.concatenate([[0], np.cumsum([len(t) for t in trajs])]).astype(np.int64)
    merged["object_names"] = np.asarray(object_names, dtype=str)
    merged["meta"] = np.asarray(json.dumps(meta))
    return merged


def _pad_batch(n: int, batch: int) -> int:
    """Worlds to simulate for n pending demos: a power of two up to `batch`, so
    retries reuse a few compiled shapes."""
    return min(batch, 1 << max(n - 1, 0).bit_length())


def _open_bank(cfg: GenerateConfig) -> dict:
    """The existing manifest (checked for compatible settings) or a fresh one."""
    config = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()
              if k in COMPATIBLE}
    if (cfg.out / MANIFEST).exists():
        manifest = read_manifest(cfg.out)
        clash = {k: (manifest["config"].get(k), config[k]) for k in COMPATIBLE
                 if manifest["config"].get(k) != config[k]}
        if clash:
            details = ", ".join(f"{k}: bank {a!r} vs requested {b!r}" for k, (a, b) in clash.items())
            raise BankError(f"{cfg.out} was generated with other settings ({details}); use the "
                            "same settings to extend it or a new --out")
        return manifest
    import agnostos_mjx

    cfg.out.mkdir(parents=True, exist_ok=True)
    return {"format_version": FORMAT_VERSION, "package_version": agnostos_mjx.__version__,
            "created": datetime.now().isoformat(timespec="seconds"), "versions": versions(),
            "config": config, "tasks": {}}


def _load_existing(cfg: GenerateConfig, entry: dict | None) -> dict[str, np.ndarray] | None:
    """The task's archive as the manifest describes it.  An archive newer than
    the manifest (interrupted between the two writes) is accepted if it reads."""
    if entry is None or not (cfg.out / entry["file"]).exists():
        return None
    try:
        return read_shard(cfg.out / entry["file"], entry["sha256"])
    except BankError:
        log.warning("%s does not match the manifest's checksum; checking it as an archive",
                    entry["file"])
        return read_shard(cfg.out / entry["file"])


def _stride(cfg: GenerateConfig, dt: float) -> int:
    """Physics steps per recorded frame."""
    return max(1, round(cfg.frame_dt / dt))


@dataclass(frozen=True)
class Chunk:
    """Demo indices [start, stop) of one task: the unit of work a process runs."""

    task: str
    start: int
    stop: int


@dataclass
class ChunkResult:
    chunk: Chunk
    demos: dict[str, list]  # see _demo_arrays
    failed_attempts: int
    given_up: int
    seconds: float


def run_chunk(cfg: GenerateConfig, chunk: Chunk, episodes) -> ChunkResult:
    """Run the expert on a chunk's demos in batches until each succeeds or runs out
    of attempts; nothing is written (the caller merges and stores)."""
    from agnostos_mjx.runtime.outcome import Outcome

    task = episodes.task
    stride = _stride(cfg, episodes.dt)
    t0 = time.perf_counter()
    result = ChunkResult(chunk, {}, 0, 0, 0.0)
    for first_index in range(chunk.start, chunk.stop, cfg.batch):
        indices = np.arange(first_index, min(first_index + cfg.batch, chunk.stop))
        attempts = np.zeros(len(indices), np.int64)
        pending = np.ones(len(indices), bool)
        while pending.any():
            todo = np.nonzero(pending)[0]
            size = _pad_batch(len(todo), cfg.batch)
            rows = np.resize(todo, size)  # pad by repeating pending worlds
            keys = demo_keys(cfg.seed, task.name, indices[rows], attempts[rows])
            variations = indices[rows] % task.num_variations
            env0 = episodes.reset(keys, variations, stop_at_success=False)
            first = {c: episodes.render(env0, c, cfg.image_size, cfg.image_size)
                     for c in cfg.cameras}
            record: list = []
            env = episodes.run_expert(env0, record)
            ok = env.outcome == Outcome.SUCCESS
            ok[len(todo):] = False  # padding worlds are duplicates
            frames = {c: (first[c], episodes.render(env, c, cfg.image_size, cfg.image_size))
                      for c in cfg.cameras}
            arrays = _demo_arrays(episodes, env, record, frames, indices[rows],
                                  attempts[rows], ok, stride)
            for k, rows_k in arrays.items():
                result.demos.setdefault(k, []).extend(rows_k)
            failed = ~ok[:len(todo)]
            result.failed_attempts += int(failed.sum())
            pending[todo[ok[:len(todo)]]] = False
            attempts[todo[failed]] += 1
            exhausted = pending & (attempts >= cfg.max_attempts)
            if exhausted.any():
                log.warning("%s: demos %s failed %d attempts; skipped", task.name,
                            indices[exhausted].tolist(), cfg.max_attempts)
                result.given_up += int(exhausted.sum())
                pending &= ~exhausted
    result.seconds = time.perf_counter() - t0
    return result


def _covered(entry: dict) -> list[list[int]]:
    """Index intervals [start, stop) already run (banks of format 1 stored `next_index`)."""
    if "done" in entry:
        return [list(r) for r in entry["done"]]
    return [[0, int(entry.get("next_index", 0))]] if entry.get("next_index") else []


def _add_interval(done: list[list[int]], start: int, stop: int) -> list[list[int]]:
    merged: list[list[int]] = []
    for a, b in sorted([*done, [start, stop]]):
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return merged


def _gaps(done: list[list[int]], stop: int) -> list[tuple[int, int]]:
    """Parts of [0, stop) not covered by `done`."""
    gaps, cursor = [], 0
    for a, b in done:
        if a > cursor:
            gaps.append((cursor, min(a, stop)))
        cursor = max(cursor, b)
    if cursor < stop:
        gaps.append((cursor, stop))
    return [(a, b) for a, b in gaps if a < b]


def plan_chunks(cfg: GenerateConfig, task: str, entry: dict, have: int) -> list[Chunk]:
    """Chunks still to run for a task: the uncovered part of [0, demos), or, once that
    is covered but demos were given up, fresh indices after the last one run."""
    done = _covered(entry)
    gaps = _gaps(done, cfg.demos)
    if not gaps and have < cfg.demos:
        end = max((b for _, b in done), default=0)
        gaps = [(end, end + cfg.demos - have)]
    size = cfg.chunk or cfg.batch
    return [Chunk(task, a, min(a + size, b)) for a, b in gaps for a in range(a, b, size)]


class _TaskStore:
    """One task's archive and manifest entry; every added chunk is written atomically
    (archive first, then the manifest), so an interruption loses at most running chunks."""

    def __init__(self, cfg: GenerateConfig, task, manifest: dict):
        self.cfg, self.task, self.manifest = cfg, task, manifest
        entry = manifest["tasks"].get(task.name)
        self.archive = _load_existing(cfg, entry)
        self.entry = dict(entry or {"file": f"{task.name}.npz", "failed_attempts": 0,
                                    "given_up": 0, "seconds": 0.0})
        self.entry["done"] = _covered(self.entry)
        self.entry.pop("next_index", None)
        self.entry["demos"] = self.have

    @property
    def have(self) -> int:
        return 0 if self.archive is None else len(self.archive["index"])

    def add(self, result: ChunkResult, frame_dt: float) -> int:
        before = self.have
        if result.demos.get("index"):
            meta = {"task": self.task.name, "split": self.task.split.value,
                    "format_version": FORMAT_VERSION, "cameras": list(self.cfg.cameras),
                    "image_size": self.cfg.image_size, "frame_dt": frame_dt,
                    "traj_fields": list(TRAJ_FIELDS)}
            self.archive = _merge(self.archive, result.demos, meta, list(self.task.objects))
            self.entry["sha256"] = write_shard(self.cfg.out / self.entry["file"], self.archive)
        e = self.entry
        e["done"] = _add_interval(e["done"], result.chunk.start, result.chunk.stop)
        e["failed_attempts"] += result.failed_attempts
        e["given_up"] += result.given_up
        e["seconds"] = round(e["seconds"] + result.seconds, 2)
        e["demos"] = self.have
        self.manifest["tasks"][self.task.name] = e
        write_manifest(self.cfg.out, self.manifest)
        return self.have - before


# Per worker process: the scenes it has built (a process runs chunks of several tasks).
_WORKER_EPISODES: dict[str, object] = {}
_WORKER_THREADS = [1]  # MuJoCo threads per worker, set by _worker_init


def _worker_init(threads: int) -> None:
    # Native workers keep JAX on the CPU: sixteen processes must not each claim the GPU.
    # XLA reads its flags when the backend starts (after this), jax_platforms likewise.
    configure_jax(cpu=True)
    jax.config.update("jax_platforms", "cpu")
    setup_logging(quiet=True)  # warnings (e.g. given-up demos) still show
    _WORKER_THREADS[0] = threads


def _worker_run(cfg: GenerateConfig, chunk: Chunk) -> ChunkResult:
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    if chunk.task not in _WORKER_EPISODES:
        _WORKER_EPISODES[chunk.task] = Episodes(get_task(chunk.task), cfg.backend,
                                                _WORKER_THREADS[0])
    return run_chunk(cfg, chunk, _WORKER_EPISODES[chunk.task])


def resolve_workers(cfg: GenerateConfig) -> int:
    """--workers 0 means one process per core for a host backend (native), else 1."""
    from agnostos_mjx.physics import CAPABILITIES, resolve_backend

    backend = resolve_backend(cfg.backend)
    on_device = CAPABILITIES[backend].on_device
    if cfg.workers == 0:
        return 1 if on_device else usable_cores()
    if cfg.workers > 1 and on_device:
        raise ValueError(f"--workers {cfg.workers} needs --backend native (one {backend} "
                         "process drives the whole accelerator)")
    return cfg.workers


def generate(cfg: GenerateConfig) -> dict:
    """Generate every requested task; returns a report (also written to report.json)."""
    from agnostos_mjx.physics import resolve_backend
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    cfg = replace(cfg, backend=resolve_backend(cfg.backend, cfg.batch))
    tasks = {name: get_task(name) for name in cfg.tasks}
    manifest = _open_bank(cfg)
    stores = {name: _TaskStore(cfg, task, manifest) for name, task in tasks.items()}
    workers = resolve_workers(cfg)
    total = cfg.demos * len(tasks)
    t0 = time.perf_counter()
    counted = lambda: sum(min(s.have, cfg.demos) for s in stores.values())  # noqa: E731
    with progress_bar(total, enabled=not cfg.quiet, unit="demos") as bar:
        bar.update(counted(), force=True)
        for _round in range(cfg.max_attempts):  # later rounds only replace given-up demos
            per_task = [plan_chunks(cfg, n, s.entry, s.have) for n, s in stores.items()]
            if not any(per_task):
                break
            frame_dt = _scene_checks(cfg, tasks, {g[0].task for g in per_task if g})
            if workers == 1:  # task by task, one runner alive at a time
                for group in filter(None, per_task):
                    episodes = Episodes(tasks[group[0].task], cfg.backend)
                    _collect((run_chunk(cfg, c, episodes) for c in group), stores, frame_dt,
                             bar, counted)
                continue
            # Round-robin over tasks so that every task's chunks start early.
            chunks = [c for group in itertools.zip_longest(*per_task) for c in group if c]
            threads = max(1, usable_cores() // workers)
            with concurrent.futures.ProcessPoolExecutor(
                    workers, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_worker_init, initargs=(threads,)) as pool:
                futures = [pool.submit(_worker_run, cfg, c) for c in chunks]
                _collect((f.result() for f in concurrent.futures.as_completed(futures)),
                         stores, frame_dt, bar, counted)
    wall = time.perf_counter() - t0
    report = {"out": str(cfg.out), "wall_seconds": round(wall, 2), "workers": workers,
              "demos": sum(s.have for s in stores.values()), "backend": cfg.backend,
              "tasks": {name: manifest["tasks"][name] for name in tasks}}
    report["markdown"] = format_report(report)
    from agnostos_mjx.infra.cli import atomic_write

    atomic_write(cfg.out / "report.json", json.dumps(report, indent=1) + "\n")
    atomic_write(cfg.out / "report.md", report["markdown"])
    return report


def _scene_checks(cfg: GenerateConfig, tasks: dict, names: set[str]) -> dict[str, float]:
    """Check the cameras exist and return each task's recording interval, from the scene
    models alone (cheap: no runner is built)."""
    from agnostos_mjx.render import camera_names
    from agnostos_mjx.sim.world import build_scene

    frame_dt = {}
    for name in sorted(names):
        model = build_scene(tasks[name]).model
        known = camera_names(model)
        if unknown := [c for c in cfg.cameras if c not in known]:
            raise ValueError(f"unknown camera(s) {unknown}; the scene has {', '.join(known)}")
        dt = float(model.opt.timestep)
        frame_dt[name] = _stride(cfg, dt) * dt
    return frame_dt


def _collect(results, stores: dict, frame_dt: dict, bar, counted) -> None:
    for result in results:
        stores[result.chunk.task].add(result, frame_dt[result.chunk.task])
        bar.update(counted())


def format_report(report: dict) -> str:
    lines = ["| task | demos | failed attempts | given up | seconds |", "|---|---|---|---|---|"]
    for name, e in report["tasks"].items():
        lines.append(f"| {name} | {e['demos']} | {e['failed_attempts']} | {e['given_up']} | "
                     f"{e['seconds']:.1f} |")
    lines.append(f"\n{report['demos']} demos in this bank for these tasks; this run took "
                 f"{report['wall_seconds']:.1f} s wall ({report['backend']} backend).")
    return "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m agnostos_mjx.data.generate", formatter_class=HelpFormatter,
        description="Generate expert demonstrations of seen tasks into a resumable bank "
                    "(one .npz per task + manifest.json).")
    p.add_argument("--out", type=Path, required=True,
                   help="bank directory; an existing bank is extended/resumed")
    p.add_argument("--tasks", default="seen",
                   help="comma-separated task names and/or split names (seen, unseen, all)")
    p.add_argument("--demos", type=int, default=200, help="successful demos per task")
    p.add_argument("--seed", type=int, default=0, help="bank seed (scenes derive from it)")
    p.add_argument("--backend", default="auto", choices=BACKENDS,
                   help="physics backend (auto: MJX-warp on a CUDA GPU for batches of >= 4096 "
                        "worlds, else native MuJoCo, which is faster below that)")
    p.add_argument("--batch", type=int, default=100, help="worlds simulated at once")
    p.add_argument("--image-size", type=int, default=128, help="square RGB frame size")
    p.add_argument("--cameras", default="front",
                   help="comma-separated cameras to store first/last frames of "
                        "(front, left_shoulder, right_shoulder, overhead, wrist)")
    p.add_argument("--max-attempts", type=int, default=10,
                   help="scenes tried per demo before it is skipped (counted in the report)")
    p.add_argument("--workers", type=int, default=0,
                   help="processes running chunks of demos in parallel, native backend only "
                        "(0: one per CPU core for native, 1 for MJX); results do not depend "
                        "on it")
    p.add_argument("--chunk", type=int, default=0,
                   help="demos per unit of work handed to a process (0: --batch)")
    p.add_argument("--quiet", action="store_true", help="no progress bar, warnings only")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    args = build_parser().parse_args(argv)
    setup_logging(args.quiet)
    from agnostos_mjx.tasks import parse_tasks

    try:
        if args.demos < 1 or args.batch < 1 or args.image_size < 8 or args.max_attempts < 1:
            raise ValueError("--demos, --batch, --max-attempts must be >= 1, --image-size >= 8")
        if args.workers < 0 or args.chunk < 0:
            raise ValueError("--workers and --chunk must be >= 0")
        problem = check_writable_dir(args.out)
        if problem:
            raise ValueError(f"--out: {problem}")
        cfg = GenerateConfig(
            out=args.out, tasks=tuple(t.name for t in parse_tasks(args.tasks)),
            demos=args.demos, seed=args.seed, backend=args.backend, batch=args.batch,
            image_size=args.image_size,
            cameras=tuple(c.strip() for c in args.cameras.split(",") if c.strip()),
            max_attempts=args.max_attempts, quiet=args.quiet, workers=args.workers,
            chunk=args.chunk)
        report = generate(cfg)
    except (KeyError, ValueError, BankError) as err:
        print(f"error: {err.args[0] if isinstance(err, KeyError) else err}", file=sys.stderr)
        return 2
    except OSError as err:  # e.g. the disk filled up
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(report["markdown"], end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
