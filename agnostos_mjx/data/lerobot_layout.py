"""What the LeRobot export's rows hold: the state layouts (``--state``), the action layout
(``--rotation``), the feature dictionary of ``meta/info.json`` and the statistics of
``meta/stats.json`` / the per-episode stats.  Pure numpy; the file layout is
data/lerobot.py.

State layouts (``observation.state``, float32, per-dimension ``names`` in info.json):

* ``rlbench`` (8): RLBench's ``gripper_pose`` x y z qx qy qz qw (world frame, the
  quaternion scalar-last as observed) and ``gripper_open`` (1.0 open / 0.0 closed): what
  our evaluator sends as ``gripper_pose`` / ``gripper_open`` (remote/adapter.py).
* ``libero`` (8): the gripper position x y z, its orientation as an axis-angle vector
  ax ay az (angle in [0, pi]) and the two finger joint positions (metres): LIBERO's /
  openpi's ``observation/state``, bit-identical to the adapter's ``libero_state``.
* ``xicm`` (7): x y z, extrinsic x-y-z Euler angles rx ry rz (radians, scipy's 'xyz') and
  gripper_open: the state of X-ICM's ``custom_agent.py`` (AGNOSTOS's VLA harness).

Action (``action``, float32): the absolute world-frame gripper (tip) target x y z, its
orientation in ``--rotation`` (data/rotations.py: quat = qx qy qz qw with qw >= 0, euler =
rx ry rz, axis_angle = ax ay az, rot6d = r11 r21 r31 r12 r22 r32), then ``gripper``, an
open amount in [0, 1] (1 open).  What it is per frame is data/lerobot.py's docstring.

Statistics (LeRobot's keys, src/lerobot/datasets/compute_stats.py): per feature ``min``,
``max``, ``mean``, ``std`` (population), ``count`` (frames) and the quantiles ``q01``,
``q10``, ``q50``, ``q90``, ``q99``.  Vectors: per dimension, exact (numpy's linear
quantiles).  Images: per channel, shape (3, 1, 1), pixel values / 255 in [0, 1], exact
over every pixel of every frame from 256-bin histograms (quantile = the smallest value
whose cumulative share reaches q); LeRobot samples and downsamples images and bins
vectors into 5000-bin histograms, so its figures are approximations of these.
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.data.rotations import ROTATION_NAMES, check_rotation, from_quat
from agnostos_mjx.sim.math3d import xyzw_to_axis_angle_f32

STATE_LAYOUTS = ("rlbench", "libero", "xicm")
STATE_NAMES: dict[str, tuple[str, ...]] = {
    "rlbench": ("x", "y", "z", "qx", "qy", "qz", "qw", "gripper_open"),
    "libero": ("x", "y", "z", "ax", "ay", "az", "finger_joint1", "finger_joint2"),
    "xicm": ("x", "y", "z", "rx", "ry", "rz", "gripper_open"),
}
STATE_DOCS = {
    "rlbench": "gripper_pose x y z qx qy qz qw (world frame, scalar-last quaternion as "
               "observed) + gripper_open (1 open, 0 closed)",
    "libero": "gripper position x y z + axis-angle ax ay az (angle in [0, pi]) + the two "
              "finger joint positions (m)",
    "xicm": "x y z + extrinsic x-y-z Euler angles rx ry rz (rad, scipy 'xyz') + gripper_open",
}
ROTATION_DOCS = {
    "quat": "unit quaternion qx qy qz qw, qw >= 0",
    "euler": "extrinsic x-y-z Euler angles rx ry rz (rad, scipy 'xyz')",
    "axis_angle": "rotation vector ax ay az = axis * angle, angle in [0, pi]",
    "rot6d": "first two rotation-matrix columns r11 r21 r31 r12 r22 r32",
}
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
QUANTILE_KEYS = tuple(f"q{round(q * 100):02d}" for q in QUANTILES)
STAT_KEYS = ("min", "max", "mean", "std", "count") + QUANTILE_KEYS
# LeRobot's DEFAULT_FEATURES (src/lerobot/utils/constants.py), appended after ours.
DEFAULT_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}
IMAGE_PREFIX = "observation.images."


def check_state(layout: str) -> str:
    if layout not in STATE_LAYOUTS:
        raise ValueError(f"unknown state layout {layout!r}; choose from {', '.join(STATE_LAYOUTS)}")
    return layout


def action_names(rotation: str) -> tuple[str, ...]:
    return ("x", "y", "z", *ROTATION_NAMES[check_rotation(rotation)], "gripper")


def state_vector(layout: str, gripper_pose: np.ndarray, gripper_open: np.ndarray,
                 fingers: np.ndarray) -> np.ndarray:
    """(T, D) float32 state rows from per-frame gripper_pose (T, 7) x y z qx qy qz qw,
    gripper_open (T,) and the finger joints (T, 2), as the observation holds them."""
    pose = np.asarray(gripper_pose, np.float32)
    grip = np.asarray(gripper_open, np.float32).reshape(-1, 1)
    if check_state(layout) == "rlbench":
        return np.concatenate([pose, grip], 1)
    if layout == "libero":  # exactly the adapter's libero_state (float32 arithmetic)
        return np.concatenate([pose[:, :3], xyzw_to_axis_angle_f32(pose[:, 3:]),
                               np.asarray(fingers, np.float32)], 1).astype(np.float32)
    euler = from_quat(pose[:, 3:].astype(np.float64), "euler")
    return np.concatenate([pose[:, :3], euler.astype(np.float32), grip], 1)


def action_vector(rotation: str, pose: np.ndarray, gripper: np.ndarray) -> np.ndarray:
    """(T, D) float32 action rows from targets x y z qx qy qz qw (T, 7) and open amounts."""
    pose = np.asarray(pose, np.float64)
    rot = from_quat(pose[:, 3:], rotation)
    return np.concatenate([pose[:, :3], rot, np.asarray(gripper, np.float64).reshape(-1, 1)],
                          1).astype(np.float32)


def features(cameras, height: int, width: int, state: str, rotation: str,
             video_info: dict | None = None) -> dict:
    """info.json's ``features``: cameras, state, action, then LeRobot's default columns.
    `video_info` (per-camera ``info`` dict) makes the cameras ``video`` features."""
    out: dict = {}
    for cam in cameras:
        out[IMAGE_PREFIX + cam] = {"dtype": "video" if video_info else "image",
                                   "shape": [height, width, 3],
                                   "names": ["height", "width", "channels"]}
        if video_info:
            out[IMAGE_PREFIX + cam]["info"] = dict(video_info)
    names = list(STATE_NAMES[check_state(state)])
    out["observation.state"] = {"dtype": "float32", "shape": [len(names)], "names": names}
    names = list(action_names(rotation))
    out["action"] = {"dtype": "float32", "shape": [len(names)], "names": names}
    out.update({k: dict(v) for k, v in DEFAULT_FEATURES.items()})
    return out


def hf_features(feats: dict) -> dict:
    """The Hugging Face ``datasets`` feature dict of the data parquet's columns (its schema
    metadata ``huggingface``), as LeRobot's ``get_hf_features_from_features`` builds it:
    Image for images, Value for shape (1,), Sequence(length) for vectors - ``Sequence``,
    which datasets 3.x (openpi's 3.6.0) and 4.x both read, not 4.x's ``List``."""
    out = {}
    for key, ft in feats.items():
        if ft["dtype"] == "video":
            continue
        if ft["dtype"] == "image":
            out[key] = {"_type": "Image"}
        elif list(ft["shape"]) == [1]:
            out[key] = {"dtype": ft["dtype"], "_type": "Value"}
        else:
            out[key] = {"feature": {"dtype": ft["dtype"], "_type": "Value"},
                        "length": int(ft["shape"][0]), "_type": "Sequence"}
    return out


# ---- statistics -------------------------------------------------------------------------------
def vector_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """Stats of (T,) or (T, D) values; scalars get shape (1,) as LeRobot's."""
    v = np.asarray(values, np.float64)
    v = v.reshape(len(v), -1)
    out = {"min": v.min(0), "max": v.max(0), "mean": v.mean(0), "std": v.std(0),
           "count": np.array([len(v)])}
    for key, q in zip(QUANTILE_KEYS, np.quantile(v, QUANTILES, axis=0)):
        out[key] = q
    return out


def image_histogram(images: np.ndarray) -> np.ndarray:
    """(T, H, W, 3) uint8 -> (3, 256) pixel counts per channel."""
    flat = np.asarray(images, np.uint8).reshape(-1, 3)
    return np.stack([np.bincount(flat[:, c], minlength=256) for c in range(3)]).astype(np.int64)


def histogram_stats(hist: np.ndarray, frames: int) -> dict[str, np.ndarray]:
    """Per-channel stats, shape (3, 1, 1) in [0, 1], from (3, 256) pixel counts; count =
    frames (as LeRobot counts images)."""
    hist = np.asarray(hist, np.float64)
    values = np.arange(256) / 255.0
    total = hist.sum(1)
    mean = hist @ values / total
    var = np.maximum(hist @ values**2 / total - mean**2, 0.0)
    seen = hist > 0
    out = {"min": values[np.argmax(seen, 1)], "max": values[255 - np.argmax(seen[:, ::-1], 1)],
           "mean": mean, "std": np.sqrt(var)}
    cum = np.cumsum(hist, 1) / total[:, None]
    quantiles = {k: values[np.array([np.searchsorted(c, q - 1e-12) for c in cum])]
                 for k, q in zip(QUANTILE_KEYS, QUANTILES)}
    out = {k: v.reshape(3, 1, 1) for k, v in {**out, **quantiles}.items()}
    out["count"] = np.array([int(frames)])
    return {k: out[k] for k in STAT_KEYS}


def jsonable(stats: dict) -> dict:
    """{feature: {stat: array}} -> nested lists / ints (json.dump-able)."""
    return {f: {k: np.asarray(v).tolist() for k, v in s.items()} for f, s in stats.items()}
