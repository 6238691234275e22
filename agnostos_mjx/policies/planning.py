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
from typing import TYPE_CHECKING, Any

import numpy as np

from agnostos_mjx.tasks.base import KeyActions

if TYPE_CHECKING:
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.state import EnvState


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


class PlanningPolicy:
    """Subclasses implement `plan(episodes, env, worlds) -> list[PlanResult]`."""

    name = "planning"

    def __init__(self) -> None:
        self._queues: list[deque] = []
        self._logs: list[list[dict]] = []
        self.end_reasons = np.zeros(0, np.int32)
        self._seeds: list[int] = []

    def plan(self, episodes: Episodes, env: EnvState, worlds: np.ndarray) -> list[PlanResult]:
        raise NotImplementedError

    def plan_steps(self, episodes: Episodes, env: EnvState, worlds: np.ndarray
                   ) -> Generator[concurrent.futures.Future, Any, list[PlanResult]]:
        """`plan` as a generator that yields the futures it waits on (LLM batches), so
        the evaluator can simulate other tasks meanwhile.  Default: no waiting."""
        return self.plan(episodes, env, worlds)
        yield  # noqa: B901 - makes this a generator

    def reset(self, episodes: Episodes, env: EnvState, instructions: list[str],
              episode_seeds: list[int] | None = None) -> None:
        b = len(instructions)
        self.instructions = list(instructions)
        self._queues = [deque() for _ in range(b)]
        self._logs = [[] for _ in range(b)]
        self._replans = np.zeros(b, np.int32)
        self._seeds = list(episode_seeds) if episode_seeds is not None else list(range(b))
        self.end_reasons = np.zeros(b, np.int32)

    def plan_seed(self, world: int) -> int:
        """A reproducible seed per (episode, replan)."""
        return (int(self._seeds[world]) * 1_000_003 + int(self._replans[world])) & 0x7FFFFFFF

    def act(self, episodes: Episodes, env: EnvState) -> KeyActions:
        return run_blocking(self.act_steps(episodes, env))

    def act_steps(self, episodes: Episodes, env: EnvState
                  ) -> Generator[concurrent.futures.Future, Any, KeyActions]:
        """`act` as a generator over the futures planning waits on (see plan_steps)."""
        b = len(self._queues)
        need = np.array([not env.done[i] and not self._queues[i] for i in range(b)])
        worlds = np.nonzero(need)[0]
        if len(worlds):
            results = yield from self.plan_steps(episodes, env, worlds)
            for w, result in zip(worlds, results):
                self._replans[w] += 1
                self._logs[w].append(result.info)
                if result.size:
                    self._queues[w].extend(zip(result.pos, result.quat, result.gripper))
                else:
                    self.end_reasons[w] = result.end_reason
        pos = np.zeros((b, 3), np.float32)
        quat = np.tile(np.array([1.0, 0, 0, 0], np.float32), (b, 1))
        grip = np.ones(b, np.float32)
        valid = np.zeros(b, bool)
        for i, queue in enumerate(self._queues):
            if queue and not env.done[i]:
                pos[i], quat[i], grip[i] = queue.popleft()
                valid[i] = True
        return KeyActions(pos, quat, grip, valid)

    def episode_info(self, world: int) -> dict:
        """What the evaluator stores with the episode record."""
        return {"plans": self._logs[world]}


def run_blocking(steps: Generator[concurrent.futures.Future, Any, Any]) -> Any:
    """Drive a generator of futures to its return value, waiting on each future."""
    try:
        future = next(steps)
        while True:
            concurrent.futures.wait([future])
            future = steps.send(None)
    except StopIteration as stop:
        return stop.value
