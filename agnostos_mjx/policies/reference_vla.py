"""The reference in-domain VLA as an evaluator policy: ``--policy reference-vla
--policy-arg checkpoint=RUN`` (a run directory of ``python -m agnostos_mjx.train.vla``, or
its float16 export: vla/checkpoint.py).

It declares the observation its checkpoint was trained on (the cameras and image size
in the checkpoint's metadata; RGB and point clouds), and at every step predicts each
world's next key action from the fused point cloud, the gripper state, the number of key
actions taken so far and the instruction: the tip position, X-ICM's Euler bins
(decoded as textualise.euler_bins_to_quat) and the gripper's open amount (0, 0.1, ..., 1).
It gives up (an invalid action: the episode ends as no_action) after as many key actions
as the longest training demo had (``max_key_actions`` in the checkpoint; the key-action
index embedding never saw more), so that a lost episode does not run to the task's limit of
25; ``--policy-arg max_steps=25`` turns that off.  The network runs on ``chunk`` worlds at a
time (``--policy-arg chunk=N``, default 25; the last chunk is padded, so one program serves
every batch): at 75 at once one forward pass needed 3.65 GiB of GPU memory, and 16
evaluation processes on one GPU ran out of it.
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.policies.base import Policy, Round
from agnostos_mjx.policies.learned_options import ReferenceVLAOptions
from agnostos_mjx.runtime.observation import ObservationSpec
from agnostos_mjx.sim.actions import KeyActions


class ReferenceVLAPolicy(Policy):
    """A trained reference VLA (vla/model.py) behind the policy interface."""

    name = "reference-vla"

    def __init__(self, options: ReferenceVLAOptions | None = None) -> None:
        o = options or ReferenceVLAOptions()
        if not o.checkpoint:
            raise ValueError("reference-vla needs its run directory: --policy-arg "
                             "checkpoint=RUN (python -m agnostos_mjx.train.vla --out RUN)")
        import jax
        from flax import nnx

        from agnostos_mjx.dynamics.checkpoint import CheckpointError
        from agnostos_mjx.vla.checkpoint import load
        from agnostos_mjx.vla.model import MAX_STEPS, predict
        from agnostos_mjx.vla.views import render_views

        try:
            model, self.meta = load(o.checkpoint)
        except CheckpointError as err:
            raise ValueError(str(err)) from None
        self.max_steps = int(o.max_steps or self.meta.get("max_key_actions") or MAX_STEPS)
        self.chunk = o.chunk
        obs = self.meta["observation"]
        self.cameras = tuple(obs["cameras"])
        self.observation_spec = ObservationSpec(
            cameras=self.cameras, height=obs["size"], width=obs["size"],
            modalities=("rgb", "point_cloud"), renderer=o.renderer)
        self.cfg = model.cfg
        graphdef, params = nnx.split(model)
        size = self.cfg.view_size

        @jax.jit
        def forward(params, points, rgb, gripper, ids, mask, gripper_open, step):
            views = render_views(points, rgb, gripper, size)
            return predict(nnx.merge(graphdef, params), views, ids, mask, gripper_open, step)

        self._forward, self._params = forward, params
        self.steps = np.zeros(0, np.int32)

    @classmethod
    def warm_up(cls, options: ReferenceVLAOptions, batch: int) -> bool:
        """Its network's one program (`chunk` worlds, `_predict`) on a blank observation."""
        policy = cls(options)
        spec = policy.observation_spec
        size, n = min(policy.chunk, batch), len(spec.cameras) * spec.height * spec.width
        ids, mask = policy._tokenize(["press the button"] * size)
        policy._predict(np.zeros((size, n, 3), np.float32), np.zeros((size, n, 3), np.uint8),
                        np.zeros((size, 3), np.float32), ids, mask, np.ones(size, np.float32),
                        np.zeros(size, np.int32))
        return True

    def _tokenize(self, instructions: list[str]) -> tuple[np.ndarray, np.ndarray]:
        from agnostos_mjx.dynamics.text import tokenize

        return tokenize(instructions, self.cfg.text_len)

    def reset(self, view: Round) -> None:
        self.ids, self.mask = self._tokenize(list(view.instructions))
        self.steps = np.zeros(view.batch, np.int32)

    def act(self, view: Round) -> KeyActions:
        from agnostos_mjx.sim.textualise import euler_bins_to_quat

        observation = view.observation
        b = observation.batch
        cams = [observation.cameras[c] for c in self.cameras]
        points = np.concatenate([np.asarray(c.point_cloud).reshape(b, -1, 3) for c in cams], 1)
        rgb = np.concatenate([np.asarray(c.rgb).reshape(b, -1, 3) for c in cams], 1)
        pos, bins, grip = self._predict(
            points.astype(np.float16).astype(np.float32), rgb,  # as stored
            np.asarray(observation.gripper_pose[:, :3], np.float32), self.ids[:b],
            self.mask[:b], np.asarray(observation.gripper_open, np.float32), self.steps[:b])
        valid = self.steps[:b] < self.max_steps
        self.steps = self.steps + 1
        return KeyActions(pos=np.asarray(pos, np.float32),
                          quat=euler_bins_to_quat(np.asarray(bins)).astype(np.float32),
                          gripper=np.asarray(grip, np.float32), valid=valid)

    def _predict(self, *inputs: np.ndarray) -> list[np.ndarray]:
        """The network on `chunk` worlds at a time, the last chunk padded with its last world."""
        b = inputs[0].shape[0]
        size = min(self.chunk, b)
        parts = []
        for start in range(0, b, size):
            part = [x[start:start + size] for x in inputs]
            n = part[0].shape[0]
            if n < size:
                part = [np.concatenate([x, np.repeat(x[-1:], size - n, 0)]) for x in part]
            parts.append([np.asarray(y)[:n] for y in self._forward(self._params, *part)])
        return [np.concatenate(ys) for ys in zip(*parts)]
