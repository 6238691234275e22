"""push_buttons (seen): press one, two or three coloured buttons in order."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp

from agnostos_mjx.sim.colors import COLORS
from agnostos_mjx.sim.conditions import JointMoved, all_of
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders import push_button
from agnostos_mjx.tasks.builders.common import DOWN, spawn_many_on_root_plane

# The 18-colour list without red and lime; variation i uses permutation i // 3
# of it and presses 1 + i % 3 buttons (only permutations 0-16 are reachable).
BUTTON_COLORS = tuple((n, c) for n, c in COLORS if n not in ("red", "lime"))
PERMUTATIONS = tuple(itertools.islice(itertools.permutations(range(len(BUTTON_COLORS)), 3), 17))
BOUNDARY_HALF = (0.258, 0.339)
UNIT_HALF = (0.05, 0.05)
HOVER, PRESS = 0.083 + 0.009, 0.016


class PushButtons(Task):
    name = "push_buttons"
    split = Split.SEEN
    num_variations = 50
    objects = {"button": "push_buttons_target0"}
    frames = ("push_buttons_target1", "push_buttons_target2")
    joints = tuple(f"target_button{k}_joint" for k in range(3))
    notes = ("The plates stay red: RLBench's step() means to turn a pressed button's plate "
             "and ring green, but its check (condition_met() == (True, True); conditions "
             "return (met, False)) never holds.")

    def descriptions(self, variation: int) -> list[str]:
        names = [BUTTON_COLORS[i][0] for i in PERMUTATIONS[variation // 3]]
        n = 1 + variation % 3
        push = f"push the {names[0]} button" + "".join(
            f", then push the {c} button" for c in names[1:n])
        press = f"press the {names[0]} button" + "".join(
            f", then press the {c} button" for c in names[1:n])
        base = f"push down the button with the {names[0]} base" + "".join(
            f", then the {c} one" for c in names[1:n])
        return [push, press, base]

    def build(self, scene) -> None:
        for k in range(3):
            unit = scene.mocap(f"push_buttons_target{k}")
            push_button(scene, unit, f"target_button{k}")

    def sample(self, key, variation) -> Placement:
        k_root, k_units, k_spare = jax.random.split(key, 3)
        root_pos, root_quat = place_root(k_root, BOUNDARY_HALF, jnp.pi)
        units = spawn_many_on_root_plane(k_units, (root_pos, root_quat), [UNIT_HALF] * 3,
                                         (0.0, 0.0), BOUNDARY_HALF, min_distance=0.1)
        bodies = {f"push_buttons_target{k}": pose for k, pose in enumerate(units)}
        # Bases 0..n-1 take the permutation's colours, the rest spare colours.
        perm = jnp.asarray(PERMUTATIONS)[variation // 3]
        n = 1 + variation % 3
        rgb = jnp.asarray([c for _, c in BUTTON_COLORS], jnp.float32)
        used = jnp.zeros(len(BUTTON_COLORS), bool).at[perm].set(jnp.arange(3) < n)
        spare_order = jax.random.permutation(k_spare, len(BUTTON_COLORS))
        spare = spare_order[jnp.argsort(used[spare_order], stable=True)]  # unused first
        colors = {}
        for k in range(3):
            idx = jnp.where(k < n, perm[k], spare[k])
            colors[f"target_button{k}_base"] = rgb[idx]
        return Placement(bodies=bodies, colors=colors)

    def success(self, variation):
        presses = [JointMoved((j,), 0.001) for j in self.joints]
        return all_of(presses, ordered=True, count=1 + variation % 3)

    def expert(self, obs, variation):
        n = 1 + variation % 3
        steps, valid = [], []
        for k in range(3):
            frame = f"push_buttons_target{k}"
            steps += [(in_frame(obs, frame, (0, 0, HOVER)), DOWN, 0.1),
                      (in_frame(obs, frame, (0, 0, PRESS)), DOWN, 0.1)]
            valid += [k < n, k < n]
        return key_actions(steps, valid=jnp.stack(valid))


TASK = PushButtons()
