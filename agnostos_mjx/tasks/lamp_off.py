"""lamp_off (unseen, Level 1): press the floor switch to turn the lamp off."""

from __future__ import annotations

from agnostos_mjx.tasks.base import Split, Task
from agnostos_mjx.tasks.lamp import (
    LAMP_OBJECTS,
    build_lamp,
    press_switch,
    sample_lamp,
    switch_expert,
)


class LampOff(Task):
    name = "lamp_off"
    split = Split.LEVEL1
    objects = LAMP_OBJECTS
    joints = ("target_button_joint",)
    notes = ("The bulb starts white. RLBench means to turn it black on success but its check "
             "never holds (a bug); the colour change is visual only and not rendered here.")

    def descriptions(self, variation: int) -> list[str]:
        return ["turn off the light", "press the button to turn off the lamp",
                "press the light switch", "turn the lamp off",
                "close the gripper and press on the button until the light turns off"]

    def build(self, scene) -> None:
        build_lamp(scene, bulb_rgb=(1.0, 1.0, 1.0))

    def sample(self, key, variation):
        return sample_lamp(key)

    def success(self, variation):
        return press_switch()

    def expert(self, obs, variation):
        return switch_expert(obs)
