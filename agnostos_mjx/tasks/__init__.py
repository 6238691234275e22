"""Task registry: every task by name and split."""

from __future__ import annotations

from agnostos_mjx.tasks.base import Split, Task
from agnostos_mjx.tasks.close_microwave import CloseMicrowave
from agnostos_mjx.tasks.lamp_off import LampOff
from agnostos_mjx.tasks.lamp_on import LampOn
from agnostos_mjx.tasks.open_drawer import OpenDrawer
from agnostos_mjx.tasks.push_buttons import PushButtons

_TASKS: dict[str, Task] = {
    t.name: t for t in (OpenDrawer(), PushButtons(), CloseMicrowave(), LampOn(), LampOff())
}


def get_task(name: str) -> Task:
    """The task called `name`; an unknown name lists the valid ones."""
    try:
        return _TASKS[name]
    except KeyError:
        valid = ", ".join(sorted(_TASKS))
        raise KeyError(f"unknown task {name!r}; valid task names: {valid}") from None


def list_tasks(split: Split | str | None = None) -> list[str]:
    """Names of the registered tasks, optionally of one split."""
    if split is None:
        return list(_TASKS)
    split = Split(split)
    return [n for n, t in _TASKS.items() if t.split == split]


def parse_tasks(spec: str) -> list[Task]:
    """'a,b' or a split name ('seen', 'unseen', 'unseen_level1', ...) or 'all'."""
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
    return [get_task(n) for n in dict.fromkeys(names)]


__all__ = ["Split", "Task", "get_task", "list_tasks", "parse_tasks"]
