"""meat_off_grill (seen): take the chicken or the steak off the grill and set it down beside it."""

from __future__ import annotations

import jax.numpy as jnp
import mujoco

from agnostos_mjx.sim.conditions import Detected, NothingGrasped, Select, all_of
from agnostos_mjx.tasks.base import (
    Placement,
    Split,
    Task,
    frame_quat,
    in_frame,
    key_actions,
    place_root,
)
from agnostos_mjx.tasks.builders.appliances import (
    GRATE_Z,
    GRILL_BOUNDARY_CENTER,
    GRILL_BOUNDARY_HALF,
    GRILL_X,
    grill,
)
from agnostos_mjx.tasks.builders.common import DOWN, free_body, grasp_site, pose_in_root
from agnostos_mjx.tasks.builders.primitives import panel, rod

MEATS = ("chicken", "steak")
GRILL_CX = (GRILL_X[0] + GRILL_X[1]) / 2
MEAT_Y = (-0.1, 0.1)  # on the grate, root frame
# The "beside the grill" sensor: a box on the table in front of the grill.
SUCCESS_POS, SUCCESS_HALF = (-0.05, 0.0, 0.05), (0.1, 0.2, 0.05)
HOVER, LIFT = 0.1, 0.15


def _chicken(body: mujoco.MjsBody) -> None:
    """A drumstick along x: a meaty capsule and a bone end (visual)."""
    rod(body, (-0.03, 0, 0), (0.03, 0, 0), 0.022, (0.85, 0.6, 0.35), collide=True,
        name="chicken_meat").mass = 0.1
    rod(body, (0.03, 0, 0), (0.075, 0, 0), 0.007, (0.95, 0.93, 0.85))


def _steak(body: mujoco.MjsBody) -> None:
    panel(body, (0.05, 0.035, 0.01), (0, 0, 0), (0.55, 0.12, 0.1), name="steak_meat").mass = 0.1


class MeatOffGrill(Task):
    name = "meat_off_grill"
    split = Split.SEEN
    num_variations = 2
    # X-ICM's name map lists only the chicken and the grill, for both variations.
    objects = {"chicken": "chicken", "grill": "grill_center"}
    frames = ("steak", "meat_off_grill_root", "meat_off_grill_success")
    graspables = MEATS
    graspable_radius = (0.02, 0.02)
    notes = ("Scene layout undocumented in the spec: designed here. The grill of open_grill "
             "without its lid; chicken (drumstick) and steak lie on the grate, 0.2 m apart; the "
             "'success' sensor is a 0.2 x 0.4 x 0.1 m box on the table in front of the grill. "
             "The root is placed through open_grill's grill_root proxy with any yaw (RLBench's "
             "default). Expert: top-down grasp, lift, carry to the front, release 3 cm above "
             "the table (RLBench's waypoints are undocumented). As in X-ICM's name map, the "
             "text lists the chicken and the grill, also in the steak variation.")

    def descriptions(self, variation: int) -> list[str]:
        m = MEATS[variation]
        return [f"take the {m} off the grill", f"pick up the {m} and place it next to the grill",
                f"remove the {m} from the grill and set it down to the side"]

    def build(self, scene) -> None:
        root = scene.mocap("meat_off_grill_root")
        grill(scene, root)
        grasp_site(root, "meat_off_grill_success", list(SUCCESS_POS))
        for name, y, shape in zip(MEATS, MEAT_Y, (_chicken, _steak)):
            shape(free_body(scene, name, pos=(0.25 + GRILL_CX, y, 1.2)))

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, GRILL_BOUNDARY_HALF, jnp.pi, offset=GRILL_BOUNDARY_CENTER)
        bodies = {"meat_off_grill_root": (pos, quat)}
        for name, y, half_h in zip(MEATS, MEAT_Y, (0.022, 0.01)):
            local = jnp.array([GRILL_CX, y, GRATE_Z + half_h + 0.001])
            bodies[name] = pose_in_root(pos, quat, local)
        return Placement(bodies=bodies)

    def success(self, variation):
        detected = tuple(Detected(m, "meat_off_grill_success", SUCCESS_HALF) for m in MEATS)
        return all_of([Select(detected, variation), NothingGrasped()])

    def expert(self, obs, variation):
        meat = jnp.stack([obs.pos(m) for m in MEATS])[variation]
        grip = jnp.stack([frame_quat(obs, m, DOWN) for m in MEATS])[variation]
        # Set down in front of the grill, level with where it lay, 3 cm above the table.
        drop = in_frame(obs, "meat_off_grill_root",
                        jnp.stack([SUCCESS_POS[0], jnp.asarray(MEAT_Y)[variation], 0.045]))
        up = jnp.array([0.0, 0.0, 1.0])
        return key_actions([
            (meat + HOVER * up, grip, 1.0),  # above the meat
            (meat + 0.005 * up, grip, 0.0),  # around it, close: attach
            (meat + LIFT * up, grip, 0.0),  # lift off the grate
            (drop.at[2].set(meat[2] + LIFT), grip, 0.0),  # over the table beside the grill
            (drop, grip, 1.0),  # lower and release
        ])


TASK = MeatOffGrill()
