"""Declarative success and failure conditions with RLBench semantics.

A condition is a small static object with two pure functions:
`init(obs0) -> carry` (values captured at reset, e.g. a joint's start
position) and `step(carry, obs) -> (carry, met)` evaluated at every physics
step.  Parameters may be traced (they may depend on the variation), the tree
structure may not.  This mirrors RLBench's JointCondition, DetectedCondition,
NothingGrasped, GraspedCondition, DetectedSeveralCondition and ConditionSet
(plus `Select`, a per-variation choice among conditions).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp

from agnostos_mjx.sim.math3d import quat_conj, quat_rotate
from agnostos_mjx.sim.observables import Observation


class Condition:
    def init(self, obs0: Observation) -> Any:
        return ()

    def step(self, carry: Any, obs: Observation) -> tuple[Any, jnp.ndarray]:
        raise NotImplementedError


def _select(values: jnp.ndarray, index: Any) -> jnp.ndarray:
    return values[..., 0] if index is None else jnp.take(values, index, axis=-1)


@dataclass(frozen=True)
class JointMoved(Condition):
    """|q_now - q_at_reset| > threshold for one joint (RLBench JointCondition).

    `joints` may list several joints with a traced `index` choosing one, so a
    task can pick the joint by variation inside jit.  Direction is not
    checked, exactly as in RLBench.
    """

    joints: tuple[str, ...]
    threshold: float
    index: Any = None

    def _q(self, obs: Observation) -> jnp.ndarray:
        return _select(jnp.stack([obs.joint(j) for j in self.joints], axis=-1), self.index)

    def init(self, obs0: Observation) -> jnp.ndarray:
        return self._q(obs0)

    def step(self, carry, obs):
        return carry, jnp.abs(self._q(obs) - carry) > self.threshold


@dataclass(frozen=True)
class Detected(Condition):
    """An object's probe points intersect a box sensor volume (DetectedCondition).

    The volume is a site observed as `<volume>.pos/.quat` with half sizes
    `half_extents`; the object is represented by its frame origin grown by
    `radius` (a sphere test), a primitive stand-in for CoppeliaSim's
    shape-versus-volume test.
    """

    object: str
    volume: str
    half_extents: tuple[float, float, float]
    radius: float = 0.0
    negated: bool = False

    def step(self, carry, obs):
        local = quat_rotate(quat_conj(obs.quat(self.volume)), obs.pos(self.object) - obs.pos(self.volume))
        outside = jnp.maximum(jnp.abs(local) - jnp.asarray(self.half_extents), 0.0)
        inside = jnp.linalg.norm(outside, axis=-1) <= self.radius
        return carry, jnp.logical_xor(inside, self.negated)


@dataclass(frozen=True)
class NothingGrasped(Condition):
    def step(self, carry, obs):
        return carry, ~jnp.any(obs.attached, axis=-1)


@dataclass(frozen=True)
class Grasped(Condition):
    """Graspable number `index` (in the task's `graspables` order) is attached."""

    index: int

    def step(self, carry, obs):
        return carry, obs.attached[..., self.index]


@dataclass(frozen=True)
class AllOf(Condition):
    """All hold (ConditionSet).  With `ordered`, they must become true in list
    order, one advance per step, and progress persists through the episode.
    `count` (may be traced) limits the set to its first `count` members, which
    lets one static tree serve variations that need 1, 2 or 3 sub-goals."""

    conditions: tuple[Condition, ...]
    ordered: bool = False
    count: Any = None

    def init(self, obs0):
        progress = jnp.zeros(jnp.shape(obs0.data)[:-1], jnp.int32)
        return tuple(c.init(obs0) for c in self.conditions), progress

    def step(self, carry, obs):
        sub, progress = carry
        new_sub, met = [], []
        for cond, c in zip(self.conditions, sub):
            c, m = cond.step(c, obs)
            new_sub.append(c)
            met.append(m)
        met = jnp.stack(met, axis=-1)
        n = len(self.conditions) if self.count is None else self.count
        active = jnp.arange(len(self.conditions)) < jnp.asarray(n)[..., None]
        if self.ordered:
            current = jnp.take_along_axis(
                met, jnp.minimum(progress, len(self.conditions) - 1)[..., None], axis=-1
            )[..., 0]
            progress = progress + (current & (progress < n)).astype(jnp.int32)
            return (tuple(new_sub), progress), progress >= n
        return (tuple(new_sub), progress), jnp.all(met | ~active, axis=-1)


@dataclass(frozen=True)
class AnyOf(Condition):
    conditions: tuple[Condition, ...]

    def init(self, obs0):
        return tuple(c.init(obs0) for c in self.conditions)

    def step(self, carry, obs):
        out = [cond.step(c, obs) for cond, c in zip(self.conditions, carry)]
        return tuple(c for c, _ in out), jnp.any(jnp.stack([m for _, m in out], -1), -1)


@dataclass(frozen=True)
class Select(Condition):
    """The member number `index` (may be traced, e.g. the variation) of a
    static tuple of conditions: one tree serves variations whose target
    differs (which drawer's volume, which slot).  All members are stepped."""

    conditions: tuple[Condition, ...]
    index: Any

    def init(self, obs0):
        return tuple(c.init(obs0) for c in self.conditions)

    def step(self, carry, obs):
        out = [cond.step(c, obs) for cond, c in zip(self.conditions, carry)]
        met = jnp.stack([m for _, m in out], -1)
        return tuple(c for c, _ in out), _select(met, self.index)


def never() -> Condition:
    return _Never()


class _Never(Condition):
    def step(self, carry, obs):
        return carry, jnp.zeros(jnp.shape(obs.data)[:-1], bool)


def all_of(conditions: Sequence[Condition], ordered: bool = False, count: Any = None) -> AllOf:
    return AllOf(tuple(conditions), ordered=ordered, count=count)
