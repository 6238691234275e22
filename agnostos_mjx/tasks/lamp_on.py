"""lamp_on (unseen, Level 1): press the floor switch to turn the lamp on."""

from __future__ import annotations

from agnostos_mjx.tasks.base import Split, Task
from agnostos_mjx.tasks.lamp import (
    LAMP_OBJECTS,
    build_lamp,
    press_switch,
    sample_lamp,
    switch_expert,
)


class LampOn(Task):
    name = "lamp_on"
    split = Split.LEVEL1
    objects = LAMP_OBJECTS
    joints = ("target_button_joint",)
    notes = ("The bulb starts black; RLBench turns it white once the switch is pressed. The "
             "colour change is visual only and not rendered here yet.")

    def descriptions(self, variation: int) -> list[str]:
        return ["turn on the light", "press the button to turn on the lamp",
                "press the light switch", "turn the lamp on",
                "close the gripper and press on the button until the light turns on"]

    def build(self, scene) -> None:
        build_lamp(scene, bulb_rgb=(0.0, 0.0, 0.0))

    def sample(self, key, variation):
        return sample_lamp(key)

    def success(self, variation):
        return press_switch()

    def expert(self, obs, variation):
        return switch_expert(obs)
