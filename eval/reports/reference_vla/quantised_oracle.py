"""The reference VLA's action representation as a ceiling: the scripted expert's key actions
passed through it (position -> Gaussian heatmaps on the three virtual views -> the decoder
the model uses; rotation -> X-ICM's 5-degree Euler bins and back; gripper -> steps of 0.1).
A perfect model could do no better than this policy.

python -m agnostos_mjx.eval --policy eval/reports/reference_vla/quantised_oracle.py:QuantisedOracle \
    --policy-arg view_size=96 --tasks seen --episodes 4 --seeds 0
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.policies.base import Round
from agnostos_mjx.policies.oracle import OraclePolicy
from agnostos_mjx.sim.actions import KeyActions
from agnostos_mjx.sim.textualise import euler_bins_to_quat, quat_to_euler_bins
from agnostos_mjx.vla.views import decode_position, target_heatmaps


class QuantisedOracle(OraclePolicy):
    name = "quantised-oracle"

    def __init__(self, view_size: int = 96, sigma: float = 1.5, parts: str = "pos,rot") -> None:
        super().__init__()
        self.view_size, self.sigma = int(view_size), float(sigma)
        self.parts = set(parts.split(","))  # which of pos, rot are quantised

    def act(self, view: Round) -> KeyActions:
        a = super().act(view)
        pos, quat = np.asarray(a.pos, np.float32), np.asarray(a.quat, np.float32)
        if "pos" in self.parts:
            maps = target_heatmaps(pos, self.view_size, self.sigma)
            pos = np.asarray(decode_position(np.log(np.asarray(maps) + 1e-9)), np.float32)
        if "rot" in self.parts:
            quat = euler_bins_to_quat(quat_to_euler_bins(quat)).astype(np.float32)
        grip = np.round(np.asarray(a.gripper) * 10).astype(np.float32) / 10  # GRIP_BINS
        return KeyActions(pos=pos, quat=quat, gripper=grip, valid=a.valid)
