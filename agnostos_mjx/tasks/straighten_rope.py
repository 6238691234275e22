"""straighten_rope (unseen, Level 2): drag each end of a rope onto its
green patch, leaving the rope straight between them."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, all_of
from agnostos_mjx.sim.math3d import yaw_quat
from agnostos_mjx.tasks.base import Placement, Split, Task, in_frame, key_actions, place_root
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    grasp_site,
    pose_in_root,
    sensor_volume,
    yaw_of,
)
from agnostos_mjx.tasks.builders.primitives import panel
from agnostos_mjx.tasks.builders.props import rope

ROOT = "straighten_rope_root"
# RLBench's rope, tail to head: the tail's free end, the 17 joints, the
# head's free end (root frame); 18 links of 0.01 m diameter.
POINTS = ((-0.035, 0.083), (-0.059, 0.083), (-0.081, 0.078), (-0.101, 0.067), (-0.117, 0.051),
          (-0.128, 0.031), (-0.132, 0.009), (-0.128, -0.014), (-0.116, -0.034), (-0.100, -0.049),
          (-0.083, -0.065), (-0.070, -0.083), (-0.064, -0.105), (-0.066, -0.128), (-0.075, -0.149),
          (-0.091, -0.165), (-0.113, -0.173), (-0.136, -0.171), (-0.158, -0.161))
MASSES = (0.00157,) + (0.0251,) * 17
LINK_RADIUS = 0.005
TAIL, HEAD = "rope_0", f"rope_{len(POINTS) - 2}"
TAIL_TARGET, HEAD_TARGET = (-0.127, 0.095), (-0.127, -0.293)
# Sensors `success_tail` / `success_head`: 0.06 (x) x 0.10 (y) m, from the
# patch up to 0.018 m; an end link counts when its centre is within its
# half-length (0.01 m) of the box.
SENSOR_HALF = (0.03, 0.05, 0.01)
# Where the expert leaves each end: the tail on its patch, the head 3.3 cm
# short of its patch's centre so the rope (0.37 m end to end) stays slack
# and does not pull the tail off again.
TAIL_DROP, HEAD_DROP = TAIL_TARGET, (-0.127, -0.26)
PINCH_HEIGHT = 0.007  # tip above a link's centre: fingertips 3 mm above the table


def _pinch(obs, link: str):
    """Tip pose pinching a link across its axis, the wrist turned at most 90
    degrees from home."""
    return obs.pos(link) + jnp.array([0.0, 0.0, PINCH_HEIGHT]), down_grasp(yaw_of(obs.quat(link)))


class StraightenRope(Task):
    name = "straighten_rope"
    split = Split.LEVEL2
    objects = {"rope head": HEAD, "rope head target": "rope_head_target",
               "rope head tail": "rope_tail_target", "rope tail": TAIL}
    frames = (ROOT, "rope_success_head", "rope_success_tail")
    graspables = (TAIL, HEAD)
    graspable_radius = (0.01, 0.01)
    notes = ("RLBench drags the rope's ends by pinching them with friction (they are not "
             "registered graspables); here closing on an end attaches it (kinematic grasp), "
             "which is reliable with capsule links. The links do not collide with each other. "
             "The sensors are read as 0.06 m along x by 0.10 m along y, as their near faces say. "
             "The expert drags the tail onto its patch, then the head to 3.3 cm short of its "
             "patch's centre (RLBench overshoots with the tail and lets the head drag pull it "
             "back). X-ICM's 'rope head tail' is the tail's patch (the original's name).")

    def descriptions(self, variation: int) -> list[str]:
        return ["straighten rope", "pull the rope straight",
                "grasping each end of the rope in turn, leave the rope straight on the table",
                "pull each end of the rope until is is straight", "tighten the rope",
                "pull the rope tight"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        for target, (x, y) in (("head", HEAD_TARGET), ("tail", TAIL_TARGET)):
            patch = panel(root, (0.05, 0.025, 0.0005), (x, y, 0.0005), (0.2, 0.6, 0.2),
                          collide=False, name=f"rope_{target}_target_patch")
            patch.group = 1
            grasp_site(root, f"rope_{target}_target", (x, y, 0.001))
            sensor_volume(root, f"rope_success_{target}", (x, y, 0.008), SENSOR_HALF)
        rope(scene, "rope", POINTS, radius=LINK_RADIUS, masses=MASSES)

    def sample(self, key, variation) -> Placement:
        # RLBench only turns the root (any yaw).  Footprint: rope and patches,
        # x[-0.18, -0.03], y[-0.32, 0.12].
        pos, quat = place_root(key, (0.075, 0.22), jnp.pi, offset=(-0.105, -0.1))
        a, b = jnp.asarray(POINTS[0]), jnp.asarray(POINTS[1])
        local = jnp.array([*(a + b) / 2, LINK_RADIUS])
        yaw = jnp.arctan2(*(b - a)[::-1])
        return Placement(bodies={ROOT: (pos, quat),
                                 TAIL: pose_in_root(pos, quat, local, yaw_quat(yaw))})

    def success(self, variation):
        return all_of([
            Detected(HEAD, "rope_success_head", SENSOR_HALF, radius=0.01),
            Detected(TAIL, "rope_success_tail", SENSOR_HALF, radius=0.01),
        ])

    def expert(self, obs, variation):
        steps = []
        for link, drop in ((TAIL, TAIL_DROP), (HEAD, HEAD_DROP)):
            at, quat = _pinch(obs, link)
            target = in_frame(obs, ROOT, (*drop, 0.0)).at[2].set(at[2])
            up = jnp.array([0.0, 0.0, 0.06])
            steps += [(at + up, quat, 1.0),  # above the end
                      (at, quat, 0.0),  # pinch it, close: attach
                      (target, quat, 1.0),  # drag it along the table, release
                      (target + up, quat, 1.0)]  # lift clear
        return key_actions(steps)


TASK = StraightenRope()
