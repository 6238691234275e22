"""stack_cups (seen): stack the two other cups into the cup of the named colour."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from agnostos_mjx.sim.colors import COLORS
from agnostos_mjx.sim.conditions import Detected, NothingGrasped, all_of
from agnostos_mjx.tasks.base import Placement, Split, Task, key_actions, place_root
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    free_body,
    grasp_site,
    sensor_volume,
    spawn_many_on_root_plane,
    yaw_of,
)
from agnostos_mjx.tasks.builders.containers import (
    CUP_HALF_HEIGHT,
    cup,
    cup_geoms,
    cup_radius,
    other_color,
)

BOUNDARY_CENTER, BOUNDARY_HALF = (-0.008, -0.001), (0.2, 0.3)
CUP_FOOTPRINT = (0.047, 0.047)
# RLBench grasps the cup wall on the root's +y side, 0.05 m above the cup centre.
GRASP_Z = 0.05
GRASP = (0.0, cup_radius(CUP_HALF_HEIGHT + GRASP_Z) - 0.0015, GRASP_Z)
# RLBench's sensor: a cylinder of radius 0.02, 0.1 m tall from 0.01 m above
# cup2's bottom (here its bounding box), probed at the other cups' bottoms.
SENSOR = (0.0, 0.0, -CUP_HALF_HEIGHT + 0.06)
SENSOR_HALF = (0.02, 0.02, 0.05)
# RLBench keeps cups 0.05 m apart (centres) and relies on collision-aware
# planning; our fingers straddling a wall reach 0.10 m from the cup's axis, so
# cups stay far enough apart that the outer finger never lands on a neighbour.
MIN_DISTANCE = 0.15
RELEASE_ABOVE = 0.097  # carried cup's bottom above the base cup's bottom at release


class StackCups(Task):
    name = "stack_cups"
    split = Split.SEEN
    num_variations = 20
    objects = {"first cup": "cup1", "second cup": "cup2", "third cup": "cup3"}
    frames = ("cup1_grasp", "cup2_grasp", "cup3_grasp", "cup1_bottom", "cup3_bottom",
              "stack_cups_success")
    graspables = ("cup1", "cup3")
    grasp_points = ("cup1_grasp", "cup3_grasp")
    graspable_radius = (0.005, 0.005)
    notes = ("Cups are 12-sided tapered shells of box panels (RLBench: a compound of 19 "
             "primitives), so same-yaw cups nest. RLBench's cylindrical sensor inside cup2 "
             "is approximated by the box inscribing it, and a cup counts when its bottom "
             "centre is inside (CoppeliaSim tests the cup's shape). cup2 itself is "
             "not graspable, as in RLBench. Cups are spawned at least 0.15 m apart "
             "(RLBench 0.05 m, with a collision-aware planner): closer, the outer finger "
             "would land on a neighbouring cup.")

    def descriptions(self, variation: int) -> list[str]:
        c = COLORS[variation][0]
        return [f"stack the other cups on top of the {c} cup",
                "place two of the cups onto the odd cup out",
                f"put the remaining two cups on top of the {c} cup",
                f"pick up and set the cups down into the {c} cup",
                f"create a stack of cups with the {c} cup as its base",
                f"keeping the {c} cup on the table, stack the other two onto it"]

    def build(self, scene) -> None:
        scene.mocap("stack_cups_root")
        for k in (1, 2, 3):
            body = free_body(scene, f"cup{k}", pos=(0, 0, 1.0 + 0.2 * k))
            cup(body, f"cup{k}")
            grasp_site(body, f"cup{k}_grasp", GRASP)
            grasp_site(body, f"cup{k}_bottom", (0, 0, -CUP_HALF_HEIGHT))
        sensor_volume(scene.spec.body("cup2"), "stack_cups_success", SENSOR, SENSOR_HALF)

    def sample(self, key, variation) -> Placement:
        k_root, k_cups, k1, k3 = jax.random.split(key, 4)
        root = place_root(k_root, BOUNDARY_HALF, jnp.pi, offset=BOUNDARY_CENTER)
        # RLBench samples cup2 first, then cup1 and cup3, without rotation.
        poses = spawn_many_on_root_plane(k_cups, root, [CUP_FOOTPRINT] * 3, BOUNDARY_CENTER,
                                         BOUNDARY_HALF, yaw_range=0.0, min_distance=MIN_DISTANCE,
                                         heights=CUP_HALF_HEIGHT)
        rgb = jnp.asarray([c for _, c in COLORS], jnp.float32)
        index = {2: variation, 1: other_color(k1, variation, len(COLORS)),
                 3: other_color(k3, variation, len(COLORS))}
        return Placement(
            bodies={"stack_cups_root": root, "cup2": poses[0], "cup1": poses[1], "cup3": poses[2]},
            colors={g: rgb[index[k]] for k in (1, 2, 3) for g in cup_geoms(f"cup{k}")},
        )

    def success(self, variation):
        inside = [Detected(f"cup{k}_bottom", "stack_cups_success", SENSOR_HALF, radius=0.005)
                  for k in (1, 3)]
        return all_of([*inside, NothingGrasped()])

    def expert(self, obs, variation):
        steps = []
        base = obs.pos("cup2_grasp")
        for k in (1, 3):
            grasp = obs.pos(f"cup{k}_grasp")
            quat = down_grasp(yaw_of(obs.quat(f"cup{k}")))  # fingers across the +y wall
            release = base + jnp.array([0.0, 0.0, RELEASE_ABOVE])
            steps += [
                (grasp + jnp.array([0.0, 0.0, 0.068]), quat, 1.0),  # above the rim
                (grasp, quat, 0.0),  # fingers around the wall, close: attach
                (grasp + jnp.array([0.0, 0.0, 0.174]), quat, 0.0),  # lift
                (release + jnp.array([0.0, 0.0, 0.1]), quat, 0.0),  # above the base cup
                (release, quat, 1.0),  # lower into it, release
            ]
        return key_actions(steps)


TASK = StackCups()
