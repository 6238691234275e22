"""``python -m agnostos_mjx.eval --local-processes N``: one run as N processes on this machine.

Each process runs the launcher's config with ``--num-processes N --task-queue --out/queue``,
read from ``--out/run_spec.json`` (``--spec FILE --process-id I``: the run is not parsed
again from flags), into ``--out/proc-I``, its log in ``--out/proc-I.log``: whenever a process is
free it takes the next task no other process has taken, longest expected first
(task_queue.py); when all have finished, their records are merged into ``--out`` as one
process would have written them (summary.merge).

Why: with MJX-Warp at the protocol's batch of 75 a physics step leaves the GPU mostly idle
(its cost is latency, not work), so tasks run side by side in processes (figures in
docs/performance.md).  Each process gets ``0.6 / K`` of its GPU's memory for JAX, K being
the most processes on one GPU, unless ``--gpu-mem-fraction`` says otherwise (Warp allocates its CUDA graphs outside JAX's
pool; 0.9 / 8 ran out).

GPU placement: with G > 1 GPUs visible (the entries of CUDA_VISIBLE_DEVICES, else the
GPUs ``nvidia-smi -L`` lists), process I runs on GPU I % G alone (round-robin): its
CUDA_VISIBLE_DEVICES is that one entry, so CUDA_VISIBLE_DEVICES=0,1,2,3 and N = 6 put
processes 0..5 on GPUs 0, 1, 2, 3, 0, 1.  With one GPU or none the processes keep this
process's environment, as before.

CUDA MPS (``--mps``, agnostos_mjx/infra/mps.py): processes sharing a GPU without MPS time-slice
it (8 processes together ran slower than one; under MPS several times faster:
docs/performance.md).  For each GPU that two or more processes share, ``auto`` (the default)
and ``on`` start a private MPS control daemon for the run (pipe and log folders
``--out/mps/pipe|log``, or ``--out/mps/gpu<K>/pipe|log`` with several GPUs), give its
processes CUDA_MPS_PIPE_DIRECTORY / CUDA_MPS_LOG_DIRECTORY (and no CUDA_VISIBLE_DEVICES:
the daemon, started with its GPU's, shows them that GPU alone), and stop it when the run
ends, fails, is interrupted (Ctrl-C, SIGTERM) or cannot start.  A daemon that already
answers on $CUDA_MPS_PIPE_DIRECTORY (default /tmp/nvidia-mps) is used instead.  When MPS
cannot start, ``auto`` warns once and runs without it, ``on`` exits with 2; ``off`` starts
none and warns once that the processes will time-slice.  Without a GPU --mps does nothing
and the log says so once (``on``: exit 2).

Ctrl-C (or SIGTERM) stops every process; the same command with ``--resume`` continues each.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO

from agnostos_mjx.evaluation import report_plot, task_queue
from agnostos_mjx.evaluation.config import EvalConfig, write_spec
from agnostos_mjx.evaluation.records import EPISODES_FILE
from agnostos_mjx.evaluation.summary import merge_main
from agnostos_mjx.infra import mps
from agnostos_mjx.infra.cli import process_age_s
from agnostos_mjx.infra.settings import GPU_MEM_FRACTION

log = logging.getLogger("agnostos_mjx.eval")
JAX_MEMORY_SHARE = 0.6  # of the card, split over the processes
# --local-processes by default on a GPU host: the main job's fastest count there, 8 per
# GPU, no faster beyond (docs/performance.md); each wants two cores.
PROCESSES_PER_GPU = 8
MAX_DEFAULT_PROCESSES = 16
QUEUE_DIR = "queue"  # --out/queue: the claims of the processes (task_queue.py)
SPEC_FILE = "run_spec.json"  # --out/run_spec.json: the processes' config (--spec)


def _episodes_done(out: Path, n: int) -> int:
    total = 0
    for i in range(n):
        path = out / f"proc-{i}" / EPISODES_FILE
        if path.exists():
            with path.open("rb") as f:
                total += sum(1 for _ in f)
    return total


def default_count(cfg: EvalConfig, environ: dict[str, str] | None = None) -> tuple[int, str]:
    """--local-processes when not given: PROCESSES_PER_GPU per visible NVIDIA GPU, at most
    MAX_DEFAULT_PROCESSES, half the usable cores and one per (task, seed) of the run; one
    process without a GPU, for a process of a larger run, and for --resume without --out.
    Returns (count, why)."""
    from agnostos_mjx.infra.settings import usable_cores
    from agnostos_mjx.tasks.catalog import parse_task_names

    run = cfg.run
    if run.num_processes > 1 or run.coordinator or (run.resume and run.out is None):
        return 1, "one process of a run"
    gpus, source = mps.visible_gpus(dict(os.environ if environ is None else environ))
    if not gpus:
        return 1, source
    cores = usable_cores()
    units = len(parse_task_names(cfg.protocol.tasks)) * len(cfg.protocol.seeds)
    n = max(1, min(PROCESSES_PER_GPU * len(gpus), MAX_DEFAULT_PROCESSES, cores // 2, units))
    return n, f"{len(gpus)} GPU(s) and {cores} cores"


def main(cfg: EvalConfig) -> int:
    """``--local-processes N``: the run of `cfg` as N processes, then merged; the exit code."""
    if cfg.run.out is None:
        print("error: --local-processes needs --out DIR, the folder the processes share",
              file=sys.stderr)
        return 2
    if cfg.run.num_processes > 1 or cfg.run.coordinator:
        print("error: --local-processes starts its own processes; drop --num-processes, "
              "--process-id and --coordinator", file=sys.stderr)
        return 2
    return run(cfg)


def gpu_setup(n: int, out: Path, mode: str, environ: dict[str, str],
              daemons: mps.Daemons) -> tuple[list[dict[str, str]], int]:
    """Each process's environment (GPU placement and MPS, see the module docstring) and
    the most processes that share one GPU; starts `daemons`.  mps.MpsError: --mps on and
    MPS cannot run."""
    gpus, source = mps.visible_gpus(environ)
    if not gpus:
        if mode == "on":
            raise mps.MpsError(f"no GPU visible ({source})")
        log.info("no GPU visible (%s): --mps has no effect", source)
        return [dict(environ) for _ in range(n)], n
    where = mps.placement(n, len(gpus))
    if len(gpus) > 1:
        log.info("%d processes on %d GPUs (%s), process I on GPU I %% %d: "
                 "CUDA_VISIBLE_DEVICES %s", n, len(gpus), source, len(gpus),
                 ", ".join(gpus[k] for k in where if k is not None))
    busy = mps.shared(where)
    sharing = sum(1 for k in where if k in busy)
    if not busy:
        log.info("each process has a GPU of its own: no CUDA MPS needed")
    elif (pipe := mps.running_daemon(environ)) is not None:
        log.info("a CUDA MPS daemon answers in %s already: the processes use it", pipe)
    elif mode == "off":
        log.warning("--mps off: %s", mps.time_slice_warning(sharing, len(busy)))
    else:
        try:
            t0 = time.perf_counter()
            daemons.start(out, gpus, busy)
            log.info("CUDA MPS serves %d GPU(s), checked in %.1f s", len(busy),
                     time.perf_counter() - t0)
        except mps.MpsError as e:
            daemons.close()
            if mode == "on":
                raise
            log.warning("--mps auto: CUDA MPS could not be started (%s); %s", e,
                        mps.time_slice_warning(sharing, len(busy)))
    one = len(gpus) > 1  # one GPU each: say which; else the launcher's environment
    envs = [mps.child_env(environ, gpus[k] if one and k is not None else None,
                          daemons.of(k)) for k in where]
    return envs, max(where.count(k) for k in set(where))


# Seconds Ctrl-C may take: the processes get up to 60 s to save their episodes, then are
# killed (eval's InterruptGuard would otherwise end this process after its default 3 s,
# before it has said where the results are).
STOP_GRACE_S = 90.0
EXIT_POLL_S = 0.1  # how soon the launcher sees its last process exit


def interrupted_text(out: Path) -> str:
    return (f"interrupted: finished episodes are saved in {out}/proc-*; run the same command "
            "with --resume to continue")


def _wrote_results(out: Path, i: int) -> bool:
    """Process `i` has written its final results (it may still be ending)."""
    return (out / f"proc-{i}" / task_queue.FINISHED_FILE).exists()


def _finished(out: Path, i: int, proc: subprocess.Popen) -> bool:
    """Process `i` has ended, or has written its final results and is ending."""
    return proc.poll() is not None or _wrote_results(out, i)


def _merge(out: Path, n: int, t0: float) -> int:
    log.info("%d processes finished in %.0f s; merging", n, time.perf_counter() - t0)
    return merge_main(str(out))


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def run(cfg: EvalConfig, poll_s: float = 5.0, command: Sequence[str] | None = None) -> int:
    """Start cfg's --local-processes N processes into its --out, wait for them, merge; the
    exit code (130 if interrupted, 2 if --mps on cannot start MPS).  `command` replaces
    ``python -m agnostos_mjx.eval`` (tests).  SIGTERM is handled as Ctrl-C."""
    n, out, quiet, mps_mode = (cfg.run.local_processes or 1, Path(cfg.run.out or "."),
                               cfg.run.quiet, cfg.run.mps)
    out.mkdir(parents=True, exist_ok=True)
    package_root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ,
           "PYTHONPATH": os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
    command = list(command or [sys.executable, "-m", "agnostos_mjx.eval"])
    daemons = mps.Daemons(env)
    procs: list[subprocess.Popen] = []
    logs: list[IO[str]] = []
    main_thread = threading.current_thread() is threading.main_thread()
    old_term = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    t0 = time.perf_counter()
    try:
        try:
            envs, per_gpu = gpu_setup(n, out, mps_mode, env, daemons)
        except mps.MpsError as e:
            print(f"error: --mps {mps_mode}: {e}", file=sys.stderr)
            return 2
        spec = _child_spec(cfg, out, n, per_gpu)
        _start(command, ["--spec", str(spec)], n, out, envs, procs, logs)
        _wait(procs, out, poll_s, quiet, t0)
        # Every process has written its final results: merge while they end (their
        # interpreters' teardown), unless one ended without them.
        merged = None
        if all(_wrote_results(out, i) for i in range(n)):
            merged = _merge(out, n, t0)
        daemons.stop()  # MPS quits as its clients end: the two teardowns overlap
        for p in procs:
            p.wait()
    except KeyboardInterrupt:
        _stop(procs, daemons)
        print(interrupted_text(out), file=sys.stderr)
        return 130
    finally:
        for f in logs:
            f.close()
        daemons.close()
        if main_thread:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if old_term is None else old_term)
    failed = [(i, p.returncode) for i, p in enumerate(procs) if p.returncode != 0]
    _report_failures(failed, out)
    # A process whose task failed (results.json's failed_tasks) still finished the others.
    if failed and not all((out / f"proc-{i}" / "results.json").exists() for i, _ in failed):
        return 1
    return max(_merge(out, n, t0) if merged is None else merged, 1 if failed else 0)


def _child_spec(cfg: EvalConfig, out: Path, n: int, per_gpu: int) -> Path:
    """Writes the processes' common config to out/SPEC_FILE and returns its path: `cfg` as
    one process of N on the shared task queue (prepared here, a resumed run's tasks kept by
    their processes), with each one's share of GPU memory."""
    queue = out / QUEUE_DIR
    owners = task_queue.prepare(queue, out, n)  # resumed tasks stay with their process
    if owners:
        log.info("%d tasks stay with the processes that have episodes of them",
                 sum(task_queue.SEED_UNIT not in unit for unit in owners))
    for stale in out.glob(f"proc-*/{task_queue.FINISHED_FILE}"):  # a resumed run's
        stale.unlink()
    fraction = cfg.run.gpu_mem_fraction
    if fraction is None and GPU_MEM_FRACTION.get() is None:
        fraction = round(JAX_MEMORY_SHARE / per_gpu, 4)
    path = out / SPEC_FILE
    write_spec(path, cfg.with_options(
        num_processes=n, process_id=0, local_processes=1, task_queue=str(queue),
        gpu_mem_fraction=fraction, quiet=True, out=str(out)))
    return path


def _start(command: list[str], child: list[str], n: int, out: Path,
           envs: list[dict[str, str]], procs: list[subprocess.Popen],
           logs: list[IO[str]]) -> None:
    """Starts the N processes into `procs` (their logs into `logs`, appended one by one so
    that the caller closes and stops whatever started before a failure)."""
    for i in range(n):
        logs.append((out / f"proc-{i}.log").open("w"))
        procs.append(subprocess.Popen(
            [*command, *child, "--process-id", str(i)],
            stdout=logs[-1], stderr=subprocess.STDOUT, env=envs[i],
            start_new_session=True))  # Ctrl-C reaches them once, forwarded by `_stop`
    log.info("%d processes started %.1f s after the launcher; logs in %s/proc-I.log", n,
             process_age_s() or 0.0, out)
    # Imported while they run, for the merge's plot; on a thread of its own, so that no
    # handler in matplotlib's import can swallow a Ctrl-C meant for the wait's loop.
    threading.Thread(target=report_plot.pyplot, name="import-pyplot", daemon=True).start()


def _wait(procs: list[subprocess.Popen], out: Path, poll_s: float, quiet: bool,
          t0: float) -> None:
    """Until every process has ended or written its final results, logging the episodes
    done every `poll_s` when the count has moved."""
    n = len(procs)
    last, next_report = -1, time.perf_counter() + poll_s
    while not all(_finished(out, i, p) for i, p in enumerate(procs)):
        time.sleep(min(EXIT_POLL_S, poll_s))  # the merge starts as the last one finishes
        if time.perf_counter() < next_report:
            continue
        next_report += poll_s
        done = _episodes_done(out, n)
        if not quiet and done != last:
            log.info("%d episodes done, %.0f s", done, time.perf_counter() - t0)
            last = done


def _stop(procs: list[subprocess.Popen], daemons: mps.Daemons) -> None:
    """Ctrl-C: forwards it to the running processes, stops MPS, waits for them to save."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    daemons.stop()  # at once: eval's InterruptGuard may end this process before finally
    for p in procs:
        try:
            p.wait(timeout=60)
        except subprocess.TimeoutExpired:
            p.kill()


def _report_failures(failed: list[tuple[int, int]], out: Path) -> None:
    """Each failed process's exit code and its log's last lines, a repeated tail once."""
    shown: set[str] = set()  # a usage error fails every process alike: say it once
    for i, code in failed:
        tail = "\n  ".join(
            (out / f"proc-{i}.log").read_text(errors="replace").strip().splitlines()[-5:])
        if tail in shown:
            print(f"error: process {i} exited with {code} (the same)", file=sys.stderr)
            continue
        shown.add(tail)
        print(f"error: process {i} exited with {code}; last lines of {out}/proc-{i}.log:\n  "
              + tail, file=sys.stderr)
