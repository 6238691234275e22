"""The device planner's plans for the worlds of every task waiting on one: one call per
round instead of one per task.

Every scene has the same robot, so one program plans the key actions of any task's
worlds (control.jit_for_robot).  On a GPU a task's key action was one `plan_arm` call, and
one process's 23 tasks queued hundreds of them on its one stream, where one call of all
their rows costs not much more than one task's (docs/performance.md).  A world's plan moves
with the rows beside it (slightly; docs/performance.md), so the requests gather (agnostos_mjx/infra/gather.py): they
go out together, ordered by content, once every running task waits on one, and a task run
alone gets the one call of its own rows it got before.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from agnostos_mjx.infra.gather import RowBatcher, content_key, then
from agnostos_mjx.sim import control

if TYPE_CHECKING:
    import concurrent.futures

MAX_ROWS = 1 << 20  # every gathered request in one call (a request is never split)
_PLANNERS: dict[Any, GatheredPlanner] = {}


class GatheredPlanner:
    """`control.plan_arm` for the rows of several requests at once (see the module
    docstring): a call pads its rows to the largest request's rows times a power of two,
    so a process compiles a few sizes."""

    def __init__(self, kin: control.PandaKinematics):
        self.plan = control.jit_for_robot(control.plan_arm, kin)
        self._batcher = RowBatcher(self._plan_rows, MAX_ROWS, gather=True, name="planner")

    @classmethod
    def for_robot(cls, kin: control.PandaKinematics) -> GatheredPlanner:
        """The process's planner for this robot, shared by every task."""
        if kin.fingerprint not in _PLANNERS:
            _PLANNERS[kin.fingerprint] = cls(kin)
        return _PLANNERS[kin.fingerprint]

    def submit(self, q0: np.ndarray, pos: np.ndarray, quat: np.ndarray,
               min_rows: int | None = None) -> concurrent.futures.Future:
        """A future of plan_arm(q0, pos, quat) (path, duration, status) for these rows,
        planned in a call of at least `min_rows` rows (Episodes.plan_rows)."""
        q0, pos, quat = (np.asarray(a, np.float64) for a in (q0, pos, quat))
        size = max(len(q0), min_rows or 0)
        rows = [(size, q, p, r) for q, p, r in zip(q0, pos, quat)]
        return then(self._batcher.submit(rows, key=content_key((q0, pos, quat))),
                    lambda out: tuple(np.stack(part) for part in zip(*out)))

    def _plan_rows(self, rows: list[tuple]) -> list[tuple]:
        n = len(rows)
        size = max(r[0] for r in rows)  # the largest request's rows, doubled until all fit
        while size < n:
            size *= 2
        idx = np.minimum(np.arange(size), n - 1)  # padding repeats the last row
        q0, pos, quat = (np.stack([rows[i][k] for i in idx]) for k in (1, 2, 3))
        path, duration, status = (np.asarray(x)[:n] for x in self.plan(q0, pos, quat))
        return list(zip(path, duration, status))
