"""Requests of rows from several tasks, answered in shared calls: `RowBatcher`.

A batcher runs `fn` over the rows of every request pending when its worker is free, or,
with `gather`, holds the requests until the evaluation loop has nothing else to run
(`flush`: `evaluation.scheduler.run_interleaved` calls it once every running task waits on
a held request) and then sends them in the order of their keys; a caller that waits on
nothing else sends its own request alone at once (`send_alone`:
`policies.base.run_blocking`, a selector's `select`).  Gathering is for programs whose
result for a row moves with the rows beside it (on a GPU: the selection's sampler, the
device planner; dynamics/batching.py and runtime/plan_rows.py have the measurements):
which rows share a call then depends on the run's tasks and seeds, never on timing, and a
task run alone gets the calls it got alone.
Processes that take tasks from a shared queue (`--local-processes`) run whichever tasks
they get first, so there each request goes alone in calls of its own rows
(`allow_gathering(False)`): a task's records never depend on which tasks ran beside it.
"""

from __future__ import annotations

import collections
import concurrent.futures
import functools
import hashlib
import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

_GATHERING = [True]  # this process's tasks are a fixed set (see the module docstring)


def allow_gathering(allowed: bool) -> None:
    """Whether gathering batchers of this process may put several requests in one call
    (False: each request goes alone, in calls of its own rows from the first place)."""
    _GATHERING[0] = allowed


class _Request:
    def __init__(self, items: Sequence[Any], key: Any = None, alone: bool = False):
        self.future: concurrent.futures.Future = concurrent.futures.Future()
        self.results: list[Any] = [None] * len(items)
        self.items, self.key, self.alone = items, key, alone
        self.left = len(items)
        self.closed = False  # its future is (being) set; guarded by the batcher's lock


def content_key(arrays: Sequence[Any]) -> str:
    """A digest of arrays' bytes: a gathered request's key from what it holds, which the
    run's tasks and seeds fix (unlike the order in which requests arrive)."""
    digest = hashlib.blake2b(digest_size=16)
    for a in arrays:
        digest.update(np.ascontiguousarray(a).tobytes())
    return digest.hexdigest()


def then(future: concurrent.futures.Future, fn: Callable[[Any], Any]
         ) -> concurrent.futures.Future:
    """A future of `fn(future.result())` (or of its exception); a held `future`'s `flush`
    and `send_alone` carry over."""
    out: concurrent.futures.Future = concurrent.futures.Future()
    for release in ("flush", "send_alone"):
        if hasattr(future, release):
            setattr(out, release, getattr(future, release))

    def finish(done: concurrent.futures.Future) -> None:
        if not out.set_running_or_notify_cancel():  # cancelled (Ctrl-C): nobody waits
            return
        try:
            out.set_result(fn(done.result()))
        except Exception as error:  # the caller of out.result() sees it
            out.set_exception(error)

    future.add_done_callback(finish)
    return out


def flush(future: concurrent.futures.Future) -> None:
    """Release every request held with `future`, together (a no-op for any other future):
    what the scheduler does once each running task waits on one."""
    release = getattr(future, "flush", None)
    if release is not None and not future.done():
        release()


def send_alone(future: concurrent.futures.Future) -> None:
    """Release `future`'s request alone, in calls of its own rows (a no-op for any other
    future): for a caller that waits on nothing else (`run_blocking`, `select`), so that a
    request another thread holds meanwhile never shares its calls."""
    release = getattr(future, "send_alone", None)
    if release is not None and not future.done():
        release()


class RowBatcher:
    """`fn(items) -> results` (one result per item, at most `size` items a call) on
    `workers` threads.  `submit` returns a future of the request's results, so a task can
    wait on its rows while other tasks run; a call takes the items of every request pending
    when a worker is free (`fn` must give an item the same result wherever it sits in a
    call).  With `gather`, requests wait for `flush` (the future's `flush` attribute) and
    are then queued in the order of their `key`s, or, where `allow_gathering(False)`, go
    alone at once: see the module docstring."""

    def __init__(self, fn: Callable[[list[Any]], Sequence[Any]], size: int, workers: int = 1,
                 gather: bool = False, name: str = "rows"):
        if size < 1 or workers < 1:
            raise ValueError(f"size and workers must be positive, got {size} and {workers}")
        self.fn, self.size, self.workers, self.name = fn, size, workers, name
        self.gather = gather
        self._held: list[_Request] = []
        self._pending: collections.deque[tuple[_Request, int, Any]] = collections.deque()
        self._ready = threading.Condition()
        self._started = False

    def submit(self, items: Sequence[Any], key: Any = None) -> concurrent.futures.Future:
        """A future of `items`' results; `key` orders gathered requests (required then)."""
        request = _Request(items, key, alone=self.gather and not _GATHERING[0])
        if not items:
            request.future.set_result([])
            return request.future
        with self._ready:
            if self.gather and not request.alone:
                if key is None:
                    raise ValueError(f"{self.name}: a gathering batcher needs a key per request")
                self._held.append(request)
                request.future.flush = self.flush  # type: ignore[attr-defined]
                request.future.send_alone = functools.partial(  # type: ignore[attr-defined]
                    self._send_alone, request)
            else:
                self._queue([request])
        return request.future

    def flush(self) -> None:
        """Queue the held requests, in key order, for the workers."""
        with self._ready:
            held, self._held = sorted(self._held, key=lambda r: r.key), []
            if held:
                self._queue(held)

    def _send_alone(self, request: _Request) -> None:
        with self._ready:
            if request in self._held:
                self._held.remove(request)
                request.alone = True
                self._queue([request])

    def _queue(self, requests: list[_Request]) -> None:
        """Hand `requests`' items to the workers (the caller holds the lock)."""
        if not self._started:  # threads only for a batcher that is used
            for i in range(self.workers):
                threading.Thread(target=self._work, name=f"{self.name}-{i}", daemon=True).start()
            self._started = True
        for request in requests:
            self._pending.extend((request, i, item) for i, item in enumerate(request.items))
        self._ready.notify()

    def _work(self) -> None:
        while True:
            with self._ready:
                while not self._pending:
                    self._ready.wait()
                first = self._pending[0][0]
                take = []
                while (self._pending and len(take) < self.size
                       and (self._pending[0][0] is first
                            or not (first.alone or self._pending[0][0].alone))):
                    take.append(self._pending.popleft())
                if self._pending:
                    self._ready.notify()  # another worker can start on the rest
            try:
                results = list(self.fn([item for _, _, item in take]))
                if len(results) != len(take):
                    raise RuntimeError(f"{self.fn!r} returned {len(results)} results for "
                                       f"{len(take)} items")
            except Exception as error:  # handed to the callers waiting on these rows
                with self._ready:
                    failed = {id(r): r for r, _, _ in take if not r.closed}
                    for request in failed.values():
                        request.closed = True
                for request in failed.values():
                    if request.future.set_running_or_notify_cancel():
                        request.future.set_exception(error)
                continue
            with self._ready:  # two workers may hold rows of one request
                done = []
                for (request, i, _), result in zip(take, results):
                    request.results[i] = result
                    request.left -= 1
                    if request.left == 0 and not request.closed:
                        request.closed = True
                        done.append(request)
            for request in done:  # a cancelled request (Ctrl-C) is dropped, the worker goes on
                if request.future.set_running_or_notify_cancel():
                    request.future.set_result(request.results)
