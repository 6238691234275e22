"""The oracle: replays the task's scripted expert, one key action per step.

It is the benchmark's upper bound and the check that every task is solvable
with the runtime's control stack (X-ICM's demos come from the same expert)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agnostos_mjx.policies.base import Policy, Round
from agnostos_mjx.policies.options import PolicyOptions
from agnostos_mjx.sim.actions import KeyActions


@dataclass
class OracleOptions(PolicyOptions):
    """The oracle takes no options: the expert decides everything."""


class OraclePolicy(Policy):
    """Plans every world's expert key actions at reset and pops one per step,
    skipping padding (invalid) entries; when a world's plan is used up its
    action is invalid, which ends it with Outcome.NO_ACTION.  Privileged: the
    expert reads the scene's state."""

    name = "oracle"
    privileged = True

    def __init__(self, options: OracleOptions | None = None) -> None:
        self._plan: KeyActions | None = None
        self._cursor = np.zeros(0, np.int64)

    def reset(self, view: Round) -> None:
        self._plan = view.episodes.expert_actions(view.env)  # arrays (B, K, ...)
        self._cursor = np.zeros(view.batch, np.int64)

    def act(self, view: Round) -> KeyActions:
        if self._plan is None:
            raise RuntimeError("OraclePolicy.act called before reset")
        plan = self._plan
        valid_plan = np.asarray(plan.valid, bool)
        b, k = valid_plan.shape
        # Next valid entry at or after the cursor; k when none is left.
        ahead = valid_plan & (np.arange(k)[None] >= self._cursor[:, None])
        idx = np.where(ahead.any(1), np.argmax(ahead, 1), k)
        valid = idx < k
        take = np.minimum(idx, k - 1)
        rows = np.arange(b)
        self._cursor = idx + 1
        return KeyActions(
            pos=np.asarray(plan.pos)[rows, take],
            quat=np.asarray(plan.quat)[rows, take],
            gripper=np.asarray(plan.gripper)[rows, take],
            valid=valid,
        )
