"""scoop_with_spatula (unseen, Level 2): push the spatula's blade under a
small cube and lift the cube on it, holding the spatula."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, Grasped, all_of
from agnostos_mjx.sim.math3d import quat_rotate
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.common import DOWN_ACROSS, free_body, sensor_volume
from agnostos_mjx.tasks.builders.primitives import panel
from agnostos_mjx.tasks.builders.props import spatula

ROOT, SPATULA, CUBE = "scoop_with_spatula_root", "spatula", "scoop_cube"
GRIP = (0.13, 0.209, 0.033)  # the handle's middle (RLBench waypoint1), root frame
# RLBench's cube weighs 1 kg (125 g/cm^3); on the 69 g spatula that load bent
# the soft grasp weld ~16 degrees, so ours weighs 0.1 kg.
CUBE_START, CUBE_HALF, CUBE_MASS = (0.125, -0.075), 0.01, 0.1
# RLBench's `success` sensor: 0.2 x 0.2 m, from 0.123 to 0.173 m above the table.
SUCCESS_CENTER, SUCCESS_HALF = (0.125, -0.1, 0.148), (0.1, 0.1, 0.025)
PUSH = 0.15  # RLBench pushes 0.20 m; our blade is 0.13 m long and stops under the cube
LIFT = 0.125
# Pointing down, fingers across the handle (along the root's x).
GRASP = DOWN_ACROSS


class ScoopWithSpatula(Task):
    name = "scoop_with_spatula"
    split = Split.LEVEL2
    objects = {"cube": CUBE, "spatula": SPATULA}
    frames = (ROOT, "scoop_success")
    graspables = (SPATULA,)
    graspable_radius = (0.01,)
    notes = ("The spatula is gravity compensated and does not collide with the table: it hovers "
             "in its resting pose and its slightly pitched blade, whose front edge runs 0.5 mm "
             "below the table top, is a ramp that slides under the cube (CoppeliaSim's contact "
             "margins let RLBench's flat blade do that). The blade is 13 cm long and the expert "
             "pushes 15 cm (RLBench 20 cm) so the cube ends on the blade. The cube weighs 0.1 kg, "
             "not RLBench's 1 kg (a 2 cm cube; the load bent the grasp weld).")

    def descriptions(self, variation: int) -> list[str]:
        return ["scoop up the cube and lift it with the spatula",
                "scoop up the block and lift it with the spatula",
                "use the spatula to scoop the cube and lift it",
                "use the spatula to scoop the block and lift it",
                "pick up the cube using the spatula", "pick up the block using the spatula"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        sensor_volume(root, "scoop_success", SUCCESS_CENTER, SUCCESS_HALF)
        spatula(scene, SPATULA)
        cube = free_body(scene, CUBE)
        panel(cube, (CUBE_HALF,) * 3, (0, 0, 0), (0.85, 0.85, 1.0)).mass = CUBE_MASS

    def sample(self, key, variation) -> Placement:
        # RLBench only turns the task root (any yaw); its footprint is the
        # spatula and the cube: x[0.07, 0.19], y[-0.085, 0.276].
        pos, quat = place_root(key, (0.06, 0.181), jnp.pi, offset=(0.13, 0.096))
        at = lambda x, y, z: pos + quat_rotate(quat, jnp.array([x, y, z]))  # noqa: E731
        return Placement(bodies={ROOT: (pos, quat), SPATULA: (at(*GRIP), quat),
                                 CUBE: (at(*CUBE_START, CUBE_HALF), quat)})

    def success(self, variation):
        lifted = Detected(CUBE, "scoop_success", SUCCESS_HALF, radius=CUBE_HALF)
        return all_of([lifted, Grasped(0)])

    def expert(self, obs, variation):
        quat = frame_quat(obs, SPATULA, GRASP)
        grip = obs.pos(SPATULA)
        pushed = in_frame(obs, SPATULA, (0.0, -PUSH, 0.0))
        return key_actions([
            (grip + jnp.array([0.0, 0.0, 0.075]), quat, 1.0),  # above the handle
            (grip, quat, 0.0),  # around the handle, close: attach
            (pushed, quat, 0.0),  # push the blade under the cube
            (pushed + jnp.array([0.0, 0.0, LIFT]), quat, 0.0),  # lift
        ])


TASK = ScoopWithSpatula()
