"""One evaluation run: `evaluate(cfg)` and the folder it writes.

The folder (--out, default ``results/<policy>-<timestamp>``) is checked before anything is
loaded and created when the first episode finishes; a process of a multi-process run
writes into its own ``proc-I`` inside it.  A run resumed with --resume skips the episodes
its episodes.jsonl already holds.
"""

from __future__ import annotations

import functools
import json
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from datetime import datetime
from pathlib import Path
from typing import Any

from agnostos_mjx.evaluation.config import EvalConfig, UsageError, loading_policy, resolve_policy
from agnostos_mjx.evaluation.dense import check_action_mode
from agnostos_mjx.evaluation.protocol import pending_episodes, process_share, select_tasks
from agnostos_mjx.evaluation.records import (
    EPISODES_FILE,
    append_records,
    default_out,
    latest_run,
    record_key,
    repair_records,
)
from agnostos_mjx.evaluation.rollout import Steps, task_steps
from agnostos_mjx.evaluation.scheduler import run_interleaved
from agnostos_mjx.evaluation.summary import write_outputs
from agnostos_mjx.evaluation.task_queue import (
    FINISHED_FILE,
    TaskQueue,
    claim_order,
    split_by_seed,
    unit_task,
)
from agnostos_mjx.evaluation.timings import TIMINGS_FILE
from agnostos_mjx.infra.cli import (
    Progress,
    atomic_write,
    check_writable_dir,
    process_age_s,
    progress_bar,
    versions,
)
from agnostos_mjx.physics.capabilities import RenderRoute
from agnostos_mjx.policies.base import Policy

log = logging.getLogger("agnostos_mjx.eval")


# ---- the run's folder --------------------------------------------------------------------
def process_dir(out: Path, cfg: EvalConfig) -> Path:
    """Where this process writes: `out` itself, or out/proc-I when several processes share
    it, so each keeps its own episodes.jsonl (and --resume) with no file locking."""
    return out / f"proc-{cfg.run.process_id}" if cfg.run.num_processes > 1 else out


def resolve_out(cfg: EvalConfig, spec: str) -> Path:
    """Sets cfg.run.out (default results/<policy>-<timestamp>) and checks, before anything
    is loaded or created, that the run can write there."""
    if cfg.run.out is None and cfg.run.num_processes > 1:
        raise UsageError("--num-processes needs --out DIR, the folder the processes share")
    if cfg.run.out is None:
        if cfg.run.resume:
            latest = latest_run()
            hint = f" (the latest run is {latest})" if latest else ""
            raise UsageError(f"--resume needs --out DIR, the folder of the run to continue"
                             f"{hint}")
        cfg.run.out = str(default_out(spec))
    if not 0 <= (i := cfg.run.process_id) < (n := cfg.run.num_processes):
        raise UsageError(f"--process-id {i}: expected 0..{n - 1}")
    out_dir = process_dir(Path(cfg.run.out), cfg)
    problem = check_writable_dir(out_dir)
    if problem:
        raise UsageError(f"--out: {problem}")
    if (out_dir / EPISODES_FILE).exists() and not cfg.run.resume:
        raise UsageError(f"{out_dir / EPISODES_FILE} exists; pass --resume to continue that "
                         f"run or choose another --out")
    return out_dir


# ---- checks and loading ------------------------------------------------------------------
def _check_video(cfg: EvalConfig) -> None:
    if cfg.run.video:
        from agnostos_mjx.evaluation.video import VideoSpec

        try:
            VideoSpec.parse(cfg.run.video, cfg.run.video_cameras)
        except ValueError as e:
            raise UsageError(str(e)) from None


def _check_compare(cfg: EvalConfig) -> None:
    if cfg.run.compare:
        from agnostos_mjx.evaluation.paper import published

        try:
            published(cfg.run.compare)
        except KeyError as e:
            raise UsageError(f"--compare: {e.args[0]}") from None


def load_policy(cfg: EvalConfig) -> tuple[str, str, Policy]:
    """(spec, note, the policy) of `cfg`; a policy that cannot load is a UsageError."""
    from agnostos_mjx.policies import make_policy

    spec, kwargs, note = resolve_policy(cfg)
    if note:
        log.info("%s", note)
    with loading_policy(spec):
        policy = make_policy(spec, **kwargs)
    return spec, note, policy


def observation_route(cfg: EvalConfig, policy: Policy, backend: str) -> RenderRoute | None:
    """The route the policy's observations render through (None: it declares none),
    chosen once for the run and logged."""
    from agnostos_mjx.physics import render_route

    spec = policy.observation_spec
    if spec is None:
        return None
    chosen = cfg.protocol.renderer
    route = render_route(chosen if chosen != "auto" else spec.renderer, backend)
    log.info("observations: %s at %dx%d rendered by %s", ",".join(spec.cameras), spec.height,
             spec.width, route.label)
    return route


# ---- the run -----------------------------------------------------------------------------
def _steps_of(name: str, *args: Any) -> Steps:
    """`task_steps` of the task called `name`, its module imported when the job starts: a
    process of a task queue imports only the tasks it claims (each task module's `jnp`
    constants run op by op on a GPU)."""
    from agnostos_mjx.tasks import get_task

    return (yield from task_steps(get_task(name), *args))


def evaluate(cfg: EvalConfig) -> dict:
    """Run the evaluation described by `cfg`, write the outputs, return results.json's dict."""
    return Run(cfg).run()


class Run:
    """One process's evaluation: the state its callbacks share (the folder, the records,
    the queue, the failed tasks) in one object, so the scheduler and the rollout call
    methods rather than closures.  Built: checked, placed, policy loaded, episodes planned;
    `run()` runs them and writes the outputs."""

    def __init__(self, cfg: EvalConfig) -> None:
        self.cfg = cfg
        self.startup = {"imports_s": process_age_s()}  # a process's start-up (timings)
        self.failed: dict[str, str] = {}  # task -> its error, for a task that raised
        self.todo: list[tuple[str, str, list[tuple[int, int]]]] = []
        self.done: dict[str, tuple[int, float]] = {}
        self.progress: Progress | None = None  # the bar while the tasks run
        self._place()
        _check_compare(cfg)
        self.spec, self.note, self.policy = load_policy(cfg)
        self.startup["policy_s"] = process_age_s()
        check_action_mode(cfg, self.policy)
        policy = self.policy
        self.policy_class = f"{type(policy).__module__}.{type(policy).__qualname__}"
        log.info("policy %s (%s)", policy.name, self.policy_class)
        self._plan()
        started = datetime.now().isoformat(timespec="seconds")
        self.t0 = time.perf_counter()
        route = observation_route(cfg, policy, self.backend)
        if route is not None and route.preload:  # overlaps the first task's build and reset
            from agnostos_mjx.render.warp import preload

            preload()
        self.meta = {"config": asdict(cfg),
                     "policy": {"spec": self.spec, "name": policy.name, "note": self.note,
                                "class": self.policy_class,
                                "privileged": bool(policy.privileged)},
                     "backend": self.backend, "renderer": route and route.name,
                     "versions": versions(),
                     "started": started, "tasks": self.all_tasks}

    def _place(self) -> None:
        """The run's tasks, folder and backend, and this process's share of the tasks."""
        from agnostos_mjx.infra import gather, sharding
        from agnostos_mjx.physics import resolve_backend

        cfg = self.cfg
        tasks = select_tasks(cfg)  # names: a task's module is imported when it starts
        self.all_tasks = list(tasks)
        _check_video(cfg)
        self.out_dir = resolve_out(cfg, resolve_policy(cfg)[0])
        self.episodes_path = self.out_dir / EPISODES_FILE
        sharding.configure(cfg.run.devices)
        self.backend = resolve_backend(cfg.protocol.backend, cfg.protocol.batch)
        self.queue: TaskQueue | None = None
        # Tasks from a shared queue run beside whichever others this process got first:
        # their requests then go alone (agnostos_mjx/infra/gather.py).
        gather.allow_gathering(cfg.run.task_queue is None)
        if cfg.run.task_queue is not None:  # its balanced share first (claim_order, `_todo`)
            self.queue = TaskQueue(Path(cfg.run.task_queue), cfg.run.process_id)
            log.info("process %d of %d: tasks from the queue %s", cfg.run.process_id,
                     cfg.run.num_processes, cfg.run.task_queue)
        else:
            tasks = process_share(tasks, cfg)
            if cfg.run.num_processes > 1:
                log.info("process %d of %d: %s", cfg.run.process_id, cfg.run.num_processes,
                         ", ".join(tasks) or "no task")
        self.tasks = tasks

    def _plan(self) -> None:
        """The records already written (--resume) and each task's pending episodes."""
        cfg, tasks, name = self.cfg, self.tasks, self.policy.name
        self.records = repair_records(self.episodes_path) if cfg.run.resume else []
        if self.records:
            earlier = {r.get("policy") for r in self.records} - {None}
            if earlier and earlier != {name}:
                log.warning("%s holds episodes of policy %s; continuing with %s",
                            self.out_dir, ", ".join(sorted(earlier)), name)
        recorded = {record_key(r) for r in self.records}
        self.plan = {task: pending_episodes(task, cfg, recorded) for task in tasks}
        self.total = sum(map(len, self.plan.values()))
        seeds, episodes = cfg.protocol.seeds, cfg.protocol.episodes
        skipped = len(tasks) * len(seeds) * episodes - self.total
        log.info("%d tasks (%s), seeds %s, %d episodes each: %d to run%s", len(tasks),
                 ", ".join(tasks), ",".join(map(str, seeds)), episodes,
                 self.total, f", {skipped} already recorded" if skipped else "")

    # ---- what the callbacks read and write
    def mine(self) -> list[str]:
        """The tasks this process runs (with a queue: has claimed)."""
        if self.queue is None:
            return list(self.tasks)
        return list(dict.fromkeys(unit_task(unit)[0] for unit in self.queue.mine))

    def selected(self) -> list[dict]:
        """The records of this process's tasks, seeds and episodes."""
        names, seeds = set(self.mine()), set(self.cfg.protocol.seeds)
        return [r for r in self.records if r["task"] in names and int(r["seed"]) in seeds
                and int(r["episode"]) < self.cfg.protocol.episodes]

    def write_results(self, final: bool) -> dict:
        """The outputs so far (after each task, so a stopped run keeps its tables)."""
        # policy.report(): requests, retries, failures, what was sent (LLM, policy server)
        extra = {**self.policy.report(),
                 **({"failed_tasks": self.failed} if self.failed else {})}
        # A process of a multi-process run draws no plot: the merge draws the run's.
        return write_outputs(self.out_dir, self.meta, self.selected(), self.mine(), self.cfg,
                             time.perf_counter() - self.t0, final, extra,
                             plot=self.cfg.run.num_processes == 1)

    def on_error(self, index: int, error: Exception) -> None:
        """A task that raised: the others go on, unless the error is the run's own."""
        if isinstance(error, UsageError):  # e.g. answers of the wrong shape: the run stops
            raise error
        name = self.todo[index][1]
        self.failed[name] = f"{type(error).__name__}: {error}"
        log.error("%s failed, the other tasks go on (its episodes not recorded run again "
                  "with --resume): %s", name, self.failed[name], exc_info=error)
        self.write_results(final=False)

    def on_timing(self, split: dict) -> None:  # where each task's time went (rollout.TimeSplit)
        with open(self.out_dir / TIMINGS_FILE, "a") as f:
            f.write(json.dumps(split) + "\n")

    def on_records(self, records: list[dict]) -> None:
        """Finished episodes: to episodes.jsonl at once, so an interrupted run keeps them."""
        append_records(self.episodes_path, records)
        self.records.extend(records)

    def tick(self, unit: str, n: int, partial: float = 0.0, detail: str | None = None) -> None:
        """A unit's progress (rollout.Tick); the bar shows the sum over the units."""
        self.done[unit] = (n, partial)
        assert self.progress is not None  # ticks come from the tasks `run` runs
        self.progress.update(sum(d for d, _ in self.done.values()),
                             partial=sum(p for _, p in self.done.values()), detail=detail)

    # ---- running
    def _todo(self, overlap: int) -> list[tuple[str, str, list[tuple[int, int]]]]:
        """(unit, task, its pending episodes) in the order this process runs them; a unit
        is a task, or with a queue one seed of a long task."""
        cfg, units = self.cfg, list(self.tasks)
        if self.queue is not None:  # the units it holds episodes of, then its balanced share
            units = split_by_seed(units, self.backend, cfg.run.num_processes, cfg.protocol.seeds)
            order = [units.index(u) for u in self.queue.held(units)]
            order += [i for i in claim_order(units, self.backend, cfg.run.num_processes,
                                             cfg.run.process_id, overlap) if i not in order]
            units = [units[i] for i in order]
        return [(unit, task, pending) for unit in units
                for task, seed in [unit_task(unit)]
                if (pending := [p for p in self.plan[task] if seed in (None, p[0])])]

    def run(self) -> dict:
        """Run the pending episodes, write the outputs, return results.json's dict."""
        cfg, policy = self.cfg, self.policy
        # One policy copy per task running at once: copies share the heavy parts (LLM
        # client, memory, selector); reset() gives each its own per-episode state.
        overlap = cfg.run.overlap_tasks if policy.interleaves() else 1
        self.todo = self._todo(overlap)
        with progress_bar(self.total, enabled=not cfg.run.quiet) as self.progress:
            self.done = {unit: (0, 0.0) for unit, _, _ in self.todo}
            run_cfg = cfg.with_options(backend=self.backend)  # every task on the resolved one
            # The native physics of tasks running at once overlaps on threads (task_steps).
            pool = (ThreadPoolExecutor(overlap, thread_name_prefix="physics")
                    if overlap > 1 else None)
            jobs = [_steps_of(name, policy.fork() if overlap > 1 else policy, pending,
                              run_cfg, self.on_records, functools.partial(self.tick, unit),
                              self.on_timing, pool)
                    for unit, name, pending in self.todo]
            if self.queue is not None:
                jobs = [self.queue.claimed(unit, job)
                        for (unit, _, _), job in zip(self.todo, jobs)]
            startup_s, t_tasks = process_age_s(), time.perf_counter()
            try:
                run_interleaved(jobs, overlap,
                                on_done=lambda i, _: self.write_results(final=False),
                                on_error=None if cfg.run.fail_fast else self.on_error)
            finally:
                if pool is not None:
                    pool.shutdown(cancel_futures=True)
        if self.mine():  # the process's own costs beside its tasks' (timings.process_table)
            self.on_timing({"process": cfg.run.process_id, "startup_s": startup_s,
                            "tasks_s": round(time.perf_counter() - t_tasks, 3),
                            "tasks": len(self.mine()), "startup": self.startup})
        results = self.write_results(final=True)
        if self.queue is not None:
            atomic_write(self.out_dir / FINISHED_FILE, "")
        return results
