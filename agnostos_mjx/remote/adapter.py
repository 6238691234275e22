"""A declarative map between our observation / key actions and a policy server's keys.

Observation side: ``keys`` maps each key the server reads to one of our *sources*:

* ``<camera>_rgb`` uint8 (H, W, 3), ``<camera>_depth`` float32 (H, W) metres,
  ``<camera>_point_cloud`` float32 (H, W, 3) world frame, ``<camera>_mask`` int32 (H, W)
  geom ids, for cameras front, left_shoulder, right_shoulder, overhead, wrist (RLBench's
  names; see agnostos_mjx/runtime/observation.py for the conventions);
* ``gripper_pose`` float32 (7,) x y z qx qy qz qw (world frame, scalar-last),
  ``gripper_open`` float32 () 1 open / 0 closed, ``gripper_closed`` its complement (DROID's
  gripper_position), ``joint_positions`` / ``joint_velocities`` float32 (7,),
  ``gripper_joint_positions`` float32 (2,) metres, ``libero_state`` float32 (8,) xyz +
  axis-angle + the two finger positions (LIBERO's state layout), ``instruction`` str;
* ``xicm_state`` float64 (7,) x y z + Euler angles (extrinsic x-y-z, radians, as scipy's
  ``Rotation.as_euler("xyz")`` and so X-ICM's ``utils.convert_to_euler`` give them) +
  gripper_open: the ``observation/state`` of X-ICM's custom_agent.py (float64 there too:
  its float32 pose and scipy's float64 angles, concatenated);
* ``sim_state``: the simulator's low-dimensional state of the world (privileged; what our
  reference server needs to run a policy written against ``env``, see serve.py).

``constants`` (server key -> value) go with every request as they are (e.g. OpenVLA's
``unnorm_key``).

Action side: the answer's ``action_key`` ("actions"; None: the answer itself, as OpenVLA's
deploy.py answers) holds one action (D,) or a chunk (H, D).  Rows ``action_index`` to
``action_index + execute - 1`` are executed as that many consecutive key actions before
the server is asked again (fewer when the chunk is shorter; X-ICM's
``action_chunk_length``); an empty chunk means "nothing to execute" (the episode ends as
no_action).  A row is ``[x, y, z, rotation..., gripper]``, further columns ignored:

* x y z: the tip position in metres in the world frame (the frame of ``gripper_pose``);
* the tip orientation, as ``rotation`` says: ``quat`` (4 columns: a unit quaternion in
  ``quat_order``, xyzw (RLBench's, default) or wxyz), ``euler`` (3: extrinsic x-y-z angles
  in radians, scipy's ``Rotation.from_euler("xyz", ...)``, X-ICM's convention),
  ``axis_angle`` (3: a rotation vector, axis times angle in radians) or ``rot6d`` (6: the
  first two columns of the rotation matrix, column 0 then column 1, Zhou et al. 2019;
  orthonormalised by Gram-Schmidt);
* the gripper: an open amount in [0, 1] (``gripper="open"``) or a closed amount
  (``gripper="closed"``), clipped; with ``gripper_threshold`` t it is binary: a value >= t
  is open (``gripper="open"``) or closed (``gripper="closed"``); X-ICM's rule is t = 0.5.

So rows are 8 columns wide with quaternions, 7 with Euler angles or rotation vectors
(X-ICM's and OpenVLA's 7-D actions) and 10 with 6-D rotations.  The width comes from
``rotation``, never from the answer.

With ``relative=True`` a row is a *delta* of the current tip pose (OpenVLA's 7-D delta
end-effector actions [dx, dy, dz, droll, dpitch, dyaw, gripper]): the target position is
the current one plus the row's xyz (world frame), the target orientation the row's
rotation composed on the left of the current one, ``q_target = q_delta * q_current`` (a
rotation about the world axes, as RLBench's ``EndEffectorPose*(absolute_mode=False)``
and robosuite's OSC controller apply deltas); the gripper stays absolute.  A delta is
applied to the tip pose measured when its key action starts, so the rows of a chunk
(``execute`` > 1) chain through the poses actually reached.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from agnostos_mjx.runtime.observation import CAMERAS, ObservationSpec
from agnostos_mjx.sim import math3d

if TYPE_CHECKING:
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.observation import RLBenchObservation
    from agnostos_mjx.runtime.state import EnvState

CAMERA_FIELDS = {"rgb": "rgb", "depth": "depth", "point_cloud": "point_cloud",
                 "mask": "segmentation"}
LOWDIM_SOURCES = ("gripper_pose", "gripper_open", "gripper_closed", "joint_positions",
                  "joint_velocities", "gripper_joint_positions", "libero_state",
                  "xicm_state", "instruction", "sim_state")
QUAT_ORDERS = ("xyzw", "wxyz")
GRIPPER_CONVENTIONS = ("open", "closed")
ROTATIONS = {"quat": 4, "euler": 3, "axis_angle": 3, "rot6d": 6}  # columns of each

# One key action of a row: tip position (3,), quaternion wxyz (4,), gripper open amount;
# a delta (position offset, rotation) when the adapter is relative.
Row = tuple[np.ndarray, np.ndarray, float]


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
    action_key: str | None = "actions"
    action_index: int = 0
    execute: int = 1
    rotation: str = "quat"
    quat_order: str = "xyzw"
    relative: bool = False
    gripper: str = "open"
    gripper_threshold: float | None = None
    constants: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        bad = [s for s in self.keys.values() if s not in LOWDIM_SOURCES and not camera_source(s)]
        if bad:
            raise ValueError(f"unknown observation sources {bad}; choose from {LOWDIM_SOURCES} "
                             f"or <camera>_<rgb|depth|point_cloud|mask>, cameras {CAMERAS}")
        if self.rotation not in ROTATIONS:
            raise ValueError(f"rotation must be one of {tuple(ROTATIONS)}, got {self.rotation!r}")
        if self.quat_order not in QUAT_ORDERS:
            raise ValueError(f"quat_order must be one of {QUAT_ORDERS}, got {self.quat_order!r}")
        if self.gripper not in GRIPPER_CONVENTIONS:
            raise ValueError(f"gripper must be one of {GRIPPER_CONVENTIONS}, "
                             f"got {self.gripper!r}")
        if not isinstance(self.action_index, int) or self.action_index < 0:
            raise ValueError(f"action_index must be an integer >= 0, got {self.action_index!r}")
        if not isinstance(self.execute, int) or isinstance(self.execute, bool) \
                or self.execute < 1:
            raise ValueError(f"execute must be an integer >= 1, got {self.execute!r}")
        if not isinstance(self.relative, bool):
            raise ValueError(f"relative must be true or false, got {self.relative!r}")
        if self.gripper_threshold is not None and not isinstance(self.gripper_threshold,
                                                                 (int, float)):
            raise ValueError(f"gripper_threshold must be a number or null, "
                             f"got {self.gripper_threshold!r}")
        if self.action_key is not None and not isinstance(self.action_key, str):
            raise ValueError(f"action_key must be a string or null, got {self.action_key!r}")
        if not isinstance(self.constants, Mapping):
            raise ValueError("constants must map server keys to values")
        clash = set(self.constants) & set(self.keys)
        if clash:
            raise ValueError(f"keys {sorted(clash)} are both sources and constants")

    @property
    def row_width(self) -> int:
        """Columns a row needs: xyz, the rotation, the gripper."""
        return 3 + ROTATIONS[self.rotation] + 1

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
_OPENVLA = dict(action_key=None, rotation="euler", relative=True, gripper_threshold=0.5)
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
    # X-ICM's custom_agent.py (a pi0 behind openpi's client): three views at 256 px,
    # state xyz + Euler + open, answers [x, y, z, Euler xyz (rad), gripper >= 0.5 open].
    "xicm": Adapter(keys={"observation/front_image": "front_rgb",
                          "observation/wrist_image": "wrist_rgb",
                          "observation/overhead_image": "overhead_rgb",
                          "observation/state": "xicm_state", **_INSTRUCTION},
                    height=256, width=256, rotation="euler", gripper_threshold=0.5),
    # OpenVLA's vla-scripts/deploy.py (HTTP POST /act, json_numpy): {"image",
    # "instruction"} -> one 7-D delta action [dx, dy, dz, droll, dpitch, dyaw, gripper].
    "openvla": Adapter(keys={"image": "front_rgb", "instruction": "instruction"}, **_OPENVLA),
    # OpenVLA-OFT's deploy.py: {"full_image", "wrist_image", "state", "instruction"} ->
    # a chunk of 7-D delta actions (8 rows for its LIBERO checkpoints).
    "openvla_oft": Adapter(keys={"full_image": "front_rgb", "wrist_image": "wrist_rgb",
                                 "state": "libero_state", "instruction": "instruction"},
                           **_OPENVLA),
    # Our reference server (python -m agnostos_mjx.serve): simulator state, no images.
    "sim": Adapter(keys={"sim_state": "sim_state", **_INSTRUCTION}),
}


def make_adapter(preset: str = "rlbench", keys: Mapping[str, str] | str | None = None,
                 **options: Any) -> Adapter:
    """A preset, its keys replaced by `keys` (a mapping or its JSON text) when given, and
    other fields (height, width, action_index, execute, rotation, quat_order, relative,
    gripper, gripper_threshold, action_key, constants) overridden."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    keys = _json_mapping("keys", keys)
    if keys is not None and not all(isinstance(v, str) for v in keys.values()):
        raise ValueError("keys must map server keys to source names (strings)")
    if "constants" in options:
        options["constants"] = _json_mapping("constants", options["constants"]) or {}
    unknown = set(options) - {f for f in Adapter.__dataclass_fields__ if f != "keys"}
    if unknown:
        raise ValueError(f"unknown adapter options {sorted(unknown)}")
    base = PRESETS[preset]
    return replace(base, **({"keys": dict(keys)} if keys is not None else {}), **options)


def _json_mapping(name: str, value: Any) -> Mapping | None:
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except json.JSONDecodeError as e:
            raise ValueError(f"{name} must be a JSON object: {e}") from None
    if value is not None and not isinstance(value, Mapping):
        raise ValueError(f"{name} must be a JSON object")
    return value


# ---- observation -> request ---------------------------------------------------------------
def lowdim(proprio: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Our low-dimensional sources of a batch from observation.proprioception's fields."""
    pose = proprio["gripper_pose"]
    out = dict(proprio)
    out["gripper_closed"] = (1.0 - proprio["gripper_open"]).astype(np.float32)
    out["libero_state"] = np.concatenate(
        [pose[:, :3], math3d.xyzw_to_axis_angle_f32(pose[:, 3:]),
         proprio["gripper_joint_positions"]],
        axis=1).astype(np.float32)
    wxyz = np.asarray(pose[:, [6, 3, 4, 5]], np.float64)
    out["xicm_state"] = np.concatenate(
        [np.asarray(pose[:, :3], np.float64), math3d.quat_to_euler_xyz(wxyz),
         np.asarray(proprio["gripper_open"], np.float64).reshape(-1, 1)], axis=1)
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
    out: dict[str, Any] = dict(adapter.constants)
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


# ---- answer -> key actions ----------------------------------------------------------------
def parse_rows(adapter: Adapter, answer: Any) -> list[Row]:
    """The rows of the answer to execute, in order (``execute`` of them from
    ``action_index`` on, fewer when the chunk is shorter; none for an empty chunk), each
    (position (3,), quaternion wxyz (4,), open amount).  Raises BadAnswer on anything
    that is not such a chunk."""
    if adapter.action_key is None:
        chunk = answer
    elif isinstance(answer, Mapping) and adapter.action_key in answer:
        chunk = answer[adapter.action_key]
    else:
        keys = sorted(map(str, answer)) if isinstance(answer, Mapping) else type(answer).__name__
        raise BadAnswer(f"answer has no {adapter.action_key!r} (got {keys})")
    what = "the answer" if adapter.action_key is None else repr(adapter.action_key)
    if isinstance(chunk, (str, bytes, Mapping)):
        raise BadAnswer(f"{what} is a {type(chunk).__name__}, not an action array")
    try:
        actions = np.asarray(chunk, np.float64)
    except (TypeError, ValueError) as e:
        raise BadAnswer(f"{what} is not a numeric array: {e}") from None
    width = adapter.row_width
    if actions.ndim == 1:
        actions = actions[None]
    if actions.ndim != 2 or actions.shape[-1] < width:
        raise BadAnswer(f"{what} has shape {actions.shape}; expected ({width},) or (H, >={width}): "
                        f"{_layout(adapter)}")
    if len(actions) == 0:
        return []
    if adapter.action_index >= len(actions):
        raise BadAnswer(f"action_index {adapter.action_index} outside a chunk of "
                        f"{len(actions)}")
    rows = actions[adapter.action_index:adapter.action_index + adapter.execute, :width]
    if not np.isfinite(rows).all():
        raise BadAnswer(f"non-finite action {rows.tolist()}")
    quats = rotation_to_quat(adapter, rows[:, 3:width - 1])
    grips = rows[:, width - 1]
    if adapter.gripper_threshold is not None:
        grips = (grips >= adapter.gripper_threshold).astype(np.float64)
    else:
        grips = np.clip(grips, 0.0, 1.0)
    if adapter.gripper == "closed":
        grips = 1.0 - grips
    return [(rows[i, :3], quats[i], float(grips[i])) for i in range(len(rows))]


def parse_action(adapter: Adapter, answer: Any) -> Row | None:
    """The first row `parse_rows` gives (a delta when the adapter is relative); None for
    an empty chunk."""
    rows = parse_rows(adapter, answer)
    return rows[0] if rows else None


def rotation_to_quat(adapter: Adapter, rot: np.ndarray) -> np.ndarray:
    """Rotation columns (N, ROTATIONS[adapter.rotation]) -> unit quaternions wxyz (N, 4)."""
    if adapter.rotation == "quat":
        quat = rot if adapter.quat_order == "wxyz" else rot[:, [3, 0, 1, 2]]
        norm = np.linalg.norm(quat, axis=-1, keepdims=True)
        if (norm < 1e-6).any():
            raise BadAnswer("zero quaternion")
        # leave unit quaternions bit-exact
        return np.where(np.abs(norm - 1.0) > 1e-4, quat / norm, quat)
    if adapter.rotation == "euler":
        return math3d.euler_xyz_to_quat(rot)
    if adapter.rotation == "axis_angle":
        return math3d.rotvec_to_quat(rot)
    a1, a2 = rot[:, :3], rot[:, 3:6]
    n1 = np.linalg.norm(a1, axis=-1, keepdims=True)
    ortho = a2 - np.sum(a1 * a2, axis=-1, keepdims=True) * a1 / np.maximum(n1, 1e-12) ** 2
    if (n1 < 1e-6).any() or (np.linalg.norm(ortho, axis=-1) < 1e-6 * n1[:, 0]).any():
        raise BadAnswer("degenerate 6-D rotation (a zero column or parallel columns)")
    return np.asarray(math3d.mat_to_quat(math3d.rot6d_to_mat(rot)), np.float64)


def apply_row(adapter: Adapter, row: Row, gripper_pose: np.ndarray) -> Row:
    """The key action of `row`: itself, or for a relative adapter the delta applied to
    the current tip pose `gripper_pose` (x y z qx qy qz qw, world frame)."""
    if not adapter.relative:
        return row
    pose = np.asarray(gripper_pose, np.float64)
    delta_pos, delta_quat, grip = row
    pos, quat = math3d.apply_delta(pose[:3], pose[[6, 3, 4, 5]], delta_pos,
                                   np.asarray(delta_quat, np.float64))
    return pos, quat, grip


def _layout(adapter: Adapter) -> str:
    rot = {"quat": f"quaternion {adapter.quat_order}", "euler": "Euler xyz (radians)",
           "axis_angle": "rotation vector", "rot6d": "6-D rotation (two matrix columns)"}
    kind = "delta " if adapter.relative else ""
    return f"{kind}xyz, {kind}{rot[adapter.rotation]}, gripper"
