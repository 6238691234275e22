"""infra.gc_pause: the collector stays off until the last overlapping pause ends (a Warp
import on one thread must not switch it back on under another thread's CUDA graph capture),
and a collector that was off stays off."""

from __future__ import annotations

import gc
import threading

from agnostos_mjx.infra.gc_pause import gc_paused


def test_overlapping_pauses_resume_at_the_last() -> None:
    assert gc.isenabled()
    inside, release = threading.Event(), threading.Event()

    def other() -> None:
        with gc_paused():
            inside.set()
            release.wait(10)

    t = threading.Thread(target=other)
    with gc_paused():
        t.start()
        assert inside.wait(10)
    assert not gc.isenabled()  # the other thread still holds its pause
    release.set()
    t.join(10)
    assert gc.isenabled()


def test_a_collector_that_was_off_stays_off() -> None:
    gc.disable()
    try:
        with gc_paused():
            assert not gc.isenabled()
        assert not gc.isenabled()
    finally:
        gc.enable()
    with gc_paused():
        assert not gc.isenabled()
    assert gc.isenabled()
