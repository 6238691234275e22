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

from agnostos_mjx.sim.conditions import Condition
from agnostos_mjx.sim.math3d import array_module
from agnostos_mjx.sim.observables import Layout, Observation


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


def paint(geom_rgba, flags, geom_ids: Sequence[np.ndarray], rgbs: Sequence[np.ndarray]):
    """`geom_rgba` (B, ngeom, 4) with rule r's geoms set to rgbs[r] in the worlds where
    flags[:, r] holds (B, R); other geoms and worlds unchanged.  numpy or JAX; the input is
    not changed."""
    xp = array_module(geom_rgba, flags)
    out = xp.asarray(geom_rgba)
    for r, (ids, rgb) in enumerate(zip(geom_ids, rgbs, strict=True)):
        where = np.zeros(out.shape[1:], bool)
        where[ids, :3] = True
        colour = np.zeros(out.shape[-1], out.dtype)
        colour[:3] = rgb
        out = xp.where(flags[:, r, None, None] & where, colour, out)
    return out


class StateColors:
    """A task's state colours resolved against its compiled model."""

    def __init__(self, task, model: mujoco.MjModel, layout: Layout):
        # Geoms and colours are static by contract, so variation 0 names them.
        rules = task.state_colors(np.int32(0))
        self.geom_ids = [np.array([model.geom(g).id for g in r.geoms]) for r in rules]
        self.rgbs = [np.asarray(r.rgb, np.float32) for r in rules]

        def flags(data0, data, attached, variation):
            obs0 = Observation(data0, layout, jnp.zeros_like(attached))
            return state_flags(task.state_colors(variation), obs0,
                               Observation(data, layout, attached))

        self._flags = jax.jit(jax.vmap(flags))

    def __call__(self, geom_rgba, data0, data, attached, variation):
        """`geom_rgba` repainted for the conditions that hold at `data` (the same array
        when the task declares no state colours); numpy in, numpy out, or JAX in a trace."""
        if not self.geom_ids:
            return geom_rgba
        flags = self._flags(data0, data, attached, variation)
        if array_module(geom_rgba, data) is np:
            flags = np.asarray(flags)
        return paint(geom_rgba, flags, self.geom_ids, self.rgbs)

    def update(self, geom_rgba: np.ndarray, obs0: Observation, obs: Observation,
               variation: np.ndarray) -> np.ndarray:
        """`self(...)` for observations."""
        return self(geom_rgba, obs0.data, obs.data, obs.attached, variation)
