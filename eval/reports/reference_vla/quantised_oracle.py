"""The reference VLA's action representation as a ceiling: the scripted expert's key actions
passed through it (position -> Gaussian heatmaps on the three virtual views -> the decoder
the model uses; rotation -> X-ICM's 5-degree Euler bins and back; gripper -> open/close).
A perfect model could do no better than this policy.

python -m agnostos_mjx.eval --policy eval/reports/reference_vla/quantised_oracle.py:QuantisedOracle \
    --policy-arg view_size=64 --tasks seen --episodes 4 --seeds 0
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.policies.oracle import OraclePolicy
from agnostos_mjx.tasks.base import KeyActions
from agnostos_mjx.textualise import euler_bins_to_quat, quat_to_euler_bins
from agnostos_mjx.vla.views import decode_position, target_heatmaps


class QuantisedOracle(OraclePolicy):
    name = "quantised-oracle"

    def __init__(self, view_size: int = 64, sigma: float = 1.5) -> None:
        super().__init__()
        self.view_size, self.sigma = int(view_size), float(sigma)

    def act(self, episodes, env) -> KeyActions:
        a = super().act(episodes, env)
        maps = target_heatmaps(np.asarray(a.pos), self.view_size, self.sigma)
        pos = np.asarray(decode_position(np.log(np.asarray(maps) + 1e-9)), np.float32)
        quat = euler_bins_to_quat(quat_to_euler_bins(np.asarray(a.quat))).astype(np.float32)
        grip = (np.asarray(a.gripper) >= 0.5).astype(np.float32)
        return KeyActions(pos=pos, quat=quat, gripper=grip, valid=a.valid)
