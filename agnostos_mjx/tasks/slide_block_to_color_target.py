"""slide_block_to_color_target (seen): push the red block onto one of four coloured squares."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected
from agnostos_mjx.sim.math3d import quat_rotate
from agnostos_mjx.tasks.base import Placement, Split, Task, key_actions, place_root
from agnostos_mjx.tasks.builders.blocks import flat_patch
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_box,
    pose_in_root,
    sensor_volume,
    yaw_of,
)

ROOT = "slide_block_to_color_target_root"
BLOCK_HALF = 0.028
BLOCK_XY = (0.025, -0.025)
# Target squares (name, colour, centre in the root frame), fixed in the model.
TARGETS = (("green", (0.0, 0.68, 0.0), (0.025, 0.150)),
           ("blue", (0.0, 0.0, 0.85), (0.225, 0.075)),
           ("pink", (1.0, 0.08, 0.57), (0.025, -0.300)),
           ("yellow", (1.0, 0.76, 0.0), (-0.219, -0.129)))
TARGET_HALF = 0.05
# Pushes per target (RLBench's point<i>a..e): strokes (start, end) of the
# fingertips in the root frame.  Blue and yellow push along x first, then
# along y; green and pink have one stroke (the second repeats it, masked).
STROKES = (
    (((0.028, -0.102), (0.028, 0.145)),) * 2,
    (((-0.072, -0.027), (0.178, -0.027)), ((0.221, -0.154), (0.225, 0.070))),
    (((0.022, 0.052), (0.022, -0.295)),) * 2,
    (((0.078, -0.027), (-0.172, -0.027)), ((-0.215, 0.100), (-0.219, -0.124))),
)
TWO_STROKES = (False, True, False, True)
PUSH_Z = 0.02  # tip height while pushing (the pads reach 9 mm lower)
HOVER_Z = 0.1
BACK_OFF = 0.1  # retreat along the stroke before going round the block
HALF_CLOSED = 0.5  # RLBench's close_gripper(0.5): fingers half shut to push


class SlideBlockToColorTarget(Task):
    name = "slide_block_to_color_target"
    split = Split.SEEN
    num_variations = 4
    objects = {"target": "target1", "block": "block"}  # X-ICM names only the green target
    frames = (ROOT, "success", "target2", "target3", "target4")
    notes = (
        "RLBench ends each push with the tip 8 mm above the table (ignore_collisions); our "
        "fingers would dig into the table, so the tip stays at 2 cm. Between the two pushes "
        "for blue and yellow the expert lifts over the block (RLBench's planner went round "
        "it). One success volume is moved onto the chosen target instead of four fixed "
        "ones. The root is sampled with a 0.3 x 0.3 m footprint (the original's proxy is not "
        "documented); unreachable scenes are resampled.")

    def descriptions(self, variation: int) -> list[str]:
        c = TARGETS[variation][0]
        return [f"slide the block to {c} target", f"slide the block onto the {c} square",
                f"push the block until it is sitting on top of the {c} target",
                f"slide the block towards the {c} plane",
                f"cover the {c} target with the block by pushing the block in its direction"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        for k, (_, rgb, (x, y)) in enumerate(TARGETS):
            target = root.add_body(name=f"target{k + 1}", pos=[x, y, 0.0])
            flat_patch(target, f"target{k + 1}", (0.0, 0.0, 0.0), (TARGET_HALF, TARGET_HALF), rgb)
        # RLBench's success<i> volume (0.1 x 0.1 x 0.1 m on the target), moved
        # onto the chosen target by the sampler.
        success = scene.mocap("success_target")
        sensor_volume(success, "success", (0.0, 0.0, TARGET_HALF), (TARGET_HALF,) * 3)
        free_box(scene, "block", (BLOCK_HALF,) * 3, (1.0, 0.0, 0.0), mass=0.356)

    def sample(self, key, variation) -> Placement:
        root_pos, root_quat = place_root(key, (0.15, 0.15), jnp.pi, offset=(0.003, -0.075))
        target_xy = jnp.asarray([xy for _, _, xy in TARGETS])[variation]
        return Placement(bodies={
            ROOT: (root_pos, root_quat),
            "block": pose_in_root(root_pos, root_quat, (*BLOCK_XY, BLOCK_HALF)),
            "success_target": pose_in_root(root_pos, root_quat, (target_xy[0], target_xy[1], 0.0)),
        })

    def success(self, variation):
        return Detected("block", "success", (TARGET_HALF,) * 3, radius=BLOCK_HALF)

    def expert(self, obs, variation):
        root_pos, root_quat = obs.pos(ROOT), obs.quat(ROOT)
        strokes = jnp.asarray(STROKES, jnp.float32)[variation]  # (2, 2, 2)

        def world(xy, z):
            return root_pos + quat_rotate(root_quat, jnp.array([xy[0], xy[1], z]))

        steps, valid = [], []
        for s in range(2):
            start, end = strokes[s, 0], strokes[s, 1]
            direction = (end - start) / jnp.linalg.norm(end - start)
            # Fingers across the push direction, the wrist turned the short way.
            grip = down_grasp(yaw_of(root_quat) + jnp.arctan2(direction[1], direction[0]))
            steps += [(world(start, HOVER_Z), grip, HALF_CLOSED),  # above the start
                      (world(start, PUSH_Z), grip, HALF_CLOSED),  # down behind the block
                      (world(end, PUSH_Z), grip, HALF_CLOSED),  # push
                      (world(end - BACK_OFF * direction, PUSH_Z), grip, HALF_CLOSED)]  # back off
            second = jnp.asarray(TWO_STROKES)[variation]
            valid += [s == 0 or second] * 3 + [s == 0 and second]
        return key_actions(steps, valid=jnp.stack([jnp.asarray(v) for v in valid]))


TASK = SlideBlockToColorTarget()
