"""lamp_off (unseen, Level 1): press the floor switch to turn the lamp off."""

from __future__ import annotations

from agnostos_mjx.tasks.lamp import LampTask


class LampOff(LampTask):
    name = "lamp_off"
    bulb_rgb = (1.0, 1.0, 1.0)
    language = ("turn off the light", "press the button to turn off the lamp",
                "press the light switch", "turn the lamp off",
                "close the gripper and press on the button until the light turns off")
    notes = ("The bulb starts white. RLBench means to turn it black on success but its check "
             "(condition_met() == (True, True); conditions return (met, False)) never holds, "
             "so the bulb stays white there and here.")


TASK = LampOff()
