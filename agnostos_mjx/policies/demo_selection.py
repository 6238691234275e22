"""The demo selection that retrieval and X-ICM share: the seen-demo memory and its
selector built from the options, their programs warmed up, and each replanned world's
query (instruction, seed and, for the dynamics model's features, its front frame)."""

from __future__ import annotations

import numpy as np

from agnostos_mjx.policies.base import Round
from agnostos_mjx.policies.learned_options import RetrievalOptions
from agnostos_mjx.policies.planning import PlanningPolicy
from agnostos_mjx.xicm.memory import DemoMemory, default_memory_path
from agnostos_mjx.xicm.selection import Query, Selector, make_selector, resolve_selection

QUERY_FRAME = 128  # pixels: the front frame a selection query renders


def needs_frames(selection: str) -> bool:
    return "vis" in selection


def demo_selection(options: RetrievalOptions) -> tuple[DemoMemory, str, Selector]:
    """(the seen-demo memory, the resolved selection, its selector) of the options that
    retrieval and X-ICM share."""
    memory = DemoMemory.load(options.memory or default_memory_path())
    selection = resolve_selection(options.selection, memory)
    return memory, selection, make_selector(selection, memory, sample_steps=options.sample_steps)


def warm_selection(options: RetrievalOptions) -> bool:
    """The demo selection's programs, compiled with one query of a blank front frame: its
    networks run at one batch shape whatever the task, batch or frame
    (dynamics/batching.py), so this is every program the selection will run.  Built from
    the options alone: no LLM is asked (X-ICM shares retrieval's selection)."""
    _, selection, selector = demo_selection(options)
    frame = np.zeros((QUERY_FRAME, QUERY_FRAME, 3), np.uint8) if needs_frames(selection) \
        else None
    selector.select([Query("press the button", 0, frame)], 1)
    return True


def queries_for(policy: PlanningPolicy, view: Round, worlds: np.ndarray, selection: str
                ) -> list[Query]:
    """Selection queries of the worlds being (re)planned: instruction, a seed
    per (episode, replan) and, for dynamics features, the current front frame."""
    frames = None
    if needs_frames(selection):  # only the worlds being replanned
        frames = view.episodes.render(view.env, "front", QUERY_FRAME, QUERY_FRAME,
                                      worlds=worlds)
    return [Query(policy.instructions[w], policy.plan_seed(w),
                  None if frames is None else frames[i]) for i, w in enumerate(worlds)]
