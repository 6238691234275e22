"""Shared loop of plan-then-execute policies (X-ICM and the retrieval baseline).

Each world keeps a queue of key actions.  At every step the worlds that are
still running with an empty queue are (re)planned together, from their
current observation, in one batch (one batched LLM round for X-ICM); then
one action per world is popped.  That is X-ICM's protocol: the LLM is asked
again only when the previous plan is used up before success.
"""

from __future__ import annotations

import concurrent.futures
from collections import deque
from collections.abc import Generator
from typing import Any

import numpy as np

from agnostos_mjx.policies.base import Policy, Round, run_blocking
from agnostos_mjx.sim.actions import KeyActions


class PlanResult:
    """One world's new plan: continuous actions (n, 3)/(n, 4)/(n,) or none,
    the outcome code that ends the world when there is none, and a log entry."""

    def __init__(self, pos=None, quat=None, gripper=None, end_reason: int = 0,
                 info: dict | None = None):
        self.pos, self.quat, self.gripper = pos, quat, gripper
        self.end_reason, self.info = end_reason, info or {}

    @property
    def size(self) -> int:
        return 0 if self.pos is None else len(self.pos)


class PlanningPolicy(Policy):
    """Subclasses implement `plan(view, worlds) -> list[PlanResult]`, or `plan_steps` when
    planning waits on futures."""

    name = "planning"

    def __init__(self) -> None:
        self._queues: list[deque] = []
        self._logs: list[list[dict]] = []
        self._seeds: tuple[int, ...] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.plan is PlanningPolicy.plan and cls.plan_steps is PlanningPolicy.plan_steps:
            raise TypeError(f"{cls.__name__} must override plan (or plan_steps)")

    def plan(self, view: Round, worlds: np.ndarray) -> list[PlanResult]:
        """New plans of `worlds` (the running worlds whose queue is empty)."""
        return run_blocking(self.plan_steps(view, worlds))

    def plan_steps(self, view: Round, worlds: np.ndarray
                   ) -> Generator[concurrent.futures.Future, Any, list[PlanResult]]:
        """`plan` as a generator that yields the futures it waits on (LLM batches), so
        the evaluator can simulate other tasks meanwhile.  Default: no waiting."""
        return self.plan(view, worlds)
        yield  # noqa: B901 - makes this a generator

    def reset(self, view: Round) -> None:
        b = view.batch
        self.instructions = list(view.instructions)
        self._queues = [deque() for _ in range(b)]
        self._logs = [[] for _ in range(b)]
        self._replans = np.zeros(b, np.int32)
        self._seeds = view.episode_seeds

    def plan_seed(self, world: int) -> int:
        """A reproducible seed per (episode, replan)."""
        return (int(self._seeds[world]) * 1_000_003 + int(self._replans[world])) & 0x7FFFFFFF

    def act_steps(self, view: Round) -> Generator[concurrent.futures.Future, Any, KeyActions]:
        """`act` as a generator over the futures planning waits on (see plan_steps)."""
        b = len(self._queues)
        running = view.running
        need = np.array([running[i] and not self._queues[i] for i in range(b)])
        worlds = np.nonzero(need)[0]
        reasons = np.zeros(b, np.int32)  # why a world got no new plan
        if len(worlds):
            results = yield from self.plan_steps(view, worlds)
            for w, result in zip(worlds, results):
                self._replans[w] += 1
                self._logs[w].append(result.info)
                if result.size:
                    self._queues[w].extend(zip(result.pos, result.quat, result.gripper))
                else:
                    reasons[w] = result.end_reason
        pos = np.zeros((b, 3), np.float32)
        quat = np.tile(np.array([1.0, 0, 0, 0], np.float32), (b, 1))
        grip = np.ones(b, np.float32)
        valid = np.zeros(b, bool)
        for i, queue in enumerate(self._queues):
            if queue and running[i]:
                pos[i], quat[i], grip[i] = queue.popleft()
                valid[i] = True
        return KeyActions(pos, quat, grip, valid, end_reason=reasons)

    def episode_info(self, world: int) -> dict:
        """What the evaluator stores with the episode record."""
        return {"plans": self._logs[world]}

