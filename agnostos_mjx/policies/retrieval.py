"""Retrieval: a deterministic, LLM-free baseline.

It selects demonstrations exactly as X-ICM does and replays the top-ranked
one in the query scene: each demo key action is anchored to the demo object
nearest to it and moved with that object's counterpart in the query scene
(objects matched by their order in the task's object list, cyclically).
Orientations and gripper states are copied.  It answers "how far does
copying the most similar seen demonstration get?", the floor an LLM should
beat.
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.policies.base import Round
from agnostos_mjx.policies.demo_selection import demo_selection, queries_for, warm_selection
from agnostos_mjx.policies.learned_options import RetrievalOptions
from agnostos_mjx.policies.planning import PlanningPolicy, PlanResult
from agnostos_mjx.sim.control import ACTION_BOUNDS


def transfer(key_pos: np.ndarray, demo_objects: np.ndarray, query_objects: np.ndarray
             ) -> np.ndarray:
    """Move each key position with its nearest demo object's matched query object."""
    demo = demo_objects[~np.isnan(demo_objects).any(-1)]
    if len(demo) == 0 or len(query_objects) == 0:
        return key_pos.copy()
    nearest = np.argmin(np.linalg.norm(key_pos[:, None] - demo[None], axis=-1), axis=1)
    target = query_objects[nearest % len(query_objects)]
    moved = target + (key_pos - demo[nearest])
    lo, hi = (np.asarray(b, np.float32) for b in ACTION_BOUNDS)
    return np.clip(moved, lo, hi)


class RetrievalPolicy(PlanningPolicy):
    """Privileged: the query scene's object positions come from the simulator."""

    name = "retrieval"
    privileged = True

    def __init__(self, options: RetrievalOptions | None = None) -> None:
        super().__init__()
        o = options or RetrievalOptions()
        self.memory, self.selection, self.selector = demo_selection(o)
        self.name = f"retrieval[{self.selection}]"

    @classmethod
    def warm_up(cls, options: RetrievalOptions, batch: int) -> bool:
        return warm_selection(options)

    def plan_steps(self, view: Round, worlds: np.ndarray):
        task, env = view.episodes.task, view.env
        names = list(task.objects)
        selected = self.selector.submit(queries_for(self, view, worlds, self.selection), 1)
        yield selected  # the evaluator runs other tasks while the features are computed
        chosen = selected.result()
        results = []
        for w, idx in zip(worlds, chosen):
            i = int(idx[0])
            n = int(self.memory.n_keys[i])
            query = np.stack([np.asarray(env.obs.pos(task.objects[nm]))[w] for nm in names]) \
                if names else np.zeros((0, 3), np.float32)
            pos = transfer(self.memory.key_pos[i, :n], self.memory.objects[i], query)
            results.append(PlanResult(pos, self.memory.key_quat[i, :n],
                                      self.memory.key_open[i, :n],
                                      info={"selected": [f"{self.memory.task[i]}#{i}"]}))
        return results
