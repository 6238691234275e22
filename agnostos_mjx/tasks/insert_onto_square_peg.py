"""insert_onto_square_peg (seen): put the square ring onto the peg of one colour."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from agnostos_mjx.sim.colors import COLORS
from agnostos_mjx.sim.conditions import Detected, all_of
from agnostos_mjx.tasks.base import Placement, Split, Task, key_actions, place_root
from agnostos_mjx.tasks.builders.blocks import peg_board, square_grasp_yaw, square_ring
from agnostos_mjx.tasks.builders.common import (
    down_grasp,
    pose_in_root,
    sensor_volume,
    spawn_on_root_plane,
)

ROOT = "insert_onto_square_peg_root"
PEG_X = (-0.125, 0.0, 0.125)
BOARD_Y = -0.075
RING_HALF, RING_WALL, RING_HALF_HEIGHT = 0.025, 0.0075, 0.005
# The four side volumes around the chosen peg's foot (centre, half extents),
# relative to `success_centre`, as in the model (0.05 m high from the table).
DETECTORS = (((0.0, 0.02, 0.025), (0.02, 0.005, 0.025)),
             ((0.0, -0.023, 0.025), (0.02, 0.005, 0.025)),
             ((-0.02, -0.005, 0.025), (0.005, 0.02, 0.025)),
             ((0.02, -0.005, 0.025), (0.005, 0.02, 0.025)))
# Tip heights above the table (RLBench's waypoints 2-4): lift, above the peg,
# release with the ring already around the peg's top (peg top at 0.14).
LIFT_Z, ABOVE_PEG_Z, RELEASE_Z = 0.22, 0.217, 0.129
# The expert's last move before closing is short: the arm's servos lag on long
# moves and the tip strays up to ~2 cm sideways, enough to flip the 20 g ring.
APPROACH = 0.05
GRASP_ABOVE = 0.006  # tip above the ring centre: the finger pads (9 mm past the tip) clear the table


class InsertOntoSquarePeg(Task):
    name = "insert_onto_square_peg"
    split = Split.SEEN
    num_variations = 20
    objects = {"ring": "square_ring", "first spoke": "pillar0", "second spoke": "pillar1",
               "third spoke": "pillar2"}
    frames = (ROOT, "success_centre") + tuple(f"success_detector{k}" for k in range(4))
    graspables = ("square_ring",)
    graspable_radius = (RING_HALF,)
    notes = (
        "X-ICM names the pegs 'spok' (sic); we say 'spoke'. The ring's wall thickness is not "
        "documented: 7.5 mm, leaving a 3.5 cm hole over the 2.5 cm peg. The expert turns the "
        "ring to the pegs' yaw before lowering it (RLBench's waypoint carries that "
        "orientation), grasps it 6 mm above its centre so the finger pads clear the table, "
        "and approaches from 5 cm above instead of RLBench's 10 cm (the servos' lag on "
        "longer moves swings the fingers into the 20 g ring).")

    def descriptions(self, variation: int) -> list[str]:
        c = COLORS[variation][0]
        return [f"put the ring on the {c} spoke", f"slide the ring onto the {c} colored spoke",
                f"place the ring onto the {c} spoke"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        board = root.add_body(name="square_base", pos=[0.0, BOARD_Y, 0.0])
        peg_board(board, "square_base", "pillar", (0.2, 0.05, 0.01), (0.0125, 0.0125, 0.06),
                  PEG_X, (0.49, 0.38, 0.29), (0.5, 0.5, 0.5))
        centre = scene.mocap("success_centre")
        for k, (pos, half) in enumerate(DETECTORS):
            sensor_volume(centre, f"success_detector{k}", pos, half)
        square_ring(scene, "square_ring", RING_HALF, RING_WALL, RING_HALF_HEIGHT,
                    (0.23, 0.75, 1.0), mass=0.02)

    def sample(self, key, variation) -> Placement:
        k_root, k_ring, k_peg, k_colors = jax.random.split(key, 4)
        root_pos, root_quat = place_root(k_root, (0.2, 0.1625), jnp.pi, offset=(0.0, 0.0375))
        chosen = jax.random.randint(k_peg, (), 0, 3)
        peg_x = jnp.asarray(PEG_X)[chosen]
        bodies = {
            ROOT: (root_pos, root_quat),
            "square_ring": spawn_on_root_plane(k_ring, (root_pos, root_quat),
                                               (RING_HALF, RING_HALF), (0.0, 0.1), (0.2, 0.1),
                                               height=RING_HALF_HEIGHT),
            "success_centre": pose_in_root(root_pos, root_quat, (peg_x, BOARD_Y, 0.0)),
        }
        # The chosen peg takes the variation's colour, the others two distinct others.
        rgb = jnp.asarray([c for _, c in COLORS], jnp.float32)
        others = jax.random.choice(k_colors, len(COLORS) - 1, (2,), replace=False)
        others = others + (others >= variation)
        slot = (jnp.arange(3) - chosen) % 3  # 0 for the chosen peg, then 1, 2
        palette = jnp.stack([rgb[variation], rgb[others[0]], rgb[others[1]]])
        colors = {f"pillar{k}": palette[slot[k]] for k in range(3)}
        return Placement(bodies=bodies, colors=colors)

    def success(self, variation):
        return all_of([Detected("square_ring", f"success_detector{k}", half, RING_HALF)
                       for k, (_, half) in enumerate(DETECTORS)])

    def expert(self, obs, variation):
        ring = obs.pos("square_ring")
        grasp = down_grasp(square_grasp_yaw(obs.quat("square_ring")), wrap=False)
        # Turn the ring square to the pegs (any of the four ways round).
        place = down_grasp(square_grasp_yaw(obs.quat(ROOT)), wrap=False)
        table = obs.pos(ROOT)[2]
        peg = obs.pos("success_centre")
        return key_actions([
            (ring + jnp.array([0.0, 0.0, APPROACH]), grasp, 1.0),  # just above the ring
            (ring + jnp.array([0.0, 0.0, GRASP_ABOVE]), grasp, 0.0),  # grasp a side pair
            (ring.at[2].set(table + LIFT_Z), grasp, 0.0),  # lift
            (peg.at[2].set(table + ABOVE_PEG_Z), place, 0.0),  # above the peg
            (peg.at[2].set(table + RELEASE_Z), place, 1.0),  # lower over it, let go
        ])


TASK = InsertOntoSquarePeg()
