"""close_jar (seen): put the lid from the table on the jar of the named colour."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from agnostos_mjx.sim.colors import COLORS
from agnostos_mjx.sim.conditions import NothingGrasped, all_of
from agnostos_mjx.tasks.base import Placement, Split, Task, key_actions, place_root
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_body,
    pose_in_root,
    sensor_volume,
    spawn_many_on_root_plane,
    square_yaw,
    yaw_of,
)
from agnostos_mjx.tasks.builders.containers import (
    JAR_HALF_HEIGHT,
    LID_HALF_HEIGHT,
    detected_one_of,
    jar,
    jar_lid,
    other_color,
)

TABLE_TO_JAR = 0.051  # jar centre above the table (RLBench layout)
LID_AT = (0.043, 0.277, LID_HALF_HEIGHT)  # on the table, root frame
SPAWN_CENTER, SPAWN_HALF = (0.0, -0.089), (0.1665, 0.1865)
JAR_FOOTPRINT = (0.046, 0.046)
# RLBench's success sensor: a 0.05 x 0.05 x 0.02 box from 0.05 m above the jar centre.
MOUTH = (0.0, 0.0, 0.06)
MOUTH_HALF = (0.025, 0.025, 0.01)
GRIP_ABOVE_LID = 0.005  # tip above the lid centre when grasping (pads clear the table)
ABOVE = 0.167  # approach and lift height above the lid / jar


class CloseJar(Task):
    name = "close_jar"
    split = Split.SEEN
    num_variations = 20
    objects = {"lid": "jar_lid0", "jar": "jar0"}
    frames = ("jar1", "jar0_mouth", "jar1_mouth", "close_jar_root")
    graspables = ("jar_lid0",)
    graspable_radius = (0.012,)
    notes = ("Jars are static primitive stand-ins (body + neck, 0.11 m tall). The success "
             "sensor is a site at each jar's mouth, the variation picks which one counts "
             "(RLBench moves one sensor to the target jar). The lid is grasped 5 mm above "
             "its centre (our tip frame's pads reach 9 mm past the tip) and the wrist turns "
             "the grasp to the lid's nearest square face. The screwing is kinematic, as in "
             "RLBench: the attached lid turns 90 degrees with the hand.")

    def descriptions(self, variation: int) -> list[str]:
        c = COLORS[variation][0]
        return [f"close the {c} jar", f"screw on the {c} jar lid",
                f"grasping the lid, lift it from the table and use it to seal the {c} jar",
                f"pick up the lid from the table and put it on the {c} jar"]

    def build(self, scene) -> None:
        scene.mocap("close_jar_root")
        for k in range(2):
            body = scene.mocap(f"jar{k}")
            jar(body, f"jar{k}")
            sensor_volume(body, f"jar{k}_mouth", MOUTH, MOUTH_HALF)
        jar_lid(free_body(scene, "jar_lid0", pos=(0, 0, 1.0)), "jar_lid0")

    def sample(self, key, variation) -> Placement:
        k_root, k_jars, k_color = jax.random.split(key, 3)
        # Footprint of the whole scene (jars' plane and the lid) in the root frame.
        root = place_root(k_root, (0.166, 0.295), 0.6 * jnp.pi, offset=(0.0, 0.02))
        jars = spawn_many_on_root_plane(k_jars, root, [JAR_FOOTPRINT] * 2, SPAWN_CENTER,
                                        SPAWN_HALF, heights=TABLE_TO_JAR)
        rgb = jnp.asarray([c for _, c in COLORS], jnp.float32)
        target = variation % 2
        other = other_color(k_color, variation, len(COLORS))
        colors = jnp.where(target == 0, jnp.stack([variation, other]),
                           jnp.stack([other, variation]))
        return Placement(
            bodies={"close_jar_root": root, "jar0": jars[0], "jar1": jars[1],
                    "jar_lid0": pose_in_root(*root, LID_AT)},
            colors={f"jar{k}_{part}": rgb[colors[k]] for k in range(2) for part in ("body", "neck")},
        )

    def success(self, variation):
        on_target = detected_one_of([("jar_lid0", "jar0_mouth"), ("jar_lid0", "jar1_mouth")],
                                    variation % 2, MOUTH_HALF, radius=0.01)
        return all_of([on_target, NothingGrasped()])

    def expert(self, obs, variation):
        lid = obs.pos("jar_lid0")
        target = jnp.where(variation % 2 == 0, obs.pos("jar0"), obs.pos("jar1"))
        # Fingers square to the lid's contact box.
        lid_yaw = square_yaw(yaw_of(obs.quat("jar_lid0")))
        grip = down_grasp(lid_yaw, wrap=False)
        screwed = down_grasp(lid_yaw + jnp.pi / 2, wrap=False)  # a quarter turn on
        up = jnp.array([0.0, 0.0, ABOVE])
        grasp = lid + jnp.array([0.0, 0.0, GRIP_ABOVE_LID])
        # Lid bottom 2 mm above the neck, then it drops onto the jar when released.
        seal = target + jnp.array([0.0, 0.0, JAR_HALF_HEIGHT + LID_HALF_HEIGHT + 0.002
                                   + GRIP_ABOVE_LID])
        over_jar = target + jnp.array([0.0, 0.0, 0.126])
        return key_actions([
            (lid + up, grip, 1.0),  # above the lid
            (grasp, grip, 0.0),  # down, close: attach
            (lid + up, grip, 0.0),  # lift
            (over_jar, grip, 0.0),  # above the target jar
            (seal, grip, 0.0),  # lower onto the neck
            (seal, screwed, 1.0),  # screw a quarter turn, release
        ])


TASK = CloseJar()
