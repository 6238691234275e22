"""A declarative map between our observation / key actions and a policy server's keys.

Observation side: ``keys`` maps each key the server reads to one of our *sources*:

* ``<camera>_rgb`` uint8 (H, W, 3), ``<camera>_depth`` float32 (H, W) metres,
  ``<camera>_point_cloud`` float32 (H, W, 3) world frame, ``<camera>_mask`` int32 (H, W)
  geom ids, for cameras front, left_shoulder, right_shoulder, overhead, wrist (RLBench's
  names; see agnostos_mjx/observation.py for the conventions);
* ``gripper_pose`` float32 (7,) x y z qx qy qz qw (world frame, scalar-last),
  ``gripper_open`` float32 () 1 open / 0 closed, ``gripper_closed`` its complement (DROID's
  gripper_position), ``joint_positions`` / ``joint_velocities`` float32 (7,),
  ``gripper_joint_positions`` float32 (2,) metres, ``libero_state`` float32 (8,) xyz +
  axis-angle + the two finger positions (LIBERO's state layout), ``instruction`` str;
* ``sim_state``: the simulator's low-dimensional state of the world (privileged; what our
  reference server needs to run a policy written against ``env``, see serve.py).

Action side: the answer's ``action_key`` ("actions") holds one action (D,) or a chunk
(H, D); row ``action_index`` of a chunk is executed (an empty chunk means "nothing to
execute": the episode ends as no_action).  Columns 0-2: absolute tip position in metres
in the world frame (the frame of ``gripper_pose``), 3-6: tip orientation as a unit
quaternion in ``quat_order`` (xyzw, RLBench's, by default; or wxyz), 7: gripper, an open
amount in [0, 1] (``gripper="open"``) or a closed amount (``gripper="closed"``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from agnostos_mjx.observation import CAMERAS, ObservationSpec

if TYPE_CHECKING:
    from agnostos_mjx.observation import RLBenchObservation
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.state import EnvState

CAMERA_FIELDS = {"rgb": "rgb", "depth": "depth", "point_cloud": "point_cloud",
                 "mask": "segmentation"}
LOWDIM_SOURCES = ("gripper_pose", "gripper_open", "gripper_closed", "joint_positions",
                  "joint_velocities", "gripper_joint_positions", "libero_state",
                  "instruction", "sim_state")
QUAT_ORDERS = ("xyzw", "wxyz")
GRIPPER_CONVENTIONS = ("open", "closed")


class BadAnswer(ValueError):
    """The server's answer cannot be read as a key action."""


def camera_source(source: str) -> tuple[str, str] | None:
    """(camera, observation field) of a camera source, None for the others."""
    for cam in CAMERAS:
        if source.startswith(cam + "_") and source[len(cam) + 1:] in CAMERA_FIELDS:
            return cam, CAMERA_FIELDS[source[len(cam) + 1:]]
    return None


@dataclass(frozen=True)
class Adapter:
    """Which of our sources go to which server key, and how to read its actions."""

    keys: Mapping[str, str] = field(default_factory=dict)
    height: int = 224
    width: int = 224
    action_key: str = "actions"
    action_index: int = 0
    quat_order: str = "xyzw"
    gripper: str = "open"

    def __post_init__(self) -> None:
        bad = [s for s in self.keys.values() if s not in LOWDIM_SOURCES and not camera_source(s)]
        if bad:
            raise ValueError(f"unknown observation sources {bad}; choose from {LOWDIM_SOURCES} "
                             f"or <camera>_<rgb|depth|point_cloud|mask>, cameras {CAMERAS}")
        if self.quat_order not in QUAT_ORDERS:
            raise ValueError(f"quat_order must be one of {QUAT_ORDERS}, got {self.quat_order!r}")
        if self.gripper not in GRIPPER_CONVENTIONS:
            raise ValueError(f"gripper must be one of {GRIPPER_CONVENTIONS}, "
                             f"got {self.gripper!r}")
        if self.action_index < 0:
            raise ValueError(f"action_index must be >= 0, got {self.action_index}")

    def spec(self) -> ObservationSpec | None:
        """What to render for the server (None: no camera, nothing is rendered)."""
        found = [c for c in map(camera_source, self.keys.values()) if c]
        if not found:
            return None
        cams = tuple(dict.fromkeys(c for c, _ in found))
        mods = {m for _, m in found}
        return ObservationSpec(cameras=cams, height=self.height, width=self.width,
                               modalities=tuple(sorted(mods)))

    @property
    def wants_sim_state(self) -> bool:
        return "sim_state" in self.keys.values()


_INSTRUCTION = {"prompt": "instruction"}
PRESETS: dict[str, Adapter] = {
    # RLBench's own field names (PerAct, RVT and GemBench-style servers), 128 px.
    "rlbench": Adapter(keys={**{f"{c}_rgb": f"{c}_rgb" for c in
                                ("front", "left_shoulder", "right_shoulder", "wrist")},
                             "gripper_pose": "gripper_pose", "gripper_open": "gripper_open",
                             "joint_positions": "joint_positions", **_INSTRUCTION},
                       height=128, width=128),
    # openpi's LiberoInputs keys (pi0 / pi0.5 LIBERO checkpoints), 224 px.
    "libero": Adapter(keys={"observation/image": "front_rgb",
                            "observation/wrist_image": "wrist_rgb",
                            "observation/state": "libero_state", **_INSTRUCTION}),
    # openpi's DroidInputs keys (pi0 / pi0.5 DROID checkpoints), 224 px.
    "droid": Adapter(keys={"observation/exterior_image_1_left": "front_rgb",
                           "observation/wrist_image_left": "wrist_rgb",
                           "observation/joint_position": "joint_positions",
                           "observation/gripper_position": "gripper_closed",
                           **_INSTRUCTION}),
    # Our reference server (python -m agnostos_mjx.serve): simulator state, no images.
    "sim": Adapter(keys={"sim_state": "sim_state", **_INSTRUCTION}),
}


def make_adapter(preset: str = "rlbench", keys: Mapping[str, str] | str | None = None,
                 **options: Any) -> Adapter:
    """A preset, its keys replaced by `keys` (a mapping or its JSON text) when given, and
    other fields (height, width, action_index, quat_order, gripper, ...) overridden."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    if isinstance(keys, str):
        try:
            keys = json.loads(keys)
        except json.JSONDecodeError as e:
            raise ValueError(f"keys must be a JSON object: {e}") from None
    if keys is not None and not (isinstance(keys, Mapping)
                                 and all(isinstance(v, str) for v in keys.values())):
        raise ValueError("keys must map server keys to source names (strings)")
    base = PRESETS[preset]
    return replace(base, **({"keys": dict(keys)} if keys is not None else {}), **options)


# ---- observation -> request ---------------------------------------------------------------
def quat_to_axis_angle(xyzw: np.ndarray) -> np.ndarray:
    """Scalar-last unit quaternions (..., 4) -> axis * angle (..., 3), angle in [0, pi]."""
    q = np.where(xyzw[..., 3:4] < 0, -xyzw, xyzw)
    s = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., 3:4])
    return np.where(s > 1e-12, q[..., :3] / np.maximum(s, 1e-12) * angle, 0.0).astype(np.float32)


def lowdim(proprio: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Our low-dimensional sources of a batch from observation.proprioception's fields."""
    pose = proprio["gripper_pose"]
    out = dict(proprio)
    out["gripper_closed"] = (1.0 - proprio["gripper_open"]).astype(np.float32)
    out["libero_state"] = np.concatenate(
        [pose[:, :3], quat_to_axis_angle(pose[:, 3:]), proprio["gripper_joint_positions"]],
        axis=1).astype(np.float32)
    return out


def sim_state(episodes: Episodes, env: EnvState, world: int, episode_seed: int) -> dict:
    """The simulator state of one world, enough to rebuild a one-world EnvState (serve.py)."""
    p = env.physics
    return {"task": episodes.task.name, "variation": int(env.variation[world]),
            "episode_seed": int(episode_seed), "key_actions": int(env.key_actions[world]),
            "sensordata": np.asarray(env.data[world]),
            "initial_sensordata": np.asarray(env.initial_data[world]),
            "attached": np.asarray(env.attached[world], bool),
            "gripper": float(env.gripper[world]),
            "qpos": np.asarray(p.qpos[world]), "mocap_pos": np.asarray(p.mocap_pos[world]),
            "mocap_quat": np.asarray(p.mocap_quat[world]),
            "geom_rgba": np.asarray(env.geom_rgba[world], np.float32)}


def request(adapter: Adapter, world: int, sources: Mapping[str, Any],
            observation: RLBenchObservation | None) -> dict[str, Any]:
    """The server's observation dict of one world.  `sources` holds the batch's low-dim
    sources (`lowdim`), ``instruction`` (list) and ``sim_state`` (list) where wanted."""
    out: dict[str, Any] = {}
    for key, source in adapter.keys.items():
        cam = camera_source(source)
        if cam is not None:
            assert observation is not None
            out[key] = np.asarray(getattr(observation.cameras[cam[0]], cam[1])[world])
        elif source in ("instruction", "sim_state"):
            out[key] = sources[source][world]
        else:
            value = sources[source][world]
            out[key] = np.asarray(value) if np.ndim(value) else np.float32(value)
    return out


# ---- answer -> key action -----------------------------------------------------------------
def parse_action(adapter: Adapter, answer: Any
                 ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(position (3,), quaternion wxyz (4,), open amount) of the answer's executed row;
    None for an empty chunk.  Raises BadAnswer on anything else."""
    if not isinstance(answer, Mapping) or adapter.action_key not in answer:
        keys = sorted(map(str, answer)) if isinstance(answer, Mapping) else type(answer).__name__
        raise BadAnswer(f"answer has no {adapter.action_key!r} (got {keys})")
    try:
        actions = np.asarray(answer[adapter.action_key], np.float64)
    except (TypeError, ValueError) as e:
        raise BadAnswer(f"{adapter.action_key!r} is not numeric: {e}") from None
    if actions.ndim == 1:
        actions = actions[None]
    if actions.ndim != 2 or actions.shape[-1] < 8:
        raise BadAnswer(f"{adapter.action_key!r} has shape {actions.shape}; expected (8,) or "
                        f"(H, >=8): xyz, quaternion {adapter.quat_order}, gripper")
    if len(actions) == 0:
        return None
    if adapter.action_index >= len(actions):
        raise BadAnswer(f"action_index {adapter.action_index} outside a chunk of "
                        f"{len(actions)}")
    row = actions[adapter.action_index]
    if not np.isfinite(row[:8]).all():
        raise BadAnswer(f"non-finite action {row[:8].tolist()}")
    quat = row[3:7] if adapter.quat_order == "wxyz" else row[[6, 3, 4, 5]]
    norm = float(np.linalg.norm(quat))
    if norm < 1e-6:
        raise BadAnswer("zero quaternion")
    if abs(norm - 1.0) > 1e-4:  # leave unit quaternions bit-exact
        quat = quat / norm
    grip = float(np.clip(row[7], 0.0, 1.0))
    return row[:3], quat, grip if adapter.gripper == "open" else 1.0 - grip
