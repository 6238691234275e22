"""`timing`: a policy that looks and answers at once, to time the evaluator's closed loop.

It declares cameras like a VLA (``--policy-arg cameras=front,wrist size=128``), touches every
image it is given, and holds each world's gripper where it is: every episode then runs its
whole step budget, and a run's time is the loop's own (rendering, physics, bookkeeping)
with no network in it.  In dense mode it answers a chunk of ``chunk`` rows (asked again
every ``chunk`` control steps, as ACT and pi0 clients are); in key-action mode one key
action to the current pose.  tools/closed_loop_bench.py drives it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from agnostos_mjx.policies.base import Policy, Round
from agnostos_mjx.policies.options import OptionsError, PolicyOptions, option
from agnostos_mjx.sim.actions import KeyActions

if TYPE_CHECKING:
    from agnostos_mjx.runtime.observation import RLBenchObservation


@dataclass
class TimingOptions(PolicyOptions):
    """What the timing policy looks at, and how many rows it answers."""

    cameras: str = option("front,wrist", "comma-separated cameras it declares")
    size: int = option(128, "image height and width, pixels")
    chunk: int = option(1, "dense mode: rows per answer (asked again every chunk steps)")
    modalities: str = option("rgb", "comma-separated: rgb, depth, point_cloud, segmentation")
    numpy: bool = option(True, "images as numpy arrays (false: device arrays)")
    renderer: str = option("auto", "its ObservationSpec.renderer: auto, cpu or warp")

    def check(self) -> None:
        if self.chunk < 1:
            raise OptionsError(f"chunk={self.chunk}: must be a positive number of rows")
        if self.size < 1:
            raise OptionsError(f"size={self.size}: must be a positive number of pixels")


class TimingPolicy(Policy):
    """Holds every world still; sees `cameras` at `size` px each time it is asked."""

    name = "timing"
    action_modes = ("keyaction", "dense")

    def __init__(self, options: TimingOptions | None = None) -> None:
        from agnostos_mjx.runtime.observation import ObservationSpec

        o = options or TimingOptions()
        self.chunk = o.chunk
        self.observation_spec = ObservationSpec(
            cameras=tuple(n.strip() for n in o.cameras.split(",")), height=o.size,
            width=o.size, modalities=tuple(k.strip() for k in o.modalities.split(",")),
            renderer=o.renderer, numpy=o.numpy)
        self.pixels = 0  # pixels seen, so that no image goes unused

    def act(self, view: Round) -> KeyActions:
        self.pixels += _touch(view.observation)
        pose = view.proprioception["gripper_pose"]  # x y z qx qy qz qw
        b = len(pose)
        pos = np.asarray(pose[:, :3], np.float64)
        quat = np.asarray(pose[:, [6, 3, 4, 5]], np.float64)  # KeyActions: w first
        grip = np.ones(b)
        valid = np.ones(b, bool)
        if self.chunk == 1:
            return KeyActions(pos, quat, grip, valid)
        rows = lambda x: np.repeat(x[:, None], self.chunk, axis=1)  # noqa: E731
        return KeyActions(rows(pos), rows(quat), rows(grip), rows(valid))


def _touch(obs: RLBenchObservation) -> int:
    """Read every image once (a device array is waited for), as a model's input would."""
    seen = 0
    for cam in obs.cameras.values():
        for image in (cam.rgb, cam.depth, cam.point_cloud, cam.segmentation):
            if image is not None:
                seen += int(np.prod(image.shape[:3]))
                np.asarray(image[:, 0, 0])
    return seen
