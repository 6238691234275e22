"""toilet_seat_down (unseen, Level 1): push the raised toilet seat over so it falls shut."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import JointMoved
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.appliances import toilet
from agnostos_mjx.tasks.builders.common import DOWN_ACROSS

# Gripper pointing down, fingers (closed into a fist) along the hinge axis.
FIST = DOWN_ACROSS
# Root-frame key points: above and behind the raised seat, down behind its
# top edge (RLBench's wp0), forward past upright (wp1), then on along the
# seat's arc until it lies on the bowl (RLBench lets it fall after wp2/wp3).
PATH = (
    ((-0.006, -0.105, 0.56), 1.0),
    ((-0.006, -0.105, 0.475), 0.0),
    ((-0.006, 0.0, 0.48), 0.0),
    ((-0.006, 0.118, 0.424), 0.0),
    ((-0.006, 0.203, 0.283), 1.0),
)
# Model bounding box: x[-0.118, 0.107], y[-0.176, 0.201].
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.1125, 0.1885), (-0.0055, 0.0125)


class ToiletSeatDown(Task):
    name = "toilet_seat_down"
    split = Split.LEVEL1
    # X-ICM's names are raw sim names ("toilet seat up_toilet", "toilet seat
    # up_seat", "toilet" for the cistern); we use clean ones.
    objects = {"toilet bowl": "toilet_bowl", "toilet seat": "toilet_seat_center",
               "toilet": "toilet_cistern"}
    frames = ("toilet_root",)
    joints = ("toilet_seat_joint",)
    notes = ("Primitive toilet (boxes). Object names cleaned from X-ICM's raw sim names "
             "'toilet seat up_toilet' -> 'toilet bowl', 'toilet seat up_seat' -> 'toilet seat'. "
             "The seat has no contact with the toilet and rests on its joint limits (0 = down), "
             "so the 1.7 rad success threshold means lying flat. The expert pushes the seat "
             "along its arc down to the bowl instead of letting it fall after a 5 cm push; "
             "the duplicated description 'leave the toilet seat down' is kept verbatim.")

    def descriptions(self, variation: int) -> list[str]:
        return ["toilet seat down", "put the toilet seat down",
                "grasping the top of the lid, close the toilet seat", "put the toilet lid down",
                "leave the toilet seat down", "close the lid on the toilet",
                "leave the toilet seat down", "lower the toilet seat",
                "grip the edge of the toilet lid and lower it flat on the toilet seat"]

    def build(self, scene) -> None:
        toilet(scene, scene.mocap("toilet_root"))

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, FOOTPRINT_HALF, jnp.pi / 4, offset=FOOTPRINT_CENTER)
        return Placement(bodies={"toilet_root": (pos, quat)})

    def success(self, variation):
        return JointMoved(self.joints, 1.7)

    def expert(self, obs, variation):
        quat = frame_quat(obs, "toilet_root", FIST)
        return key_actions([(in_frame(obs, "toilet_root", p), quat, g) for p, g in PATH])


TASK = ToiletSeatDown()
