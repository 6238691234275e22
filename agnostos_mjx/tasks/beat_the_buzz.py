"""beat_the_buzz (unseen, Level 2): slide the ring wand along the wire
without touching it, then let go at the far end."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from agnostos_mjx.sim.conditions import AnyOf, Detected, NothingGrasped, all_of
from agnostos_mjx.sim.math3d import axis_angle_quat, quat_mul, quat_rotate
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.common import DOWN, grasp_site, pose_in_root, sensor_volume
from agnostos_mjx.tasks.builders.props import buzz_wire, ring_wand

ROOT, WAND = "beat_the_buzz_root", "beat_the_buzz_wand"
WIRE_Z = 0.295
RING_RADIUS, TUBE_RADIUS = 0.0385, 0.0055
WAND_START = (0.0, 0.111, 0.296)  # ring centre in the root frame (RLBench's wand_visual)
HANDLE_END = (-0.10, 0.0, -0.236)  # wand frame; the handle starts at the ring's bottom
# Grasp point on the handle and the approach direction in the ring's plane,
# from behind and above.  RLBench grasps 8.4 cm below the ring, approaching
# perpendicular to the handle (27 degrees below horizontal); that pose sits at
# the wrist's limits when the stand faces the robot.  We grasp 2.7 cm lower
# and tilt the approach 40 degrees further down along the handle, which keeps
# the palm clear of the ring and the wrist inside its range.
_handle = np.subtract(HANDLE_END, (0.0, 0.0, -RING_RADIUS))
_handle /= np.linalg.norm(_handle)
GRIP = tuple(np.array([0.0, 0.0, -RING_RADIUS]) + 0.11 * _handle)  # ~(-0.050, 0, -0.137)
_tilt = np.deg2rad(40.0)
APPROACH = tuple(np.cos(_tilt) * np.array([-_handle[2], 0.0, _handle[0]]) + np.sin(_tilt) * _handle)
# The down-pointing gripper (fingers along y) pitched about y onto APPROACH.
GRASP = quat_mul(axis_angle_quat(np.array([0.0, 1.0, 0.0]), np.arctan2(-APPROACH[0], -APPROACH[2])),
                 DOWN)
# The fingers do not collide with the wand (squeezing the round handle
# squirted the light, free wand away before the grasp attached it); they
# close to the handle's width instead of through it.
CLOSED = 0.14
GRASP_FLIPPED = quat_mul(GRASP, axis_angle_quat(np.array([0.0, 0.0, 1.0]), np.pi))
SLIDE = 0.20  # RLBench's waypoint3 slides the wand 0.2 m along the wire (-y)
# RLBench follows that slide on a linear path.  Our controller falls back to
# a joint-space path where straight-line IK fails (near the wrist's limits
# when the stand faces the robot), which bowed onto the wire; via-points every
# 5 cm keep any fallback path within a few millimetres of the line.
SLIDE_STEPS = 4
# Sensor volumes (root frame).  `middle_sensor` is a cylinder of radius
# 0.01 m around the wire from y = 0.09 to -0.06; the ring touches it once its
# centre is off the wire axis by RING - TUBE - 0.01 = 0.023 m.  We test that
# with an octagonal prism (two squares, one turned 45 degrees) of inradius
# 0.023 m; `right_sensor` (a disc of radius 0.1 m, 0.02 m thick at the far
# end) becomes a 0.2 x 0.2 m square slab.
MIDDLE_CENTER, MIDDLE_HALF_LENGTH = (0.0, 0.015, WIRE_Z), 0.075
CORE = 0.023
RIGHT_CENTER, RIGHT_HALF = (0.0, -0.091, WIRE_Z), (0.1, 0.01, 0.1)
ROLL_45 = tuple(float(x) for x in axis_angle_quat(np.array([0.0, 1.0, 0.0]), np.pi / 4))


class BeatTheBuzz(Task):
    name = "beat_the_buzz"
    split = Split.LEVEL2
    # X-ICM's names: the stand is "cube" (RLBench's `Cuboid`), the ring "pole",
    # the handle "pole head".
    objects = {"cube": "beat_the_buzz_stand", "pole": WAND, "pole head": "beat_the_buzz_handle"}
    frames = (ROOT, "beat_the_buzz_middle", "beat_the_buzz_middle45", "beat_the_buzz_right")
    graspables = (WAND,)
    grasp_points = ("beat_the_buzz_grip",)
    graspable_radius = (0.01,)
    notes = ("The expert grasps the handle 2.7 cm lower than RLBench and approaches 40 degrees "
             "steeper (RLBench's pose is at the wrist's limits when the stand faces the robot), "
             "and slides in four 5 cm steps (RLBench: one linear path; our controller has no "
             "linear-path constraint when straight-line IK fails). The fingers do not collide "
             "with the wand and close to the handle's width; the kinematic grasp holds it. "
             "The wand is gravity compensated: RLBench saves it hovering with the ring centred "
             "on the wire at the start end, and grasps it kinematically from there. The "
             "cylindrical middle_sensor is an octagonal prism of the same inradius (0.023 m "
             "offset of the ring centre), the disc right_sensor a square slab.")

    def descriptions(self, variation: int) -> list[str]:
        return [
            "beat the buzz",
            "slide the ring along the pole without allowing them to touch",
            "slide the ring along the metal pole, avoiding contact between them",
            "slide the ring from one end of the pole to the other without allowing them to touch",
            "slide the ring from one end of the pole to the other, avoiding contact between them",
            "move the ring from one end of the pole to the other, maintaining a gap between them",
            "move the ring from end of the pole to the other whilst maintaining separation "
            "between them",
        ]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        buzz_wire(root, "beat_the_buzz", wire_z=WIRE_Z)
        grasp_site(root, "beat_the_buzz_stand", (0, 0, 0.149))
        sensor_volume(root, "beat_the_buzz_middle", MIDDLE_CENTER, (CORE, MIDDLE_HALF_LENGTH, CORE))
        sensor_volume(root, "beat_the_buzz_middle45", MIDDLE_CENTER,
                      (CORE, MIDDLE_HALF_LENGTH, CORE), quat=ROLL_45)
        sensor_volume(root, "beat_the_buzz_right", RIGHT_CENTER, RIGHT_HALF)
        wand = ring_wand(scene, WAND, ring_radius=RING_RADIUS, tube_radius=TUBE_RADIUS,
                         handle_end=HANDLE_END)
        for finger in ("left_finger", "right_finger"):
            scene.exclude(finger, WAND)
        grasp_site(wand, "beat_the_buzz_grip", GRIP)
        grasp_site(wand, "beat_the_buzz_handle", np.add(HANDLE_END, (0, 0, -RING_RADIUS)) / 2)

    def sample(self, key, variation) -> Placement:
        # Footprint x[-0.10, 0.05], y[-0.18, 0.18]; RLBench samples any yaw.
        pos, quat = place_root(key, (0.077, 0.176), jnp.pi, offset=(-0.024, 0.0))
        return Placement(bodies={ROOT: (pos, quat), WAND: pose_in_root(pos, quat, WAND_START)})

    def success(self, variation):
        far_end = Detected(WAND, "beat_the_buzz_right", RIGHT_HALF, radius=TUBE_RADIUS)
        return all_of([far_end, NothingGrasped()])

    def failure(self, variation):
        """The ring's tube enters the thin cylinder around the wire's middle."""
        span = (1.0, MIDDLE_HALF_LENGTH, 1.0)
        along = Detected(WAND, "beat_the_buzz_middle", span, radius=TUBE_RADIUS)
        core = (CORE, 1.0, CORE)
        off_axis = AnyOf((Detected(WAND, "beat_the_buzz_middle", core, negated=True),
                          Detected(WAND, "beat_the_buzz_middle45", core, negated=True)))
        return all_of([along, off_axis])

    def expert(self, obs, variation):
        grip = in_frame(obs, "beat_the_buzz_grip")
        # Of the two finger orientations, take the one whose fingers point
        # along world +y, as at home: it keeps the wrist clear of its limits.
        side = quat_rotate(obs.quat(ROOT), jnp.array([0.0, 1.0, 0.0]))[1]
        quat = frame_quat(obs, ROOT, jnp.where(side >= 0, GRASP, GRASP_FLIPPED))
        approach = quat_rotate(obs.quat(ROOT), jnp.asarray(APPROACH, jnp.float32))
        along = quat_rotate(obs.quat(ROOT), jnp.array([0.0, -SLIDE / SLIDE_STEPS, 0.0]))
        up = jnp.array([0.0, 0.0, 0.15])
        slide = [(grip + (i + 1) * along, quat, CLOSED) for i in range(SLIDE_STEPS)]
        slide[-1] = (slide[-1][0], quat, 1.0)  # at the far end, release
        return key_actions([
            (grip - 0.2 * approach + up, quat, 1.0),  # via-point: clear of the ring
            (grip - 0.09 * approach, quat, 1.0),  # behind the handle
            (grip, quat, CLOSED),  # on the handle, close: attach the wand
            *slide,
        ])


TASK = BeatTheBuzz()
