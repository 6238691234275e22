"""State-dependent colours: what RLBench's ``Task.step()`` paints with ``set_color``
while an episode runs (lamp_on's bulb turns white once its switch is pressed).

A task declares them (``Task.state_colors``): "geoms G take colour A once condition X
holds"; until then they keep the colour the scene or the sampler gave them.  The
runtime evaluates the conditions from the observation after every phase and repaints
the per-world ``geom_rgba`` the renderers read.  A colour never turns back within an
episode, as in RLBench, where only ``init_episode`` resets it.  Task-agnostic: the
rules come from the task, the geoms are resolved by name against its model.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from agnostos_mjx.conditions import Condition
from agnostos_mjx.observables import Layout, Observation


@dataclass(frozen=True)
class StateColor:
    """Geoms `geoms` take colour `rgb` once `when` holds (a condition as in
    ``success``: initialised at reset, tested at the latest observation).
    `geoms` and `rgb` must not depend on the variation; `when` may."""

    geoms: tuple[str, ...]
    rgb: tuple[float, float, float]
    when: Condition


def state_flags(rules: Sequence[StateColor], obs0: Observation, obs: Observation) -> jnp.ndarray:
    """Whether each rule's condition holds at `obs` (one world; (R,) bool)."""
    if not rules:
        return jnp.zeros((0,), bool)
    return jnp.stack([jnp.asarray(r.when.step(r.when.init(obs0), obs)[1]).reshape(())
                      for r in rules])


def paint(geom_rgba: np.ndarray, flags: np.ndarray, geom_ids: Sequence[np.ndarray],
          rgbs: Sequence[np.ndarray]) -> np.ndarray:
    """A copy of `geom_rgba` (B, ngeom, 4) with rule r's geoms set to rgbs[r] in the
    worlds where flags[:, r] holds (B, R); other geoms and worlds unchanged."""
    out = np.array(geom_rgba, copy=True)
    for r, (ids, rgb) in enumerate(zip(geom_ids, rgbs, strict=True)):
        worlds = np.nonzero(flags[:, r])[0]
        out[np.ix_(worlds, ids, np.arange(3))] = rgb
    return out


class StateColors:
    """A task's state colours resolved against its compiled model."""

    def __init__(self, task, model: mujoco.MjModel, layout: Layout):
        # Geoms and colours are static by contract, so variation 0 names them.
        rules = task.state_colors(jnp.int32(0))
        self.geom_ids = [np.array([model.geom(g).id for g in r.geoms]) for r in rules]
        self.rgbs = [np.asarray(r.rgb, np.float32) for r in rules]

        def flags(data0, data, attached, variation):
            obs0 = Observation(data0, layout, jnp.zeros_like(attached))
            return state_flags(task.state_colors(variation), obs0,
                               Observation(data, layout, attached))

        self._flags = jax.jit(jax.vmap(flags))

    def update(self, geom_rgba: np.ndarray, obs0: Observation, obs: Observation,
               variation: np.ndarray) -> np.ndarray:
        """`geom_rgba` repainted for the conditions that hold at `obs` (the same array
        when the task declares no state colours)."""
        if not self.geom_ids:
            return geom_rgba
        flags = np.asarray(self._flags(obs0.data, obs.data, obs.attached, variation))
        return paint(geom_rgba, flags, self.geom_ids, self.rgbs)
