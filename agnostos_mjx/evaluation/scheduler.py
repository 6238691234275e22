"""Tasks side by side: while one task's policy waits (an LLM batch, a policy server's
answers), another task simulates.  Each task's episodes run in their own order on their
own policy copy.  A request that gathers (agnostos_mjx/infra/gather.py: the demo selection on a
GPU, the device planner's plans) is released once every running task waits on one, so
the tasks' rows go out together in an order that timing cannot change: on the CPU results
do not depend on the overlap, on a GPU they do only through those shared calls' rounding,
the same in every run of the same tasks and overlap."""

from __future__ import annotations

import collections
import concurrent.futures
from collections.abc import Callable, Generator, Sequence
from typing import Any

Steps = Generator[concurrent.futures.Future, Any, Any]


def run_interleaved(jobs: Sequence[Steps], limit: int,
                    on_done: Callable[[int, Any], None] | None = None,
                    on_error: Callable[[int, Exception], None] | None = None) -> list:
    """Run generators of futures (rollout.task_steps) with up to `limit` started at once:
    whenever one waits on a future, the next ready one runs.  The generators run on the
    calling thread; the awaited work (LLM requests, the selection, native physics) runs
    elsewhere.  `on_done(index, value)` is called as each finishes; returns the values.
    With `on_error(index, error)` a job that raises is handed to it and the others go on
    (its value stays None); without, the error stops the run."""
    pending = collections.deque(enumerate(jobs))
    active: list[list] = []  # [index, generator, future or None]
    values: list = [None] * len(jobs)
    try:
        while pending or active:
            while pending and len(active) < limit:
                active.append([*pending.popleft(), None])
            ready = [slot for slot in active if slot[2] is None or slot[2].done()]
            if not ready:
                waiting = [slot[2] for slot in active]
                releases = [getattr(f, "flush", None) for f in waiting]
                if all(releases):  # every task waits on gathered rows: send them together
                    for release in releases:  # the first sends them, the others find none
                        release()
                concurrent.futures.wait(waiting, return_when=concurrent.futures.FIRST_COMPLETED)
                continue
            for slot in ready:
                try:
                    slot[2] = slot[1].send(None)
                except StopIteration as stop:
                    values[slot[0]] = stop.value
                    active.remove(slot)
                    if on_done is not None:
                        on_done(slot[0], stop.value)
                except Exception as error:
                    if on_error is None:
                        raise
                    active.remove(slot)
                    on_error(slot[0], error)
    except BaseException:  # Ctrl-C or a failure: cancel the work still waited on
        for _, steps, future in active:
            if future is not None:
                future.cancel()
            steps.close()
        raise
    return values
