"""The table lamp with a floor push-button switch: the shared base of lamp_on and lamp_off."""

from __future__ import annotations

import jax.numpy as jnp
import mujoco

from agnostos_mjx.sim.conditions import JointMoved
from agnostos_mjx.sim.visual_state import StateColor
from agnostos_mjx.tasks.base import Placement, Split, Task, in_frame, key_actions, place_root
from agnostos_mjx.tasks.builders import disc, panel, push_button, rod
from agnostos_mjx.tasks.builders.common import DOWN

# Model bounding box of the lamp scene in the root frame: x[-0.138, 0.167],
# y[-0.183, 0.311].
FOOTPRINT_HALF, FOOTPRINT_CENTER = (0.153, 0.247), (0.015, 0.064)


def _build_lamp(scene, bulb_rgb) -> None:
    root = scene.mocap("lamp_root")
    base = root.add_body(name="lamp_base", pos=[0.058, -0.073, 0.0])
    disc(base, 0.047, 0.01, (0, 0, 0.01), (0.85, 0.85, 1.0))
    rod(base, (0, 0, 0.02), (0, 0, 0.273), 0.012, (0.85, 0.85, 1.0))
    panel(base, (0.03, 0.03, 0.137), (0, 0, 0.137), collide=True).rgba = [0, 0, 0, 0]
    disc(base, 0.025, 0.029, (0, 0, 0.302), (0.1, 0.1, 0.1), name="lamp_screw")
    base.add_geom(name="bulb", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.034, 0, 0], pos=[0, 0, 0.36],
                  rgba=[*bulb_rgb, 1.0], contype=0, conaffinity=0, group=1)
    disc(base, 0.109, 0.004, (0, 0, 0.46), (0.08, 0.58, 0.50), name="lampshade")
    rod(base, (0.1, 0, 0.26), (0.1, 0, 0.46), 0.004, (0.08, 0.58, 0.50))
    rod(base, (-0.1, 0, 0.26), (-0.1, 0, 0.46), 0.004, (0.08, 0.58, 0.50))
    rod(root, (0.02, -0.03, 0.004), (-0.1, 0.1, 0.004), 0.004, (0, 0, 0))  # cable
    rod(root, (-0.1, 0.1, 0.004), (0.054, 0.14, 0.004), 0.004, (0, 0, 0))
    switch = root.add_body(name="push_button_target", pos=[0.054, 0.156, 0.0])
    push_button(scene, switch, "target_button", base_half=(0.0175, 0.0175, 0.01),
                base_rgba=(0.0, 0.0, 0.0), plate_radius=0.0165, plate_top=0.025,
                wrap_height=0.006, rest=0.0, plate_rgba=(0.0, 1.0, 0.0))


class LampTask(Task):
    """A lamp with a floor switch: press the switch more than 3 mm
    (RLBench's JointCondition).  Subclasses set the name, language, the
    bulb's starting colour and the colour it takes once the switch is pressed
    (None: it never changes)."""

    split = Split.LEVEL1
    objects = {"button": "push_button_target", "button topPlate": "target_button_plate",
               "lamp": "lamp_base"}
    joints = ("target_button_joint",)
    bulb_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    pressed_bulb_rgb: tuple[float, float, float] | None = None
    language: tuple[str, ...] = ()

    def descriptions(self, variation: int) -> list[str]:
        return list(self.language)

    def build(self, scene) -> None:
        _build_lamp(scene, self.bulb_rgb)

    def sample(self, key, variation) -> Placement:
        pos, quat = place_root(key, FOOTPRINT_HALF, jnp.pi, offset=FOOTPRINT_CENTER)
        return Placement(bodies={"lamp_root": (pos, quat)})

    def success(self, variation):
        return JointMoved(("target_button_joint",), 0.003)

    def state_colors(self, variation):
        if self.pressed_bulb_rgb is None:
            return ()
        return (StateColor(("bulb",), self.pressed_bulb_rgb, self.success(variation)),)

    def expert(self, obs, variation):
        """Hover 0.083 m above the switch with fingers closed to 0.1, then press."""
        return key_actions([
            (in_frame(obs, "push_button_target", (0, 0, 0.091)), DOWN, 0.1),
            (in_frame(obs, "push_button_target", (0, 0, 0.016)), DOWN, 0.1),
        ])
