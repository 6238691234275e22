"""Task registry: the AGNOSTOS benchmark's 41 tasks, by name and split (`catalog`, which
imports no task module and no JAX); each task's module `agnostos_mjx.tasks.<name>` defines
`TASK` and is imported on first use (`get_task`).
"""

from __future__ import annotations

import functools
import importlib
from typing import TYPE_CHECKING, Any

from agnostos_mjx.tasks.catalog import (
    BENCHMARK,
    SEEN,
    UNSEEN_LEVEL1,
    UNSEEN_LEVEL2,
    Split,
    is_implemented,
    list_tasks,
    parse_task_names,
    task_split,
)

if TYPE_CHECKING:
    from agnostos_mjx.tasks.base import Task


@functools.cache
def get_task(name: str) -> Task:
    """The task called `name`; an unknown name lists the valid ones."""
    split = task_split(name)
    task = importlib.import_module(f"agnostos_mjx.tasks.{name}").TASK
    if task.name != name or task.split != split:
        raise RuntimeError(f"module agnostos_mjx.tasks.{name} declares {task!r}")
    return task


def parse_tasks(spec: str) -> list[Task]:
    """'a,b' or a split name ('seen', 'unseen', 'unseen_level1', ...) or 'all'."""
    return [get_task(n) for n in parse_task_names(spec)]


def __getattr__(name: str) -> Any:
    if name == "Task":  # the task base class, imported (with JAX) when asked for
        from agnostos_mjx.tasks.base import Task

        return Task
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["BENCHMARK", "SEEN", "UNSEEN_LEVEL1", "UNSEEN_LEVEL2", "Split", "Task", "get_task",
           "is_implemented", "list_tasks", "parse_task_names", "parse_tasks", "task_split"]
