"""put_money_in_safe (seen): put the stack of bank notes on the named shelf of the safe."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from agnostos_mjx.sim.conditions import NothingGrasped, all_of
from agnostos_mjx.sim.math3d import yaw_quat
from agnostos_mjx.tasks.base import Placement, Split, Task, in_frame, key_actions, sample_on_plane
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_body,
    pose_in_root,
    sensor_volume,
    yaw_of,
)
from agnostos_mjx.tasks.builders.containers import (
    MONEY_HALF,
    SAFE_HALF,
    SAFE_SHELVES,
    detected_one_of,
    money_stack,
    place_root_between,
    safe,
)

SHELVES = ("bottom", "middle", "top")
SAFE_AT, SAFE_YAW = (-0.048, -0.25, SAFE_HALF[2]), 0.349  # root frame; 20 degrees
# RLBench's detectors: 0.2 x 0.2 x 0.01 m boxes on each shelf, their centre
# 0.012 m behind the safe's centre.
DETECTOR_HALF = (0.1, 0.1, 0.005)
DETECTOR_Y = -0.012
MONEY_PLANE_HALF = (0.1115, 0.1415)  # dollar_stack_boundary on the safe's roof
MONEY_RADIUS = 0.068  # the stack's half diagonal: fits the plane at any yaw
GRIP_ABOVE = 0.0  # tip at the money's centre when grasping
BOTTOM_CLEARANCE = 0.02  # m, money above the bottom shelf while sliding in
IN_FRONT = 0.075  # stand-off in front of the safe's face: the money's front end clears it
# What must fit the workspace: the safe's box, turned by SAFE_YAW in the root
# frame (with the open door the footprint would never fit our inferred
# workspace, and the sampler would fall back to unchecked placements).
SAFE_FOOTPRINT = (np.cos(SAFE_YAW) * SAFE_HALF[0] + np.sin(SAFE_YAW) * SAFE_HALF[1],
                  np.sin(SAFE_YAW) * SAFE_HALF[0] + np.cos(SAFE_YAW) * SAFE_HALF[1])


class PutMoneyInSafe(Task):
    name = "put_money_in_safe"
    split = Split.SEEN
    num_variations = 3
    # X-ICM's name map calls the safe "shelf"; we name it what it is.
    objects = {"money": "dollar_stack", "safe": "safe_body"}
    frames = ("success_detector0", "success_detector1", "success_detector2")
    joints = ("safe_body_door_joint",)
    graspables = ("dollar_stack",)
    graspable_radius = (0.01,)
    notes = ("Primitive safe (box walls, two shelf planks, door swung open on a passive hinge "
             "held by friction) in the layout of RLBench's model, rotated 20 degrees in the "
             "root frame. X-ICM's name map calls the safe 'shelf'; we use 'safe'. RLBench "
             "keeps one tilted gripper orientation and grasps the stack's front end; our "
             "expert grasps the stack top-down across its width, turns it in the air to "
             "face the safe and slides it in level (the hand fits a shelf's 0.145 m slot), "
             "with via-points in front of the safe instead of the planner. The money's "
             "yaw (0..pi/2) and the root's yaw (0..pi/2) follow RLBench; the root is "
             "placed so that the safe's box (not the swung-open door, which would never "
             "fit our inferred workspace) lies in the workspace. When the safe faces the "
             "robot from close by, the bottom shelf is at the elbow's limit; the expert "
             "descends to it in two straight moves (one long one loses the IK track there).")

    def descriptions(self, variation: int) -> list[str]:
        s = SHELVES[variation]
        return [f"put the money away in the safe on the {s} shelf",
                f"leave the money on the {s} shelf on the safe",
                f"place the stack of bank notes on the {s} shelf of the safe"]

    def build(self, scene) -> None:
        root = scene.mocap("put_money_in_safe_root")
        body = safe(scene, root, "safe_body", SAFE_AT, SAFE_YAW)
        for k, top in enumerate(SAFE_SHELVES):
            z = -SAFE_HALF[2] + top + DETECTOR_HALF[2] - 0.001
            sensor_volume(body, f"success_detector{k}", (0.0, DETECTOR_Y, z), DETECTOR_HALF)
        money_stack(free_body(scene, "dollar_stack", pos=(0, 0, 1.2)), "dollar_stack")

    def sample(self, key, variation) -> Placement:
        k_root, k_money = jax.random.split(key)
        root_pos, root_quat = place_root_between(k_root, SAFE_FOOTPRINT, 0.0, jnp.pi / 2,
                                                 offset=SAFE_AT[:2])
        # The money lies on the safe's roof (its spawn plane), turned 45 degrees.
        safe_bottom = pose_in_root(root_pos, root_quat, (*SAFE_AT[:2], 0.0), yaw_quat(SAFE_YAW))
        xy, yaw = sample_on_plane(k_money, (MONEY_RADIUS, MONEY_RADIUS), jnp.pi / 4,
                                  plane_center=(0.0, 0.0), plane_half=MONEY_PLANE_HALF)
        top = jnp.array([xy[0], xy[1], 2 * SAFE_HALF[2] + MONEY_HALF[2]])
        return Placement(bodies={"put_money_in_safe_root": (root_pos, root_quat),
                                 "dollar_stack": pose_in_root(*safe_bottom, top,
                                                              yaw_quat(yaw + jnp.pi / 4))})

    def success(self, variation):
        on_shelf = detected_one_of([("dollar_stack", f"success_detector{k}") for k in range(3)],
                                   variation, DETECTOR_HALF, radius=0.012)
        return all_of([on_shelf, NothingGrasped()])

    def expert(self, obs, variation):
        money = obs.pos("dollar_stack")
        # Fingers across the stack's width (its x axis): the gripper's finger
        # axis is its y axis, so turn by a quarter.
        grip = down_grasp(yaw_of(obs.quat("dollar_stack")) + jnp.pi / 2)
        insert = down_grasp(yaw_of(obs.quat("safe_body")) + jnp.pi / 2)
        shelf = jnp.asarray(SAFE_SHELVES)[variation] - SAFE_HALF[2]
        # Tip above the shelf, the money 8 mm up; on the bottom shelf, just above the table,
        # the folded arm sags ~1.5 cm under the load, so the money goes in 2 cm up (it
        # otherwise catches on the safe's floor and is pushed along the table).
        hold = MONEY_HALF[2] + GRIP_ABOVE + jnp.where(variation == 0, BOTTOM_CLEARANCE, 0.008)
        place = in_frame(obs, "safe_body", (0.0, DETECTOR_Y + 0.01, 0.0)).at[2].add(shelf + hold)
        front = in_frame(obs, "safe_body", (0.0, SAFE_HALF[1] + IN_FRONT, 0.0)).at[2].add(
            shelf + hold)
        entrance = in_frame(obs, "safe_body", (0.0, SAFE_HALF[1] + 0.03, 0.0)).at[2].add(
            shelf + hold)
        high = front.at[2].set(obs.pos("safe_body")[2] + SAFE_HALF[2] + 0.06)
        # The 0.5 m descent to the bottom shelf ends next to the elbow's limit when the safe
        # faces the robot from close by; tracked as one straight line, the chained IK loses
        # it there and the controller falls back to a joint-space move that sweeps the money
        # into the safe's roof. Two straight halves keep each move trackable.
        halfway = (front + high) / 2
        grasp = money + jnp.array([0.0, 0.0, GRIP_ABOVE])
        up = jnp.array([0.0, 0.0, 0.12])
        return key_actions([
            (grasp + up, grip, 1.0),  # above the money
            (grasp, grip, 0.0),  # down, close: attach
            (grasp + up, grip, 0.0),  # lift
            (high, insert, 0.0),  # in front of the safe, turned to face it
            (halfway, insert, 0.0),  # down in two straight moves
            (front, insert, 0.0),  # to the shelf's height
            (entrance, insert, 0.0),  # money's front end at the opening
            (place, insert, 1.0),  # slide in, release
            (front, insert, 1.0),  # withdraw
        ])


TASK = PutMoneyInSafe()
