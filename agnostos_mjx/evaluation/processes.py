"""``python -m agnostos_mjx.eval --local-processes N``: one run as N processes on this machine.

Each process is the same command with ``--num-processes N --process-id I`` (every N-th task
into ``--out/proc-I``, its log in ``--out/proc-I.log``); when all have finished, their
records are merged into ``--out`` as one process would have written them (summary.merge).

Why: with MJX-Warp at the protocol's batch of 75 a physics step leaves the GPU mostly idle
(its cost is latency, not work), so tasks run side by side: on one H100 the main job took
407 s as 8 processes with warm caches, where physics alone bounds one process at >= 170 s
and a cold single process took 985 s (eval/reports/gpu_h100_session14).  Each
process gets ``0.6 / N`` of the GPU's memory for JAX unless ``--gpu-mem-fraction`` says
otherwise (Warp allocates its CUDA graphs outside JAX's pool; 0.9 / 8 ran out).
Ctrl-C stops every process; the same command with ``--resume`` continues each.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from agnostos_mjx.evaluation.config import EvalConfig
from agnostos_mjx.evaluation.records import EPISODES_FILE
from agnostos_mjx.evaluation.summary import merge_main

log = logging.getLogger("agnostos_mjx.eval")
JAX_MEMORY_SHARE = 0.6  # of the card, split over the processes


def _without(argv: Sequence[str], flag: str) -> list[str]:
    """`argv` without `flag` and its value (``--flag N`` or ``--flag=N``)."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == flag:
            skip = True
        elif not arg.startswith(flag + "="):
            out.append(arg)
    return out


def _episodes_done(out: Path, n: int) -> int:
    total = 0
    for i in range(n):
        path = out / f"proc-{i}" / EPISODES_FILE
        if path.exists():
            with path.open("rb") as f:
                total += sum(1 for _ in f)
    return total


def main(cfg: EvalConfig, argv: Sequence[str]) -> int:
    """``--local-processes N``: the run of `argv` as N processes, then merged; the exit code."""
    if cfg.out is None:
        print("error: --local-processes needs --out DIR, the folder the processes share",
              file=sys.stderr)
        return 2
    if cfg.num_processes > 1 or cfg.coordinator:
        print("error: --local-processes starts its own processes; drop --num-processes, "
              "--process-id and --coordinator", file=sys.stderr)
        return 2
    return run(argv, cfg.local_processes, Path(cfg.out), cfg.quiet, cfg.gpu_mem_fraction)


def run(argv: Sequence[str], n: int, out: Path, quiet: bool, memory_fraction: float | None,
        poll_s: float = 5.0) -> int:
    """Start the N processes, wait for them, merge; the exit code (130 if interrupted)."""
    child = _without(argv, "--local-processes")
    if memory_fraction is None and not os.environ.get("AGNOSTOS_GPU_MEM_FRACTION"):
        child += ["--gpu-mem-fraction", f"{JAX_MEMORY_SHARE / n:.4f}"]
    out.mkdir(parents=True, exist_ok=True)
    package_root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ,
           "PYTHONPATH": os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
    procs: list[subprocess.Popen] = []
    logs = []
    t0 = time.perf_counter()
    try:
        for i in range(n):
            logs.append((out / f"proc-{i}.log").open("w"))
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "agnostos_mjx.eval", *child, "--quiet",
                 "--num-processes", str(n), "--process-id", str(i)],
                stdout=logs[-1], stderr=subprocess.STDOUT, env=env,
                start_new_session=True))  # Ctrl-C reaches them once, forwarded below
        log.info("%d processes started; logs in %s/proc-I.log", n, out)
        last = -1
        while any(p.poll() is None for p in procs):
            time.sleep(poll_s)
            done = _episodes_done(out, n)
            if not quiet and done != last:
                log.info("%d episodes done, %.0f s", done, time.perf_counter() - t0)
                last = done
    except KeyboardInterrupt:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
        print(f"interrupted: finished episodes are saved in {out}/proc-*; run the same "
              "command with --resume to continue", file=sys.stderr)
        return 130
    finally:
        for f in logs:
            f.close()
    failed = [(i, p.returncode) for i, p in enumerate(procs) if p.returncode != 0]
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
    if failed:
        return 1
    log.info("%d processes finished in %.0f s; merging", n, time.perf_counter() - t0)
    return merge_main(str(out))
