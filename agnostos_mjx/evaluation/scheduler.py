"""Tasks side by side: while one task's policy waits (an LLM batch, a policy server's
answers), another task simulates.  Results do not depend on the overlap: each task's
episodes run in their own order on their own policy copy."""

from __future__ import annotations

import collections
import concurrent.futures
from collections.abc import Callable, Generator, Sequence
from typing import Any

Steps = Generator[concurrent.futures.Future, Any, Any]


def run_interleaved(jobs: Sequence[Steps], limit: int,
                    on_done: Callable[[int, Any], None] | None = None) -> list:
    """Run generators of futures (rollout.task_steps) with up to `limit` started at once:
    whenever one waits on a future, the next ready one runs.  Everything runs on the calling
    thread (physics and JAX stay single-threaded); only the awaited work (LLM requests) runs
    elsewhere.  `on_done(index, value)` is called as each finishes; returns the values."""
    pending = collections.deque(enumerate(jobs))
    active: list[list] = []  # [index, generator, future or None]
    values: list = [None] * len(jobs)
    try:
        while pending or active:
            while pending and len(active) < limit:
                active.append([*pending.popleft(), None])
            ready = [slot for slot in active if slot[2] is None or slot[2].done()]
            if not ready:
                concurrent.futures.wait([slot[2] for slot in active],
                                        return_when=concurrent.futures.FIRST_COMPLETED)
                continue
            for slot in ready:
                try:
                    slot[2] = slot[1].send(None)
                except StopIteration as stop:
                    values[slot[0]] = stop.value
                    active.remove(slot)
                    if on_done is not None:
                        on_done(slot[0], stop.value)
    except BaseException:  # Ctrl-C or a failure: cancel the work still waited on
        for _, steps, future in active:
            if future is not None:
                future.cancel()
            steps.close()
        raise
    return values
