"""stack_blocks (seen): stack 2, 3 or 4 blocks of one colour on the green plate."""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from agnostos_mjx.sim.colors import COLORS
from agnostos_mjx.sim.conditions import Condition, Detected, NothingGrasped, all_of
from agnostos_mjx.sim.math3d import yaw_quat
from agnostos_mjx.tasks.base import (
    TABLE_Z,
    WORKSPACE_CENTER,
    Placement,
    Split,
    Task,
    in_frame,
    key_actions,
    sample_on_plane,
)
from agnostos_mjx.tasks.builders.blocks import robot_keep_out, spawn_on_planes, square_grasp_yaw
from agnostos_mjx.tasks.builders.common import down_grasp, free_box, pose_in_root, sensor_volume
from agnostos_mjx.tasks.builders.primitives import panel

NUMBERS = {2: "2", 3: "3", 4: "4"}
TARGETS = tuple(f"stack_blocks_target{k}" for k in range(4))
DISTRACTORS = tuple(f"stack_blocks_distractor{k}" for k in range(4))
HALF = 0.025  # 5 cm cubes
PLATE_HALF = (0.0375, 0.0375, 0.025)
PLATE_RGB = (0.5, 1.0, 0.5)
# Spawn planes around the plate, (centre, half extents) in the root frame.
BOUNDARIES = (((0.0, 0.225), (0.3, 0.18)), ((0.0, -0.225), (0.3, 0.18)),
              ((0.175, 0.0), (0.125, 0.05)), ((-0.175, 0.0), (0.125, 0.05)))
# The plate (root) lands in the central 0.2 x 0.2 m of the workspace; see notes.
ROOT_AREA_HALF = (0.1, 0.1)
PLATE_KEEP_OUT = (0.09, 0.09)
CARRY_Z = 0.3  # tip height above the plate while carrying or leaving the tower
RELEASE_GAP = 0.008  # the block is let go this far above its resting height


@dataclass(frozen=True)
class AtLeast(Condition):
    """At least `count` of the conditions hold (RLBench's DetectedSeveralCondition)."""

    conditions: tuple[Condition, ...]
    count: object

    def init(self, obs0):
        return tuple(c.init(obs0) for c in self.conditions)

    def step(self, carry, obs):
        out = [cond.step(c, obs) for cond, c in zip(self.conditions, carry)]
        met = jnp.stack([m for _, m in out], -1).sum(-1)
        return tuple(c for c, _ in out), met >= self.count


class StackBlocks(Task):
    name = "stack_blocks"
    split = Split.SEEN
    num_variations = 60
    objects = {"first block": TARGETS[0], "second block": TARGETS[1], "third block": TARGETS[2],
               "fourth block": TARGETS[3], "plane": "stack_blocks_target_plane"}
    frames = ("stack_blocks_success",)
    graspables = TARGETS
    graspable_radius = (HALF,) * 4
    max_key_actions = 25
    notes = (
        "The original draws two distractor colours but paints all four distractors with the "
        "first (int(i / 4) is always 0); here distractors 0-1 take the first and 2-3 the "
        "second. The plate (task root) is sampled in the central 0.2 x 0.2 m of the "
        "workspace so the 0.6 x 0.81 m spawn area around it stays mostly within reach "
        "(the workspace extent is unverified). Blocks keep 9 cm clear of the plate and "
        "out of a 0.6 m square around the robot base (arm folded at its limits); RLBench "
        "relied on resampling when planning failed. The expert approaches each block from "
        "10 cm above, carries it 0.3 m above the plate and lets it go 8 mm above its "
        "resting place (RLBench drops from higher), so towers of four stay up; its "
        "fingers close across the direction of the tower.")

    def descriptions(self, variation: int) -> list[str]:
        c = COLORS[variation // 3][0]
        n = NUMBERS[2 + variation % 3]
        return [f"stack {n} {c} blocks", f"place {n} of the {c} cubes on top of each other",
                f"pick up and set down {n} {c} blocks on top of each other",
                f"build a tall tower out of {n} {c} cubes",
                f"arrange {n} {c} blocks in a vertical stack on the table top",
                f"set {n} {c} cubes on top of each other"]

    def build(self, scene) -> None:
        root = scene.mocap("stack_blocks_root")
        plate = root.add_body(name="stack_blocks_target_plane", pos=[0.0, 0.0, 0.0])
        panel(plate, PLATE_HALF, (0.0, 0.0, PLATE_HALF[2]), PLATE_RGB)
        # A thin column from the plate's mid-height up 0.2 m.
        sensor_volume(plate, "stack_blocks_success", (0.0, 0.0, 0.125), (0.005, 0.005, 0.1))
        for name in TARGETS + DISTRACTORS:
            free_box(scene, name, (HALF,) * 3, (0.5, 0.0, 0.0), mass=0.125)

    def sample(self, key, variation) -> Placement:
        k_root, k_yaw, k_blocks, k_colors = jax.random.split(key, 4)
        xy, _ = sample_on_plane(k_root, (0.0, 0.0), 0.0, plane_center=WORKSPACE_CENTER,
                                plane_half=ROOT_AREA_HALF)
        root_pos = jnp.concatenate([xy, jnp.array([TABLE_Z])])
        root_quat = yaw_quat(jax.random.uniform(k_yaw, minval=-jnp.pi, maxval=jnp.pi))
        # Blocks keep clear of the plate (so the fingers never brush the tower)
        # and of the robot base.
        plate = (jnp.zeros(2), jnp.zeros(()), jnp.asarray(PLATE_KEEP_OUT))
        keep_out = [plate, robot_keep_out(root_pos, root_quat)]
        placed, bodies = [], {"stack_blocks_root": (root_pos, root_quat)}
        for name, k in zip(TARGETS + DISTRACTORS, jax.random.split(k_blocks, 8)):
            bxy, yaw = spawn_on_planes(k, (HALF, HALF), BOUNDARIES, others=tuple(keep_out + placed),
                                       min_distance=0.1)
            placed.append((bxy, yaw, jnp.asarray((HALF, HALF))))
            bodies[name] = pose_in_root(root_pos, root_quat, (bxy[0], bxy[1], HALF), yaw_quat(yaw))
        rgb = jnp.asarray([c for _, c in COLORS], jnp.float32)
        target = variation // 3
        others = jax.random.choice(k_colors, len(COLORS) - 1, (2,), replace=False)
        others = others + (others >= target)  # skip the target colour
        colors = {name: rgb[target] for name in TARGETS}
        colors |= {name: rgb[others[k // 2]] for k, name in enumerate(DISTRACTORS)}
        return Placement(bodies=bodies, colors=colors)

    def success(self, variation):
        stacked = AtLeast(tuple(Detected(t, "stack_blocks_success", (0.005, 0.005, 0.1), HALF)
                                for t in TARGETS), 2 + variation % 3)
        return all_of([stacked, NothingGrasped()])

    def expert(self, obs, variation):
        n = 2 + variation % 3
        plate_top = in_frame(obs, "stack_blocks_target_plane", (0.0, 0.0, 2 * PLATE_HALF[2]))
        steps, valid = [], []
        for k, block in enumerate(TARGETS):
            at = obs.pos(block)
            to_tower = (plate_top - at)[:2]
            grip = down_grasp(square_grasp_yaw(obs.quat(block), to_tower), wrap=False)
            rest = plate_top + jnp.array([0.0, 0.0, HALF * (2 * k + 1)])
            release = rest + jnp.array([0.0, 0.0, RELEASE_GAP])
            steps += [
                (at + jnp.array([0.0, 0.0, 0.1]), grip, 1.0),  # above the block
                (at, grip, 0.0),  # down around it: close, attach
                (at.at[2].set(plate_top[2] + CARRY_Z), grip, 0.0),  # lift clear of the tower
                (release + jnp.array([0.0, 0.0, 0.06]), grip, 0.0),  # above the tower
                (release, grip, 1.0),  # lower and let go
                (release.at[2].set(plate_top[2] + CARRY_Z), grip, 1.0),  # retreat upwards
            ]
            valid += [k < n] * 5 + [k < n - 1]  # no retreat after the last block
        return key_actions(steps, valid=jnp.stack([jnp.asarray(v) for v in valid]))


TASK = StackBlocks()
