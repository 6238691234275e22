"""Evaluate a policy on AGNOSTOS tasks: ``python -m agnostos_mjx.eval``.

The protocol follows X-ICM's evaluation (docs/protocol.md):
per task and seed a success rate over `--episodes` episodes; per task the
mean and population std (ddof=0) over seeds; Level-1 / Level-2 / All the
mean over that group's tasks per seed, then mean and population std over
seeds.

Episodes are reproducible and independent of batching: episode `e` of seed
`s` samples its scene from ``fold_in(PRNGKey(s), e)`` and, where the
variation is sampled, its variation from ``fold_in(that key, 1)``.  The
episodes of all seeds of a task are pooled and simulated `--batch` worlds at
a time.

Outputs in `--out` (default ``results/<policy>-<timestamp>``, created when the
run starts): episodes.jsonl (one JSON line per episode, appended and fsync'd as
each world finishes, the basis of --resume: an interrupted run keeps every
finished episode, and a torn last line is ignored), results.json (config,
versions, aggregates and the episode records), results.csv (one row per task and
group; its columns: agnostos_mjx/evaluation/summary.py), results.md (the table
that is also printed) and results.png.

Ctrl-C stops a run within seconds and prints the command that continues it
(the same options with ``--out DIR --resume``); a second Ctrl-C exits at once.

This module is the command line; the evaluator is the package agnostos_mjx.evaluation
(config, protocol, rollout, scheduler, records, summary, processes, run).

Examples::

    python -m agnostos_mjx.eval                  # the main job: auto policy (X-ICM with an LLM, else retrieval)
    python -m agnostos_mjx.eval --policy oracle --tasks all       # the experts on all 41 tasks
    python -m agnostos_mjx.eval --tasks lamp_on --seeds 0 --episodes 4
    python -m agnostos_mjx.eval --policy my_pkg.agent:MyPolicy --policy-arg model=\"qwen\"
    python -m agnostos_mjx.eval --out results/run1 --resume      # finish an interrupted run
    python -m agnostos_mjx.eval --policy remote --policy-url ws://localhost:8000  # a served VLA
"""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from agnostos_mjx import warmup
from agnostos_mjx.evaluation import processes
from agnostos_mjx.evaluation.config import (
    EvalConfig,
    UsageError,
    parse_config,
    policy_spec,
    resolve_policy,
)
from agnostos_mjx.evaluation.records import default_out, interrupted_message
from agnostos_mjx.evaluation.summary import (
    failed_task_summary,
    merge_main,
    policy_error_summary,
    request_summaries,
)
from agnostos_mjx.infra import settings
from agnostos_mjx.infra.cli import (
    InterruptGuard,
    hard_exit,
    quick_exit,
    remove_empty_dirs,
    setup_logging,
)
from agnostos_mjx.policies.base import policy_help
from agnostos_mjx.tasks.catalog import parse_task_names

log = logging.getLogger("agnostos_mjx.eval")


def main(argv: Sequence[str] | None = None, guard: InterruptGuard | None = None) -> int:
    """Command-line entry point; returns the exit code (2 for usage errors, 1 for file
    errors, 3 when most requests to a server failed or most episodes ended as policy_error,
    130 when interrupted).  `guard` (the
    command line's) bounds Ctrl-C's delay."""
    settings.configure_jax()  # before JAX is imported: its environment, no import
    argv = list(sys.argv[1:] if argv is None else argv)
    cfg = parse_config(argv)
    if cfg.run.merge:
        setup_logging(cfg.run.quiet)
        return merge_main(cfg.run.out)
    try:  # before any warm-up or process starts (the names' check imports no JAX)
        parse_task_names(cfg.protocol.tasks)
    except KeyError as e:
        print(f"error: {e.args[0]}", file=sys.stderr)
        return 2
    try:  # a bad --policy-arg is one line, before anything starts
        if "help" in cfg.policy.args:
            print(policy_help(policy_spec(cfg)[0]))
            return 0
        resolve_policy(cfg)
    except Exception as e:  # noqa: BLE001 - e.g. an unknown option, an LLM URL without a model
        print(f"error: {e}", file=sys.stderr)
        return 2
    if cfg.run.local_processes is None:
        argv = default_processes(cfg, argv)
    # What every process of a run would compile alike, once per machine and before them.
    code = None
    if warmup.builds_kernels(cfg.protocol.backend) and cfg.run.num_processes == 1:
        setup_logging(cfg.run.quiet)
        code = warmup.ensure_warp_kernels(cfg)
    elif cfg.run.local_processes > 1:
        setup_logging(cfg.run.quiet)
        code = warmup.ensure_shared_programs(cfg)
    if code == warmup.USAGE_ERROR:  # e.g. a policy that cannot load: said, in one line
        return 2
    if cfg.run.local_processes > 1:
        setup_logging(cfg.run.quiet)
        if guard is not None and cfg.run.out:  # the resume hint even if stopping takes long
            guard.message = processes.interrupted_text(Path(cfg.run.out))
            guard.grace_s = processes.STOP_GRACE_S
        return processes.main(cfg)  # the launcher imports no JAX: its processes do
    from agnostos_mjx.evaluation.run import evaluate, resolve_out

    try:
        spec, _, note = resolve_policy(cfg)
    except Exception as e:  # e.g. an LLM URL without a model
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"agnostos_mjx.eval: policy {spec}" + (f" ({note})" if note else ""), flush=True)
    setup_logging(cfg.run.quiet)
    try:
        start_devices(cfg, spec)
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out_dir = None
    try:
        out_dir = resolve_out(cfg, spec)
        existed = out_dir.exists()
        message = functools.partial(interrupted_message, out_dir, argv, Path(cfg.run.out))
        if guard is not None:
            guard.message = message
        results = evaluate(cfg)
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if guard is not None:
            guard.announce()
        else:
            print(message(), file=sys.stderr)
        return 130
    except OSError as e:  # e.g. the disk filled up
        print(f"error: {e}", file=sys.stderr)
        return 1
    finally:
        if out_dir is not None and not existed:
            remove_empty_dirs(out_dir)  # a run that failed before its first result
    print(results["markdown"], end="", flush=True)
    log.info("wrote %s", cfg.run.out)
    return max(request_summaries(results), policy_error_summary(results),
               failed_task_summary(results))


def default_processes(cfg: EvalConfig, argv: list[str]) -> list[str]:
    """Sets cfg.run.local_processes to the machine's default (processes.default_count) and
    returns the command line its processes get (with the run's folder, chosen here)."""
    n, why = processes.default_count(cfg)
    cfg.run.local_processes = n
    if n == 1:
        return argv
    if cfg.run.out is None:
        try:
            cfg.run.out = str(default_out(resolve_policy(cfg)[0]))
        except Exception:  # noqa: BLE001 - one process reports the policy's error
            cfg.run.local_processes = 1
            return argv
        argv = [*argv, "--out", cfg.run.out]
    print(f"agnostos_mjx.eval: {n} processes ({why}; --local-processes 1 runs one)",
          flush=True)
    return argv


def start_devices(cfg: EvalConfig, spec: str) -> None:
    """Cap JAX's GPU memory (before JAX starts its backend) and join the JAX cluster of
    --coordinator (before anything touches a device)."""
    from agnostos_mjx.infra.gpu import apply_memory_limit

    served = cfg.policy.url or settings.POLICY_URL.get()
    servers = {"remote": served, "openvla": served,
               "xicm": cfg.xicm.llm_url or settings.LLM_URL.get()}
    run = cfg.run
    try:
        apply_memory_limit(run.gpu_mem_fraction, [servers.get(spec)])
    except ValueError as e:
        raise UsageError(f"--gpu-mem-fraction: {e}") from None
    if run.coordinator:
        import jax

        jax.distributed.initialize(run.coordinator, run.num_processes, run.process_id)


def cli() -> int:
    """The command (``python -m agnostos_mjx.eval``, ``agnostos-eval``): `main` under a
    Ctrl-C guard; an interrupted run exits at once with 130, and so does one of a
    launcher's processes once its results are written: the launcher waits on its exit,
    which the interpreter's teardown of JAX and Warp would delay (docs/performance.md)."""
    with InterruptGuard() as guard:
        try:
            code = main(guard=guard)
        except KeyboardInterrupt:  # outside the run (printing the table, say)
            guard.announce()
            code = 130
    if code == 130:
        hard_exit(code)  # threads in native code must not delay the exit
    if launched_process(sys.argv[1:]):
        quick_exit(code)
    return code


def launched_process(argv: Sequence[str]) -> bool:
    """Whether `argv` is one of a launcher's processes (evaluation/processes.py starts them
    with ``--spec FILE --process-id I``)."""
    return "--spec" in argv and "--process-id" in argv


if __name__ == "__main__":
    sys.exit(cli())
