"""Named views into MuJoCo sensor data: everything task logic and policies read.

Every backend returns the same `sensordata` array per physics step; a static
`Layout` maps names ("tip.pos", "drawer_bottom_joint.q", "button0.pos", ...) to
slices of it, so conditions and policies never touch backend internals.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp


@dataclass(frozen=True)
class Layout:
    """Static map from observable name to (start, size) in the sensor vector."""

    entries: tuple[tuple[str, int, int], ...]

    def slice(self, name: str) -> slice:
        for entry, start, size in self.entries:
            if entry == name:
                return slice(start, start + size)
        known = ", ".join(e for e, _, _ in self.entries)
        raise KeyError(f"unknown observable {name!r}; known: {known}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(e for e, _, _ in self.entries)

    @property
    def size(self) -> int:
        return max((s + n for _, s, n in self.entries), default=0)


@jax.tree_util.register_pytree_node_class
class Observation:
    """Sensor data (any leading batch/time shape) plus per-world `attached`:

    observables that do not come from sensors: which graspable
    objects are attached to the gripper (the RLBench kinematic grasp).
    """

    def __init__(self, data: jnp.ndarray, layout: Layout, attached: jnp.ndarray):
        self.data = data
        self.layout = layout
        self.attached = attached

    def __getitem__(self, name: str) -> jnp.ndarray:
        return self.data[..., self.layout.slice(name)]

    def pos(self, frame: str) -> jnp.ndarray:
        return self[f"{frame}.pos"]

    def quat(self, frame: str) -> jnp.ndarray:
        return self[f"{frame}.quat"]

    def joint(self, joint: str) -> jnp.ndarray:
        return self[f"{joint}.q"][..., 0]

    def tree_flatten(self):
        return (self.data, self.attached), self.layout

    @classmethod
    def tree_unflatten(cls, layout, children):
        return cls(children[0], layout, children[1])
