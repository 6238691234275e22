"""RLBench's episode folder format, pure: where an episode lives, the names of its files,
the image encodings (depth and masks as 24-bit integers in PNG pixels) and the
``Observation`` a frame becomes.  Writing and reading a folder is data/episode_files.py;
the pickles are data/rlbench_demo.py; the folder layout is described in data/export.py."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from agnostos_mjx.data.rlbench_demo import Observation

# RLBench's five cameras, in the order its misc dict lists them; get_stored_demos needs the
# rgb and depth folders of all five.
RLBENCH_CAMERAS = ("left_shoulder", "right_shoulder", "overhead", "front", "wrist")
DEPTH_SCALE = 2**24 - 1  # RLBench's DEPTH_SCALE
SUMS = "SHA256SUMS"
KEYFRAMES = "keyframes.json"  # dense episodes only: indices of the keyframes among the frames
FORMAT = 2  # 1: low_dim_obs.npz and depth with R as the low byte (not RLBench's)
# Observation fields stacked per frame by read_episode (besides misc's camera keys).
LOW_DIM_FIELDS = ("gripper_pose", "gripper_open", "joint_positions", "joint_velocities",
                  "joint_forces", "gripper_matrix", "gripper_joint_positions",
                  "gripper_touch_forces", "task_low_dim_state", "ignore_collisions")


def episode_dir(out: Path, task: str, index: int) -> Path:
    return out / task / "all_variations" / "episodes" / f"episode{index}"


def is_complete(path: Path) -> bool:
    return (path / SUMS).exists()


def int_to_rgb(values: np.ndarray) -> np.ndarray:
    """Non-negative integers < 2^24 -> uint8 RGB with R the low byte: RLBench's mask
    encoding (``rgb_handles_to_mask``: R + 256 G + 65536 B)."""
    v = np.asarray(values, np.int64)
    return np.stack([v & 255, (v >> 8) & 255, (v >> 16) & 255], -1).astype(np.uint8)


def rgb_to_int(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, np.int64)
    return rgb[..., 0] | (rgb[..., 1] << 8) | (rgb[..., 2] << 16)


def encode_depth(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """Metres -> RLBench depth PNG pixels: ``float_array_to_rgb_image((d - near) / (far -
    near), DEPTH_SCALE)``, a 24-bit integer with R the HIGH byte (unlike masks)."""
    unit = (np.asarray(depth, np.float64) - near) / (far - near)
    return int_to_rgb(np.clip(np.floor(unit * DEPTH_SCALE + 0.5), 0, DEPTH_SCALE))[..., ::-1]


def decode_depth(rgb: np.ndarray, near: float, far: float) -> np.ndarray:
    """RLBench depth PNG pixels -> metres (``image_to_float_array``, then near/far)."""
    unit = rgb_to_int(np.asarray(rgb)[..., ::-1]) / DEPTH_SCALE
    return (near + unit * (far - near)).astype(np.float32)


def quat_to_matrix(pose: np.ndarray) -> np.ndarray:
    """RLBench gripper pose (x y z qx qy qz qw) -> its 4x4 ``gripper_matrix``."""
    x, y, z, w = np.asarray(pose[3:], np.float64) / np.linalg.norm(pose[3:])
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = pose[:3]
    return m


def rlbench_observation(frame: dict, cameras: Sequence[str]) -> Observation:
    """One frame (RLBenchObservation.world dict, plus ``task_low_dim_state``) -> the
    ``Observation`` that RLBench's dataset generator pickles: images None, low-dim fields as
    float64 arrays; fields we do not simulate (joint_forces, gripper_touch_forces) are zeros
    and ignore_collisions is 0 (our key actions carry no collision flag)."""
    f64 = lambda v: np.array(v, np.float64)  # noqa: E731
    misc: dict = {}
    for cam in sorted(cameras, key=lambda c: (RLBENCH_CAMERAS + (c,)).index(c)):
        m = frame["misc"]
        misc[f"{cam}_camera_extrinsics"] = f64(m[f"{cam}_camera_extrinsics"])
        misc[f"{cam}_camera_intrinsics"] = f64(m[f"{cam}_camera_intrinsics"])
        misc[f"{cam}_camera_near"] = float(m[f"{cam}_camera_near"])
        misc[f"{cam}_camera_far"] = float(m[f"{cam}_camera_far"])
    pose = f64(frame["gripper_pose"])
    joints = f64(frame["joint_positions"])
    return Observation(
        joint_velocities=f64(frame["joint_velocities"]), joint_positions=joints,
        joint_forces=f64(frame.get("joint_forces", np.zeros_like(joints))),
        gripper_open=float(frame["gripper_open"]), gripper_pose=pose,
        gripper_matrix=quat_to_matrix(pose),
        gripper_joint_positions=f64(frame["gripper_joint_positions"]),
        gripper_touch_forces=f64(frame.get("gripper_touch_forces", np.zeros(6))),
        task_low_dim_state=f64(frame.get("task_low_dim_state", np.zeros(0))),
        ignore_collisions=np.array(float(frame.get("ignore_collisions", 0.0))), misc=misc)
