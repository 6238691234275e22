"""The dense oracle replay (``--policy dense-replay --action-mode dense``): the dense
export's actions of the expert's demo of each episode's own scene, one per control step.

At reset the policy records the expert on a copy of the scene, as the exporter does
(``python -m agnostos_mjx.data.export --every rlbench``: the expert run to its end, a frame
every K physics steps of each key action plus the keyframes; data/expert_frames.py), and
takes the actions the LeRobot export writes for those frames: frame t's action is frame
t+1's gripper pose and gripper_open (`next_frame_actions`).  Control step k executes frame
k's action; past the last frame it holds the last one.  It checks that dense control can
execute the demonstrations a LeRobot-trained policy learns from.

Options (``--policy-arg``, `DenseReplayOptions`): ``every`` (the export's --every, default
"rlbench": 20 Hz), ``chunk`` (rows per answer, default 1: an action chunk of the next H
actions, for the evaluator's --execute) and ``relative`` (rows as deltas: the first of a
chunk from the tip pose measured now, the others from the previous row's target).
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.data.expert_frames import frame_every, next_frame_actions, proprio_frames
from agnostos_mjx.policies.base import Policy, Round
from agnostos_mjx.policies.learned_options import DenseReplayOptions
from agnostos_mjx.sim.actions import KeyActions
from agnostos_mjx.sim.math3d import pose_delta


class DenseReplayPolicy(Policy):
    """Replays each world's expert demo as dense actions (see the module docstring).
    Privileged: it records the expert on a copy of the scene."""

    name = "dense-replay"
    action_modes = ("dense",)
    privileged = True

    def __init__(self, options: DenseReplayOptions | None = None) -> None:
        o = options or DenseReplayOptions()
        frame_every(o.every, 0.005)  # a ValueError for a bad --every now, not at reset
        self.every, self.chunk, self.relative = o.every, o.chunk, o.relative
        self.pose = np.zeros((0, 1, 7))
        self.gripper = np.zeros((0, 1))
        self.frames = np.zeros(0, np.int64)
        self.demo_success = np.zeros(0, bool)

    def reset(self, view: Round) -> None:
        from agnostos_mjx.runtime.outcome import Outcome

        episodes, env = view.episodes, view.env
        every = frame_every(self.every, episodes.dt)
        demo, frames, _ = proprio_frames(episodes, env.replace(stop_at_success=False), every)
        self.demo_success = np.asarray(demo.outcome) == Outcome.SUCCESS
        actions = [next_frame_actions(f) for f in frames]
        self.frames = np.array([len(f) for f in frames], np.int64)
        n = int(self.frames.max())
        # Past its last frame a world holds its last action (the export's last action).
        take = np.minimum(np.arange(n)[None], self.frames[:, None] - 1)
        self.pose = np.stack([a[0][t] for a, t in zip(actions, take)])
        self.gripper = np.stack([a[1][t] for a, t in zip(actions, take)]).astype(np.float64)

    def act(self, view: Round) -> KeyActions:
        b, n = self.gripper.shape
        # Control steps executed so far: the next frame's action, whatever chunks ran.
        k = np.asarray(view.key_actions, np.int64)[:, None] + np.arange(self.chunk)[None]
        idx = np.minimum(k, n - 1)
        rows = np.arange(b)[:, None]
        pose = self.pose[rows, idx]
        pos, quat = pose[..., :3], pose[..., [6, 3, 4, 5]]
        if self.relative:
            obs = view.env.obs
            ref_pos = np.concatenate([np.asarray(obs["tip.pos"], np.float64)[:, None],
                                      pos[:, :-1]], 1)
            ref_quat = np.concatenate([np.asarray(obs["tip.quat"], np.float64)[:, None],
                                       quat[:, :-1]], 1)
            pos, quat = pose_delta(ref_pos, ref_quat, pos, quat)
        grip, valid = self.gripper[rows, idx], np.ones(idx.shape, bool)
        if self.chunk == 1:
            return KeyActions(pos[:, 0], quat[:, 0], grip[:, 0], valid[:, 0])
        return KeyActions(pos, quat, grip, valid)

    def episode_info(self, world: int) -> dict:
        """The demo behind the replay: its frames and whether the expert succeeded on it
        (the exporter keeps successful demos only)."""
        return {"demo_frames": int(self.frames[world]),
                "demo_success": bool(self.demo_success[world])}
