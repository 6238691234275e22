"""A task's pure per-world functions over its compiled scene, in one object.

The runner (runtime/env.py) vmaps and jits them; the key action (`StepSpec`) and the
physics boundary (runtime/phase.py) call them.  They hold no reference to the runner, so
what a key action runs is fixed by the task and its scene alone, and a user can trace them
into programs of their own.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from agnostos_mjx.sim.math3d import quat_conj, quat_rotate
from agnostos_mjx.sim.observables import Observation
from agnostos_mjx.sim.visual_state import StateColors
from agnostos_mjx.sim.world import SceneModel, apply_placement
from agnostos_mjx.tasks.base import KeyActions, Task

# Attach volume between the fingers in the tip frame (RLBench's attach proximity
# sensor: 0.02 x 0.10 m face, 0.045 m deep along the approach axis).
ATTACH_CENTER = np.array([0.0, 0.0, -0.018])
ATTACH_HALF = np.array([0.01, 0.05, 0.0275])


@dataclass(frozen=True, eq=False)
class TaskFunctions:
    """One task's sampler, settled-scene reading, condition step, grasp test and state
    colours, each for one world (`colors`: batched, numpy or traced)."""

    task: Task
    scene: SceneModel
    colors: StateColors  # (rgba, initial data, data, attached, variation) -> rgba

    @classmethod
    def of(cls, task: Task, scene: SceneModel) -> TaskFunctions:
        """The functions of `task` over `scene` (world.build_scene(task))."""
        return cls(task, scene, StateColors(task, scene.model, scene.layout))

    def _obs(self, data, attached) -> Observation:
        return Observation(data, self.scene.layout, attached)

    def sample(self, key: jax.Array, variation, attempt) -> tuple:
        """A placement as (qpos, mocap_pos, mocap_quat, rgba); attempt k > 0 draws from
        fold_in(key, k) (reset's re-sampling keeps each key's scenes deterministic)."""
        key = jnp.where(attempt > 0, jax.random.fold_in(key, attempt), key)
        return apply_placement(self.scene, self.task.sample(key, variation))

    def settled(self, data, attached, variation) -> tuple[tuple, KeyActions]:
        """(the success and failure trees' first carry, the expert's key actions): one
        program for what reset needs of a settled scene."""
        obs = self._obs(data, attached)
        carry = (self.task.success(variation).init(obs), self.task.failure(variation).init(obs))
        return carry, self.task.expert(obs, variation)

    def condition_step(self, carry: tuple, data, attached, variation) -> tuple:
        """One physics step of one world's success and failure trees: (carry, met, failed)."""
        obs = self._obs(data, attached)
        sc, s = self.task.success(variation).step(carry[0], obs)
        fc, f = self.task.failure(variation).step(carry[1], obs)
        return (sc, fc), jnp.asarray(s, bool), jnp.asarray(f, bool)

    def attach(self, data, attached) -> jax.Array:
        """Which graspables lie in the attach volume (RLBench's grasp on close)."""
        obs = self._obs(data, attached)
        tip_p, tip_q = obs["tip.pos"], obs["tip.quat"]
        hits = []
        for frame, radius in zip(self.task.grasp_frames, self.task.graspable_radius):
            local = quat_rotate(quat_conj(tip_q), obs.pos(frame) - tip_p) - ATTACH_CENTER
            gap = jnp.linalg.norm(jnp.maximum(jnp.abs(local) - ATTACH_HALF, 0.0))
            hits.append(gap <= radius)
        return jnp.stack(hits) if hits else jnp.zeros((0,), bool)
