"""lamp_on (unseen, Level 1): press the floor switch to turn the lamp on."""

from __future__ import annotations

from agnostos_mjx.tasks.lamp import LampTask


class LampOn(LampTask):
    name = "lamp_on"
    bulb_rgb = (0.0, 0.0, 0.0)
    pressed_bulb_rgb = (1.0, 1.0, 1.0)
    language = ("turn on the light", "press the button to turn on the lamp",
                "press the light switch", "turn the lamp on",
                "close the gripper and press on the button until the light turns on")
    notes = ("The bulb starts black and turns white once the switch is pressed (RLBench's "
             "step(); visual only), rendered from the observation after each phase.")


TASK = LampOn()
