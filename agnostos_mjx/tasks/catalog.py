"""The AGNOSTOS benchmark's 41 task names by split, and the checks of a --tasks text, without
importing a task module or JAX (a launcher of processes checks its tasks before starting
them and must not start JAX).

The lists are in the order of X-ICM's `gather_score.py`; each task lives in its own module
`agnostos_mjx.tasks.<name>` that defines `TASK`.  A listed task whose module does not exist
yet is reported as not implemented, never silently skipped.
"""

from __future__ import annotations

import enum
import importlib.util


class Split(str, enum.Enum):
    SEEN = "seen"
    LEVEL1 = "unseen_level1"
    LEVEL2 = "unseen_level2"


SEEN = (
    "open_drawer", "slide_block_to_color_target", "sweep_to_dustpan_of_size", "meat_off_grill",
    "turn_tap", "put_item_in_drawer", "close_jar", "reach_and_drag", "stack_blocks",
    "light_bulb_in", "put_money_in_safe", "place_wine_at_rack_location",
    "put_groceries_in_cupboard", "place_shape_in_shape_sorter", "push_buttons",
    "insert_onto_square_peg", "stack_cups", "place_cups",
)
UNSEEN_LEVEL1 = (
    "put_toilet_roll_on_stand", "put_knife_on_chopping_board", "close_fridge",
    "close_microwave", "close_laptop_lid", "phone_on_base", "toilet_seat_down", "lamp_off",
    "lamp_on", "put_books_on_bookshelf", "put_umbrella_in_umbrella_stand", "open_grill",
    "put_rubbish_in_bin",
)
UNSEEN_LEVEL2 = (
    "take_usb_out_of_computer", "take_lid_off_saucepan", "take_plate_off_colored_dish_rack",
    "basketball_in_hoop", "scoop_with_spatula", "straighten_rope", "turn_oven_on",
    "beat_the_buzz", "water_plants", "unplug_charger",
)
BENCHMARK: dict[Split, tuple[str, ...]] = {
    Split.SEEN: SEEN, Split.LEVEL1: UNSEEN_LEVEL1, Split.LEVEL2: UNSEEN_LEVEL2,
}


def is_implemented(name: str) -> bool:
    return importlib.util.find_spec(f"agnostos_mjx.tasks.{name}") is not None


def task_split(name: str) -> Split:
    """The split of the task called `name`, without importing its module; KeyError for an
    unknown name (listing the valid ones) or one not implemented."""
    split = next((s for s, names in BENCHMARK.items() if name in names), None)
    if split is None:
        valid = ", ".join(sorted(n for names in BENCHMARK.values() for n in names))
        raise KeyError(f"unknown task {name!r}; valid task names: {valid}")
    if not is_implemented(name):
        raise KeyError(f"task {name!r} ({split.value}) is part of the benchmark but not "
                       f"implemented yet; implemented: {', '.join(list_tasks())}")
    return split


def list_tasks(split: Split | str | None = None) -> list[str]:
    """Names of the implemented tasks in benchmark order, optionally of one split."""
    splits = list(BENCHMARK) if split is None else [Split(split)]
    return [n for s in splits for n in BENCHMARK[s] if is_implemented(n)]


def parse_task_names(spec: str) -> list[str]:
    """The names `parse_tasks` gives, checked as it checks them, without importing a task
    module (a process of a task queue imports only the tasks it runs)."""
    names: list[str] = []
    for part in (p.strip() for p in spec.split(",") if p.strip()):
        if part == "all":
            names += list_tasks()
        elif part == "unseen":
            names += list_tasks(Split.LEVEL1) + list_tasks(Split.LEVEL2)
        elif part in {s.value for s in Split}:
            names += list_tasks(part)
        else:
            names.append(part)
    names = list(dict.fromkeys(names))
    for name in names:
        task_split(name)
    return names
