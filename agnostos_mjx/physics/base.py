"""The one physics boundary: `run(state, ctrl) -> (state, sensordata per step)`.

A `PhysicsState` is a batch of B worlds.  Everything above this layer reads
the world only through sensor data (see observables.py), so the native,
MJX-jax and MJX-warp backends are interchangeable.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol

import jax
import numpy as np


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


class Backend(Protocol):
    name: str

    def run(self, state: PhysicsState, ctrl: np.ndarray) -> tuple[PhysicsState, np.ndarray]:
        """Step every world len(ctrl[0]) times with per-step controls ctrl[B, T, nu];
        return the final state and sensordata[B, T, nsensordata] after each step."""
        ...
