"""What every renderer shares: the images it returns (`CameraImages`), camera names and
clipping planes of a model, and the headless-GL install hint."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import jax
import mujoco

GL_INSTALL_HINT = (
    "Install a headless OpenGL for mujoco.Renderer. Debian/Ubuntu, EGL (preferred): "
    "apt-get install -y libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libgles2 "
    "(list in .ci/apt-packages.txt) and set MUJOCO_GL=egl; or OSMesa: "
    "apt-get install -y libosmesa6 and set MUJOCO_GL=osmesa."
)


def gl_backend() -> str:
    """The MUJOCO_GL backend this process uses ('' means mujoco's default, GLFW)."""
    return os.environ.get("MUJOCO_GL", "").strip().lower()


def camera_names(model: mujoco.MjModel) -> tuple[str, ...]:
    """All camera names of a model, in camera-id order."""
    return tuple(
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) or f"<camera {i}>"
        for i in range(model.ncam)
    )


def unknown_camera(model: mujoco.MjModel, camera: str) -> ValueError:
    return ValueError(f"unknown camera {camera!r}; model cameras: {list(camera_names(model))}")


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class CameraImages:
    """One camera's images of B worlds and the pose they were taken from.

    Both renderers return this, numpy (CPU) or JAX device arrays (Warp), so everything
    built on top (point clouds, RLBench observations) is written once.
    """

    pos: Any  # (B, 3) camera position in the world
    mat: Any  # (B, 3, 3) MuJoCo camera axes as columns: x right, y up, looking along -z
    rgb: Any = None  # (B, H, W, 3) uint8
    depth: Any = None  # (B, H, W) float32 metres along the optical axis; `far` where empty
    segmentation: Any = None  # (B, H, W) int32 geom id, -1 where no geom


def clip_planes(model: mujoco.MjModel) -> tuple[float, float]:
    """(near, far) clipping distances in metres, as both renderers use them."""
    extent = float(model.stat.extent)
    return float(model.vis.map.znear) * extent, float(model.vis.map.zfar) * extent
