"""Shared pytest setup for agnostos_mjx (the `slow` marker is registered in pyproject.toml)."""

from __future__ import annotations

import functools
import gc
from pathlib import Path

import pytest

from agnostos_mjx.infra.settings import configure_jax

# As every command does before JAX starts: XLA's lowered CPU optimisation level (the tests'
# small kernels run ~100x faster) and the persistent compile cache.
configure_jax()

TASKS = ("open_drawer", "push_buttons")  # the tiny bank's seen tasks

# The per-task tests (resets, seeds, expert success) run every task in the slow suite and,
# in the default suite, two: an articulated button (lamp_on) and pick-and-place into a volume
# (phone_on_base).  Each task a test touches costs its programs' compile (seconds
# with a cold cache), so the default suite touches few; a hinged door is reset in
# test_compile_once and a failure condition checked in test_tasks_delicate_physics.
DEFAULT_SUITE_TASKS = frozenset({"lamp_on", "phone_on_base"})


# Each compiled XLA program maps its own code pages, and Linux caps a process's mappings
# (vm.max_map_count, 65,530 by default).  The slow group compiles thousands of programs in
# one process: it reached 57,000 mappings here and, run whole, crashed inside XLA when a
# mapping failed.  Past this many, the compiled programs are dropped between test modules
# (JAX's disk cache brings back the ones a later module needs).
MAX_MAPPINGS = 25_000


def mappings() -> int:
    """This process's memory mappings (0 where /proc is not there)."""
    try:
        with open("/proc/self/maps") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


@pytest.fixture(autouse=True, scope="module")
def _bounded_mappings():
    yield
    if mappings() > MAX_MAPPINGS:
        import jax

        jax.clear_caches()
        gc.collect()


def task_params(names):
    """Parameters for a per-task test: tasks outside DEFAULT_SUITE_TASKS marked slow."""
    return [n if n in DEFAULT_SUITE_TASKS else pytest.param(n, marks=pytest.mark.slow)
            for n in names]


@functools.cache
def episodes_for(name: str):
    """One native runner per task for the whole session (test modules share it)."""
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    return Episodes(get_task(name), "native")


def tiny_bank_config(out: Path, demos: int = 2):
    from agnostos_mjx.data.generate import GenerateConfig

    return GenerateConfig(out=out, tasks=TASKS, demos=demos, seed=3, backend="native",
                          batch=2, image_size=32, quiet=True)


@pytest.fixture(scope="session")
def bank_dir(tmp_path_factory) -> Path:
    """Two seen tasks x two demos at 32 x 32 pixels (module-scoped: generation is slow)."""
    from agnostos_mjx.data.generate import generate

    out = tmp_path_factory.mktemp("bank")
    generate(tiny_bank_config(out))
    return out
