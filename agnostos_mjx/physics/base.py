"""The one physics boundary: `run(state, ctrl) -> (state, sensordata per step)`.

A `PhysicsState` is a batch of B worlds.  Everything above this layer reads
the world only through sensor data (see observables.py), so the native,
MJX-jax and MJX-warp backends are interchangeable.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

if TYPE_CHECKING:
    from agnostos_mjx.physics.capabilities import Capabilities

# MuJoCo Warp's dense constraint Jacobian stops at this many degrees of freedom.
WARP_DENSE_MAX_NV = 60


@jax.tree_util.register_dataclass
@dataclass
class PhysicsState:
    """Batch of world states (leading axis B).  `eq_data` is the per-world
    weld data of the grasp constraints (the model field, batched)."""

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray
    ctrl: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    eq_active: np.ndarray
    eq_data: np.ndarray
    time: np.ndarray

    @property
    def batch(self) -> int:
        return int(self.qpos.shape[0])

    def replace(self, **kwargs) -> PhysicsState:
        return replace(self, **kwargs)

    def numpy(self) -> PhysicsState:
        return jax.tree.map(np.asarray, self)

    def rows(self, idx: np.ndarray) -> PhysicsState:
        """The worlds `idx` as a batch of their own (host arrays)."""
        return jax.tree.map(lambda x: np.asarray(x)[idx], self)

    def with_rows(self, idx: np.ndarray, part: PhysicsState) -> PhysicsState:
        """A copy with worlds `idx` replaced by the worlds of `part`."""

        def put(full, new):
            out = np.array(full, copy=True)
            out[idx] = new
            return out

        return jax.tree.map(put, self, part)


# The fields of a world's state that a phase freezes at the world's end (and saves).
STATE_FIELDS = ("qpos", "qvel", "act", "ctrl", "time")


def keep_rows(live: jax.Array, new: jax.Array, old: jax.Array) -> jax.Array:
    """Rows of `new` where `live` (per world), else rows of `old`."""
    return jnp.where(live.reshape(-1, *[1] * (new.ndim - 1)), new, old)


def freeze(live: jax.Array, new: Any, old: Any) -> Any:
    """`new` (an mjx.Data) for live worlds; a world past its own end keeps its state (its
    ctrl too: the last control it was stepped with)."""
    return new.replace(**{f: keep_rows(live, getattr(new, f), getattr(old, f))
                          for f in STATE_FIELDS})


@dataclass(frozen=True)
class StepData:
    """The per-world data a device phase carries between physics calls (B leading) where the
    physics is not MJX's own (native MuJoCo through host callbacks, MuJoCo Warp called
    directly): the field names of mjx.Data, so the phases treat all alike."""

    qpos: Any
    qvel: Any
    act: Any
    ctrl: Any
    time: Any
    sensordata: Any
    qacc_warmstart: Any  # the solver's warm start (MuJoCo Warp carries it between calls)
    mocap_pos: Any
    mocap_quat: Any
    eq_active: Any
    eq_data: Any

    def replace(self, **changes: Any) -> StepData:
        return replace(self, **changes)

    @classmethod
    def start(cls, state: PhysicsState, nsensordata: int) -> StepData:
        """A phase's starting data: sensors and the solver's warm start at zero, as in a
        fresh mjx.Data."""
        return cls(qpos=state.qpos, qvel=state.qvel, act=state.act, ctrl=state.ctrl,
                   time=state.time, sensordata=jnp.zeros((state.batch, nsensordata), jnp.float32),
                   qacc_warmstart=jnp.zeros_like(state.qvel), mocap_pos=state.mocap_pos,
                   mocap_quat=state.mocap_quat, eq_active=state.eq_active,
                   eq_data=state.eq_data)

    def saved(self, state: PhysicsState) -> PhysicsState:
        """`state` with this data's STATE_FIELDS."""
        return state.replace(**{f: getattr(self, f) for f in STATE_FIELDS})


jax.tree_util.register_dataclass(StepData, data_fields=[f.name for f in fields(StepData)],
                                 meta_fields=[])


class Backend(Protocol):
    name: str
    capabilities: Capabilities  # what the layers above may rely on (physics.CAPABILITIES)

    def run(self, state: PhysicsState, ctrl: np.ndarray, steps: np.ndarray | None = None
            ) -> tuple[PhysicsState, np.ndarray]:
        """Step world w steps[w] times (default all T) with per-step controls ctrl[B, T, nu];
        return the final state and sensordata[B, T, nsensordata] after each step.  A world
        past its own end stays frozen: its state is that after its last step, and its
        sensordata rows repeat its last row (rows of a world with 0 steps are undefined)."""
        ...


def check_steps(steps: np.ndarray | None, batch: int, horizon: int) -> np.ndarray:
    """Per-world step counts as int32 (B,), all `horizon` when not given."""
    if steps is None:
        return np.full(batch, horizon, np.int32)
    steps = np.asarray(steps, np.int32)
    if steps.shape != (batch,) or np.any((steps < 0) | (steps > horizon)):
        raise ValueError(f"steps must be {batch} counts in 0..{horizon}, got {steps}")
    return steps


def for_warp(model: Any) -> Any:
    """`model` as MuJoCo Warp accepts it: a copy with the Jacobian left to MuJoCo's `auto`
    (sparse above 60 dofs) where the scene asks for a dense one that Warp refuses (the rope,
    the groceries).  The same model where nothing needs changing, so smaller scenes step
    exactly as before; the CPU's dense choice (scenes/world.xml) is untouched."""
    import copy

    import mujoco

    dense = model.opt.jacobian == mujoco.mjtJacobian.mjJAC_DENSE
    if not dense or model.nv <= WARP_DENSE_MAX_NV:
        return model
    warp_model = copy.copy(model)
    warp_model.opt.jacobian = mujoco.mjtJacobian.mjJAC_AUTO
    return warp_model
