"""A complete image-consuming policy plug-in: `--policy examples/vla_policy.py:GreenSeeker`.

It declares what it sees (front + wrist RGB, front point cloud and segmentation at 128 px),
and every key action it moves the gripper 10 cm above the centre of the front camera's
pixels whose colour is most green, then down onto them.  Replace `_target` with your
model's forward pass: `view.observation.cameras["front"].rgb` is a (B, 128, 128, 3) uint8
batch, `view.proprioception["gripper_pose"]` the (B, 7) tip poses, `view.instructions`
the goals.
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.policies import Policy, Round
from agnostos_mjx.runtime.observation import ObservationSpec, RLBenchObservation
from agnostos_mjx.sim.actions import KeyActions

DOWN = np.array([0.0, 1.0, 0.0, 0.0], np.float32)  # w x y z: gripper pointing down


class GreenSeeker(Policy):
    name = "green-seeker"
    observation_spec = ObservationSpec(cameras=("front", "wrist"), height=128, width=128,
                                       modalities=("rgb", "point_cloud", "segmentation"))

    def reset(self, view: Round) -> None:
        self.instructions = view.instructions
        self.steps = 0

    def _target(self, obs: RLBenchObservation) -> np.ndarray:
        """(B, 3) world point: mean of the greenest front-camera pixels' 3-D points."""
        front = obs.cameras["front"]
        rgb = front.rgb.astype(np.float32)
        greenness = rgb[..., 1] - 0.5 * (rgb[..., 0] + rgb[..., 2])  # (B, H, W)
        top = greenness >= np.percentile(greenness, 99.5, axis=(1, 2), keepdims=True)
        points = front.point_cloud  # (B, H, W, 3), world frame
        return np.stack([points[b][top[b]].mean(axis=0) for b in range(obs.batch)])

    def act(self, view: Round) -> KeyActions:
        b = view.batch
        target = self._target(view.observation) + [0.0, 0.0, 0.10 if self.steps == 0 else 0.02]
        self.steps += 1
        return KeyActions(pos=target.astype(np.float32), quat=np.tile(DOWN, (b, 1)),
                          gripper=np.ones(b, np.float32), valid=np.full(b, self.steps <= 2))
