"""The episodes of one task, a batch of worlds at a time, and their records.

A task's pending (seed, episode) pairs run in chunks of --batch worlds.  Each episode's
record goes out as soon as its world finishes, so an interrupted run keeps it.  The loop is
a generator over the futures the policy waits on, so that `scheduler.run_interleaved` can
simulate other tasks meanwhile; `run_task` drives it alone.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Generator, Iterable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from agnostos_mjx.evaluation.config import EvalConfig, UsageError
from agnostos_mjx.evaluation.dense import DenseDriver, check_answer, dense_control
from agnostos_mjx.evaluation.protocol import episode_keys, episode_variations, policy_seed
from agnostos_mjx.evaluation.timings import MEASURED
from agnostos_mjx.infra.cli import Progress, process_age_s
from agnostos_mjx.policies.base import Policy, Round

if TYPE_CHECKING:
    import concurrent.futures
    from concurrent.futures import Executor

    from agnostos_mjx.evaluation.video import EpisodeVideos
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.state import EnvState
    from agnostos_mjx.tasks.base import Task

log = logging.getLogger("agnostos_mjx.eval")

OnRecords = Callable[[list[dict]], None]
OnTiming = Callable[[dict], None]
# tick(episodes done, partial (key-action rounds of unfinished episodes, in episodes), detail)
Tick = Callable[..., None]
Steps = Generator["concurrent.futures.Future", Any, list[dict]]


def run_task(task: Task, policy: Policy, pending: list[tuple[int, int]],
             cfg: EvalConfig, on_records: OnRecords, progress: Progress | None = None,
             done_before: int = 0) -> list[dict]:
    """Run `pending` (seed, episode) pairs of one task in chunks of --batch;
    `on_records(records)` is called as episodes finish.  Returns the records."""
    from agnostos_mjx.policies.planning import run_blocking

    tick = None if progress is None else (
        lambda n, partial=0.0, detail=None: progress.update(done_before + n, partial=partial,
                                                            detail=detail))
    return run_blocking(task_steps(task, policy, pending, cfg, on_records, tick))


def task_steps(task: Task, policy: Policy, pending: list[tuple[int, int]],
               cfg: EvalConfig, on_records: OnRecords, tick: Tick | None = None,
               on_timing: OnTiming | None = None, physics_pool: Executor | None = None
               ) -> Steps:
    """`run_task` as a generator that yields the futures the policy waits on (see
    Policy.act_steps), so `run_interleaved` can simulate other tasks meanwhile.
    `tick(episodes_done, partial, detail)` reports progress within the task;
    `on_timing(split)` gets where the task's wall time went (`TimeSplit.summary`).
    With `physics_pool` the resets and key actions of native MuJoCo (whose rollouts release
    the GIL) run there and are yielded as futures too: tasks running at once overlap their
    physics with each other and with the policy.  The device backends keep this thread."""
    from agnostos_mjx.evaluation.video import EpisodeVideos
    from agnostos_mjx.runtime.env import Episodes

    t0, started = time.perf_counter(), process_age_s()
    split = TimeSplit()
    with split.measure("build"):
        protocol = cfg.protocol
        runner = Episodes(task, protocol.backend, planner=protocol.planner,
                          plan_rows=protocol.batch, renderer=protocol.renderer)
    videos = EpisodeVideos.for_task(cfg.run, runner)
    log.info("%s: %d episodes on backend %s (runner built in %.1f s)", task.name, len(pending),
             runner.backend_name, time.perf_counter() - t0)
    chunk = min(cfg.protocol.batch, len(pending))
    batches = -(-len(pending) // chunk)
    # A backend that compiles per batch shape (MJX) gets its last chunk padded.
    pad = runner.capabilities.padded_batch
    out: list[dict] = []
    for b, start in enumerate(range(0, len(pending), chunk)):
        part = pending[start:start + chunk]
        t_batch = time.perf_counter()
        label = f"{task.name} batch {b + 1}/{batches}"
        out += yield from batch_steps(task, policy, runner, part, chunk if pad else len(part),
                                      cfg, on_records, tick, len(out), label, videos, split,
                                      physics_pool if runner.capabilities.threaded else None)
        rate = 100.0 * np.mean([r["success"] for r in out[-len(part):]])
        log.info("%s: batch of %d done in %.1f s, success %.0f%%", task.name, len(part),
                 time.perf_counter() - t_batch, rate)
    split.frames = runner.observer.frames  # camera frames the policy saw
    summary = split.summary(task.name, runner.backend_name, len(pending),
                            time.perf_counter() - t0)
    if started is not None:  # the process's age at the task's start: a run's timeline
        summary["start_s"] = round(started, 2)
    log.info("%s: %.1f s: %s", task.name, summary["wall_s"], ", ".join(
        f"{k} {summary[k + '_s']:.1f} s" for k in (*TimeSplit.STAGES, "other")))
    if on_timing is not None:
        on_timing(summary)
    return out


class TimeSplit:
    """Where a task's wall time goes: building the runner (scene, compiled programs),
    resetting batches, rendering what the policy sees, the policy (reset and actions,
    including any wait for its LLM or server) and the physics (key actions or control steps, until the outcomes reach the
    host); the rest (records, videos) is "other".  With tasks running at once each stage
    also holds the other tasks' turns meanwhile.  It also counts the policy's rounds (one
    action for every running world of a batch) and the physics steps run for the batches'
    worlds (`world_steps`) against those the episodes needed (`live_steps`)."""

    STAGES = MEASURED

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(self.STAGES, 0.0)
        self.rounds = self.world_steps = self.live_steps = self.frames = 0

    def policy_turn(self, started: float, rendered_s: float) -> None:
        """A policy's turn since `started`: its observation's rendering, then the rest."""
        self.seconds["render"] += rendered_s
        self.seconds["policy"] += time.perf_counter() - started - rendered_s

    @contextlib.contextmanager
    def measure(self, stage: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - t

    def summary(self, task: str, backend: str, episodes: int, wall_s: float) -> dict:
        rec = {"task": task, "backend": backend, "episodes": episodes,
               "wall_s": round(wall_s, 3)}
        rec.update({f"{k}_s": round(v, 3) for k, v in self.seconds.items()})
        rec["other_s"] = round(max(0.0, wall_s - sum(self.seconds.values())), 3)
        rec.update(rounds=self.rounds, world_steps=self.world_steps, live_steps=self.live_steps,
                   frames=self.frames)
        return rec


def batch_steps(task: Task, policy: Policy, runner: Episodes,
                part: list[tuple[int, int]], size: int, cfg: EvalConfig,
                on_records: OnRecords, tick: Tick | None = None, done_before: int = 0,
                label: str = "", videos: EpisodeVideos | None = None,
                split: TimeSplit | None = None, physics_pool: Executor | None = None) -> Steps:
    """One batch of `task_steps`: `part` padded to `size` worlds.  Each episode goes to
    `on_records` as soon as its world finishes, so an interrupted run keeps it; `tick`
    also gets the finished key-action rounds of the unfinished episodes (`partial`)."""
    from agnostos_mjx.runtime.outcome import Outcome

    batch = Batch(task, policy, runner, part, size, cfg, on_records, tick, done_before, label)
    split = split or TimeSplit()
    batch.report(0)
    with split.measure("reset"):
        batch.env = yield from on_pool(physics_pool, runner.reset, batch.keys,
                                       batch.variations)
    if videos is not None:
        videos.start(batch.env, part)
    try:
        yield from batch.rounds(split, videos, physics_pool)
    except UsageError:  # an answer of the wrong form (dense.check_answer) stops the run
        raise
    except Exception:
        if cfg.run.fail_fast:
            raise
        log.exception("%s: the policy raised; running episodes of this batch end as "
                      "policy_error", task.name)
        env = batch.env
        batch.env = replace(env, outcome=np.where(env.done, env.outcome, Outcome.POLICY_ERROR))
    env = batch.env
    batch.record(np.where(env.done, env.outcome, Outcome.MAX_STEPS))
    split.world_steps += int(np.sum(env.world_steps))  # padding worlds included
    split.live_steps += int(np.sum(env.sim_steps[:batch.n]))
    if videos is not None:
        by_episode = {(r["seed"], r["episode"]): r for r in batch.out}
        videos.write([by_episode[int(s), int(e)] for s, e in part])
    if tick is not None:
        tick(done_before + len(batch.out))
    return batch.out


class Batch:
    """One batch of worlds in flight: its episodes, its latest state (`env`, kept here so
    that a policy error ends the episodes where they stand) and the records written so far."""

    def __init__(self, task: Task, policy: Policy, runner: Episodes,
                 part: list[tuple[int, int]], size: int, cfg: EvalConfig,
                 on_records: OnRecords, tick: Tick | None, done_before: int,
                 label: str) -> None:
        self.task, self.policy, self.runner, self.part = task, policy, runner, part
        self.on_records, self.tick, self.done_before, self.label = (on_records, tick,
                                                                     done_before, label)
        self.n = n = len(part)
        self.run_part = part + [part[-1]] * (size - n)
        dense = cfg.protocol.action_mode == "dense"
        self.ctl = dense_control(cfg, runner) if dense else None
        self.limit = self.ctl.max_steps if self.ctl is not None else task.max_key_actions
        self.mode = {"action_mode": cfg.protocol.action_mode, "step_budget": self.limit}
        if self.ctl is not None:
            self.mode["control_hz"] = round(1.0 / (self.ctl.period_steps * runner.dt), 6)
        self.execute = cfg.protocol.execute
        self.t_batch = time.perf_counter()
        self.keys = episode_keys(np.array([s for s, _ in self.run_part]),
                                 np.array([e for _, e in self.run_part]))
        self.variations = episode_variations(self.keys, task.num_variations,
                                             task.split.value, cfg.protocol.variations)
        self.instructions = [task.descriptions(int(v))[0] for v in self.variations]
        self.unit = "control step" if dense else "key action"
        self.recorded = np.zeros(n, bool)
        self.out: list[dict] = []
        self.env: EnvState | None = None  # set by the reset

    def record(self, outcome: np.ndarray) -> None:
        """Records of the worlds newly finished with `outcome`, out at once."""
        from agnostos_mjx.runtime.outcome import Outcome

        new = (outcome[:self.n] != Outcome.RUNNING) & ~self.recorded
        if new.any():
            records = episode_records(self.task, self.policy, self.runner.backend_name,
                                      self.part, self.variations, self.instructions, self.env,
                                      outcome, np.nonzero(new)[0],
                                      time.perf_counter() - self.t_batch, len(self.run_part),
                                      self.mode)
            self.recorded[new] = True
            self.out.extend(records)
            self.on_records(records)

    def report(self, rounds: int) -> None:
        """Progress after `rounds` rounds, the unfinished episodes counted in part."""
        if self.tick is not None:
            self.tick(self.done_before + len(self.out),
                      (self.n - self.recorded.sum()) * rounds / self.limit,
                      f"{self.label} {self.unit} {min(rounds + 1, self.limit)}/{self.limit}")

    def rounds(self, split: TimeSplit, videos: EpisodeVideos | None,
               pool: Executor | None) -> Generator:
        """The policy's rounds until every world is done or the budget is spent."""
        from agnostos_mjx.runtime.outcome import Outcome

        policy, runner = self.policy, self.runner
        view = Round.for_policy(policy, runner, self.env, self.instructions,
                                [policy_seed(s, e) for s, e in self.run_part])
        with split.measure("policy"):
            policy.reset(view)
        driver = DenseDriver(self.execute, policy.relative) if self.ctl is not None else None
        for rounds in range(self.limit):
            if self.env.done.all():
                break
            running = self.env.outcome == Outcome.RUNNING
            split.rounds += 1
            started = time.perf_counter(), runner.observer.render_s  # the policy's turn
            view = view.at(self.env)
            reasons = yield from self.act(view, driver, started, split, pool)
            env = self.env
            if videos is not None:
                videos.capture(env)
            if reasons is not None:  # why a world got no action (bad LLM output, ...)
                codes = np.asarray(reasons)
                ended = running & (env.outcome == Outcome.NO_ACTION) & (codes > 0)
                self.env = env = replace(env, outcome=np.where(ended, codes, env.outcome))
            self.record(np.where(env.done, env.outcome, Outcome.RUNNING))
            self.report(rounds + 1)

    def act(self, view: Round, driver: DenseDriver | None, started: tuple[float, float],
            split: TimeSplit, pool: Executor | None) -> Generator:
        """One round: the policy's answer for `view` (through `driver` in dense mode), then
        the physics that carries it out; `started`: the clock and render time at its start.
        Returns the answer's end_reason (B,) or None; the physics never sees it."""
        policy, runner = self.policy, self.runner
        t_policy, rendered = started
        if driver is not None:
            actions = yield from driver.next(policy, view, self.env)
            split.policy_turn(t_policy, runner.observer.render_s - rendered)
            with split.measure("physics"):
                self.env, _ = yield from on_pool(pool, runner.step_dense, self.env,
                                                 actions._replace(end_reason=None), self.ctl)
            return actions.end_reason
        actions = yield from policy.act_steps(view)
        check_answer(actions, self.env.batch, policy.name)
        reasons, actions = actions.end_reason, actions._replace(end_reason=None)
        split.policy_turn(t_policy, runner.observer.render_s - rendered)
        with split.measure("physics"):
            plan = runner.plan_request(self.env, actions)  # gathers with other tasks'
            if plan is not None:
                yield plan
                plan = plan.result()
            self.env, _ = yield from on_pool(pool, runner.step, self.env, actions, False, plan)
        return reasons


def on_pool(pool: Executor | None, fn: Callable, *args) -> Generator:
    """`fn(*args)`, on `pool` with its future yielded (other tasks run meanwhile), or here."""
    if pool is None:
        return fn(*args)
    future = pool.submit(fn, *args)
    yield future
    return future.result()


def episode_records(task: Task, policy: Policy, backend: str,
                    part: Sequence[tuple[int, int]], variations: np.ndarray,
                    instructions: list[str], env: EnvState, outcome: np.ndarray,
                    worlds: Iterable[int], wall_s: float, batch_size: int,
                    mode: dict | None = None) -> list[dict]:
    """The records of the finished `worlds` of a batch (episodes.jsonl's lines); `mode`:
    the action mode and step budget (key_actions counts control steps in dense mode)."""
    from agnostos_mjx.runtime.outcome import Outcome

    records = []
    for i in worlds:
        seed, episode = part[i]
        record = {
            "task": task.name, "split": task.split.value, "seed": int(seed),
            "episode": int(episode), "variation": int(variations[i]),
            "instruction": instructions[i], "policy": policy.name,
            "success": bool(outcome[i] == Outcome.SUCCESS),
            "outcome": Outcome(int(outcome[i])).label,
            "key_actions": int(env.key_actions[i]), "sim_steps": int(env.sim_steps[i]),
            "world_steps": int(env.world_steps[i]),
            "backend": backend, "batch_size": batch_size, "wall_s": round(wall_s, 4),
            **(mode or {}),
        }
        info = policy.episode_info(int(i))
        if info is not None:
            record["policy_info"] = info
        records.append(record)
    return records
