"""The state of a batch of episodes: one pytree, returned by every runtime call, never
mutated.  The same type lives on the host (numpy, native MuJoCo) and on the device (JAX
arrays next to MJX), so the key action is written once for both."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from agnostos_mjx.physics.base import PhysicsState
from agnostos_mjx.runtime.outcome import is_done
from agnostos_mjx.sim.observables import Layout, Observation


@dataclass(frozen=True)
class EnvState:
    """Per-world bookkeeping (leading axis B) of one task's batch of episodes."""

    physics: PhysicsState
    data: Any  # latest sensor row (B, nsensordata)
    attached: Any  # (B, ngraspable): grasp welds on
    carry: Any  # (success, failure) carries of the task's condition trees
    variation: Any
    gripper: Any  # commanded finger position
    outcome: Any  # runtime.outcome.Outcome per world
    key_actions: Any  # key actions executed so far
    sim_steps: Any  # physics steps each world needed (to its end in every phase)
    world_steps: Any  # physics steps run for it, counting those past its end (lockstep)
    geom_rgba: Any  # (B, ngeom, 4): each world's colours (variations, state colours)
    initial_data: Any  # the sensor row after reset: what the expert and colours start from
    layout: Layout  # static: names of the sensor columns
    stop_at_success: bool = True  # static: False for demonstrations (see outcome.is_done)

    def replace(self, **changes: Any) -> EnvState:
        return dataclasses.replace(self, **changes)

    @property
    def batch(self) -> int:
        return int(np.shape(self.outcome)[0])

    @property
    def obs(self) -> Observation:
        """The latest observation of every world (named sensor columns)."""
        return Observation(self.data, self.layout, self.attached)

    @property
    def initial_obs(self) -> Observation:
        return Observation(self.initial_data, self.layout, self.attached & False)

    @property
    def done(self):
        return is_done(self.outcome, self.stop_at_success)

    def to_device(self, dtype=jnp.float32) -> EnvState:
        """The state as JAX arrays, floats as `dtype` (what MJX steps); arrays already on
        the device pass through."""

        def put(x):
            x = jnp.asarray(x)
            return x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x

        ints = dict(outcome=jnp.int32, key_actions=jnp.int32, sim_steps=jnp.int32,
                    world_steps=jnp.int32, variation=jnp.int32)
        return self.replace(
            physics=jax.tree.map(put, self.physics), data=put(self.data),
            attached=jnp.asarray(self.attached, bool), carry=jax.tree.map(jnp.asarray, self.carry),
            gripper=put(self.gripper), geom_rgba=jnp.asarray(self.geom_rgba),
            initial_data=put(self.initial_data),
            **{k: jnp.asarray(getattr(self, k), t) for k, t in ints.items()})

    def to_host(self) -> EnvState:
        """What policies and records read, as numpy; the physics state and the condition
        carries stay where they are (the device keeps them between key actions)."""
        host = {k: np.asarray(getattr(self, k)) for k in
                ("data", "attached", "variation", "outcome", "key_actions", "sim_steps",
                 "world_steps", "geom_rgba", "initial_data")}
        host["gripper"] = np.asarray(self.gripper, np.float64)
        return self.replace(**host)


jax.tree_util.register_dataclass(
    EnvState,
    data_fields=["physics", "data", "attached", "carry", "variation", "gripper", "outcome",
                 "key_actions", "sim_steps", "world_steps", "geom_rgba", "initial_data"],
    meta_fields=["layout", "stop_at_success"])


@dataclass(frozen=True)
class StepResult:
    """Per-step sensordata of one phase of a key action (recorded for demonstrations)."""

    sensordata: np.ndarray  # (B, T, nsensordata)
    attached: np.ndarray  # (B, T, ngraspable)
    valid: np.ndarray  # (B, T): False after a world finished
    qpos: np.ndarray | None = None  # (B, T, nq) after each step when asked (native only)
