"""place_wine_at_rack_location (seen): lay the wine bottle in the middle, left or right slot of a rack."""

from __future__ import annotations

import jax.numpy as jnp

from agnostos_mjx.sim.conditions import Detected, NothingGrasped, Select, all_of
from agnostos_mjx.sim.math3d import euler_xyz_quat
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.common import DOWN_ACROSS, grasp_site, pose_in_root, sensor_volume
from agnostos_mjx.tasks.builders.furniture import wine_bottle, wine_rack

LOCATIONS = ("middle", "left", "right")
SLOT_X = (0.051, 0.170, -0.065)  # RLBench's success_<location> sensors, root frame
SLOT_Z = 0.113  # bottle axis height in a slot
ROOT = "place_wine_root"
BOTTLE_HALF_HEIGHT = 0.123
BOTTLE_LOCAL = (0.099, -0.284, BOTTLE_HALF_HEIGHT)
NECK = 0.222 - BOTTLE_HALF_HEIGHT  # grasp height on the neck above the bottle centre
# RLBench's cylinder sensors (radius 0.02, 0.20 m along -y from y = 0.375) as boxes.
VOLUME_HALF = (0.02, 0.10, 0.02)
# Horizontal, pointing along the root's +x, fingers closing along y (wp0/wp1);
# then pointing down with the bottle lying along +y, base first (wp3/wp4).
SIDE = euler_xyz_quat(0.0, jnp.pi / 2, 0.0)
LAID = DOWN_ACROSS


class PlaceWineAtRackLocation(Task):
    name = "place_wine_at_rack_location"
    split = Split.SEEN
    num_variations = 3
    objects = {"wine": "wine_bottle", "rack": "rack_top"}
    frames = (ROOT,) + tuple(f"success_{loc}" for loc in LOCATIONS)
    graspables = ("wine_bottle",)
    grasp_points = ("wine_bottle_grasp",)
    graspable_radius = (0.012,)
    notes = ("The rack is built from boxes (base slab, rails with a gap under each slot, low "
             "dividers) in RLBench's extent; its mesh cradles are not reproduced. The slot "
             "sensors are boxes around RLBench's cylinder volumes. The expert lifts higher and "
             "turns the bottle in the air before approaching the slot (RLBench plans around "
             "obstacles; our controller moves in straight lines). The root's footprint used "
             "for sampling is smaller than the scene (which does not fit our inferred "
             "workspace at 45 degrees); unreachable placements are resampled.")

    def descriptions(self, variation: int) -> list[str]:
        loc = LOCATIONS[variation]
        return [f"stack the wine bottle to the {loc} of the rack",
                f"slide the bottle onto the {loc} part of the rack", f"put the wine on the {loc}",
                f"leave the wine on the {loc} section of the shelf",
                f"grasp the bottle and put it away on the {loc}"]

    def build(self, scene) -> None:
        root = scene.mocap(ROOT)
        wine_rack(scene, root, "rack", SLOT_X)
        for loc, x in zip(LOCATIONS, SLOT_X):
            sensor_volume(root, f"success_{loc}", (x, 0.275, SLOT_Z), VOLUME_HALF)
        grasp_site(wine_bottle(scene), "wine_bottle_grasp", (0.0, 0.0, NECK))

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, (0.12, 0.22), jnp.pi / 4, offset=(0.054, 0.04))
        return Placement(bodies={ROOT: (pos, quat),
                                 "wine_bottle": pose_in_root(pos, quat, BOTTLE_LOCAL)})

    def success(self, variation):
        slots = tuple(Detected("wine_bottle", f"success_{loc}", VOLUME_HALF, radius=0.02)
                      for loc in LOCATIONS)
        return all_of([Select(slots, variation), NothingGrasped()])

    def expert(self, obs, variation):
        neck = obs.pos("wine_bottle_grasp")
        side, laid = frame_quat(obs, ROOT, SIDE), frame_quat(obs, ROOT, LAID)
        slot_x = jnp.asarray(SLOT_X)[variation]
        up = jnp.array([0.0, 0.0, 1.0])
        lifted = neck + 0.10 * up
        return key_actions([
            (in_frame(obs, "wine_bottle", (-0.15, 0.0, NECK + 0.08)), side, 1.0),  # turn clear
            (in_frame(obs, "wine_bottle", (-0.05, 0.0, NECK)), side, 1.0),  # beside the neck (wp0)
            (neck, side, 0.0),  # grasp (wp1)
            (lifted, side, 0.0),  # lift (wp2, higher than RLBench's 2.5 cm)
            (lifted, laid, 0.0),  # lay the bottle along +y in the air
            (in_frame(obs, ROOT, (slot_x, -0.050, 0.174)), laid, 0.0),  # in front of the slot (wp3)
            (in_frame(obs, ROOT, (slot_x, 0.150, 0.174)), laid, 1.0),  # slide in, release (wp4)
            (in_frame(obs, ROOT, (slot_x, 0.150, 0.30)), laid, 1.0),  # retreat upwards
        ])


TASK = PlaceWineAtRackLocation()
