"""Shared pytest setup for agnostos_mjx (the `slow` marker is registered in pyproject.toml)."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest

from agnostos_mjx.settings import configure_jax

# As every command does before JAX starts: XLA's lowered CPU optimisation level (the tests'
# small kernels run ~100x faster) and the persistent compile cache.
configure_jax()

TASKS = ("open_drawer", "push_buttons")  # the tiny bank's seen tasks

# Tasks whose resets and expert episodes take longest on 2 CPU cores (6-30 s per expert
# test, measured with --durations; lamp_on takes under 2 s): their cases of the per-task
# tests run in the slow suite only, so the default suite stays within 8 minutes while
# still covering every task family (hinged, buttons, pick-and-place, cups, tools).
HEAVY_TASKS = frozenset({
    "take_usb_out_of_computer", "open_grill", "stack_blocks", "put_rubbish_in_bin",
    "put_groceries_in_cupboard", "place_cups", "unplug_charger",
    "place_shape_in_shape_sorter", "sweep_to_dustpan_of_size", "put_item_in_drawer",
    "stack_cups", "close_jar", "place_wine_at_rack_location", "open_drawer",
    "put_toilet_roll_on_stand", "water_plants", "slide_block_to_color_target",
    "insert_onto_square_peg", "put_books_on_bookshelf", "light_bulb_in", "reach_and_drag",
    "straighten_rope", "put_money_in_safe", "meat_off_grill",
})


def task_params(names):
    """Parameters for a per-task test: the heavy tasks marked slow."""
    return [pytest.param(n, marks=pytest.mark.slow) if n in HEAVY_TASKS else n for n in names]


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
    """Two seen tasks x two demos at 32 x 32 pixels (about 20 s on 2 cores)."""
    from agnostos_mjx.data.generate import generate

    out = tmp_path_factory.mktemp("bank")
    generate(tiny_bank_config(out))
    return out
