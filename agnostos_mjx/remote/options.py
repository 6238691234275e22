"""The options of ``--policy remote`` and ``--policy openvla`` (policies/options.py), apart
from the client, whose adapter loads MuJoCo: the server's URL, the adapter's preset and
the fields that override it (remote/adapter.py says what each means), and the timeouts."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from agnostos_mjx.policies.options import OptionsError, PolicyOptions, option


class _PresetValue:
    """The default of an adapter field: the preset's value (null is a value of some)."""

    def __repr__(self) -> str:
        return "<the preset's>"


PRESET: Any = _PresetValue()
# RemoteOptions' fields that override the preset's Adapter fields (keys aside).
ADAPTER_FIELDS = ("height", "width", "action_key", "action_index", "execute", "rotation",
                  "quat_order", "relative", "gripper", "gripper_threshold", "constants")


@dataclass
class RemoteOptions(PolicyOptions):
    """A served policy: where, through which adapter, and how long to wait."""

    url: str | None = option(None, "ws://HOST:PORT (openpi) or http://HOST:PORT[/act] "
                                   "(--policy-url; default $AGNOSTOS_POLICY_URL)")
    preset: str = option("auto", "rlbench, libero, droid, xicm, openvla, openvla_oft, sim, or "
                                 "auto (the server's agnostos_preset, else by transport)")
    keys: dict[str, str] | None = option(None, "server key -> source, replacing the preset's")
    timeout_s: float = option(60.0, "seconds for an answer before the world ends as "
                                    "remote_timeout")
    connect_timeout_s: float = option(30.0, "seconds to reach the server at start-up")
    height: int = option(PRESET, "image height, pixels")
    width: int = option(PRESET, "image width, pixels")
    action_key: str | None = option(PRESET, "the answer's key of the actions (null: the "
                                            "answer itself)")
    action_index: int = option(PRESET, "first row of a chunk executed")
    execute: int = option(PRESET, "rows of a chunk executed before asking again")
    rotation: str = option(PRESET, "a row's rotation: quat, euler, axis_angle or rot6d")
    quat_order: str = option(PRESET, "xyzw or wxyz")
    relative: bool = option(PRESET, "rows as deltas of the current tip pose")
    gripper: str = option(PRESET, "the gripper column: open or closed amount")
    gripper_threshold: float | None = option(PRESET, "binary gripper at this value (null: "
                                                     "continuous)")
    constants: dict[str, Any] = option(PRESET, "server key -> value sent with every request")

    def check(self) -> None:
        for name in ("timeout_s", "connect_timeout_s"):
            if getattr(self, name) <= 0:
                raise OptionsError(f"{name}={getattr(self, name)}: must be positive")

    @classmethod
    def from_config(cls, cfg: Any) -> dict[str, Any]:
        return {"url": cfg.policy.url} if cfg.policy.url else {}

    def adapter_options(self) -> dict[str, Any]:
        """The adapter fields given, over the preset's."""
        return {k: getattr(self, k) for k in ADAPTER_FIELDS if getattr(self, k) is not PRESET}


@dataclass
class OpenVLAOptions(RemoteOptions):
    """An OpenVLA / OpenVLA-OFT deploy.py server (openvla_oft: OFT's keys)."""

    preset: str = option("openvla", "openvla or openvla_oft (or any preset of --policy "
                                    "remote)")
