"""RLBench-style observations for learned policies (VLAs): cameras and proprioception.

A policy that consumes images declares what it needs with an :class:`ObservationSpec`
(cameras, resolution, modalities) as its ``observation_spec``; the round it sees then renders
``episodes.observe(env, spec)`` on first use of ``view.observation`` (see
``policies.base.Round``).  Nothing is rendered for policies that declare nothing (oracle,
X-ICM with ground-truth objects, retrieval).

Per requested camera an observation holds (B worlds, H x W pixels):

* ``rgb`` uint8 (B, H, W, 3); ``depth`` float32 (B, H, W), metres along the optical axis,
  clipped to RLBench's far plane of that camera; ``point_cloud`` float32 (B, H, W, 3) in the
  world frame; ``segmentation`` int32 (B, H, W), the MuJoCo geom id seen by each pixel
  (-1: none), named by :class:`SceneLabels` (``geom_names`` and the task's named
  ``objects`` -> geom ids, X-ICM's names);
* ``intrinsics`` (3, 3) and ``extrinsics`` (B, 4, 4), camera-to-world, in RLBench's
  (PyRep's) convention: the camera looks along its +z, its +x points to the image's left
  and +y up, and the focal lengths are negative: ``K = [[-f, 0, cx], [0, -f, cy], [0, 0, 1]]``
  with ``f = H / (2 tan(fovy / 2))``.  RLBench's ``pointcloud_from_depth_and_camera_params``
  therefore rebuilds our point clouds exactly.  Pixel centres sit at integer indices, so
  ``cx = (W - 1) / 2`` (RLBench writes W / 2, half a pixel off for a pinhole renderer).

and per world ``gripper_pose`` (x, y, z, qx, qy, qz, qw: RLBench's order, the quaternion
scalar-last; our KeyActions use w first), ``gripper_open`` (1.0 open / 0.0 closed, the PerAct
threshold), ``joint_positions`` and ``joint_velocities`` (7 arm joints),
``gripper_joint_positions`` (the two fingers, metres) and the ``instructions``.

Rendering runs where the physics runs: MuJoCo's OpenGL renderer over all worlds on a CPU
(no multisampling: one sample per pixel, as MJX-Warp and ~3x faster on llvmpipe; the worlds
split into contiguous chunks over ``render.render_threads()`` threads, each with its own GL
context: the usable cores up to 8, or ``AGNOSTOS_RENDER_THREADS``), MJX-Warp's
batch ray-tracer on a GPU (JAX device arrays unless the spec asks for numpy).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from agnostos_mjx.physics import RENDERERS

if TYPE_CHECKING:
    from agnostos_mjx.render import CameraImages
    from agnostos_mjx.sim.world import SceneModel

CAMERAS = ("front", "left_shoulder", "right_shoulder", "overhead", "wrist")
MODALITIES = ("rgb", "depth", "point_cloud", "segmentation")
# RLBench's clipping planes per camera (spec section 2): depth saturates at `far` there.
RLBENCH_NEAR_FAR: dict[str, tuple[float, float]] = {
    "front": (0.01, 4.5), "left_shoulder": (0.01, 3.2), "right_shoulder": (0.01, 3.2),
    "overhead": (0.01, 3.3), "wrist": (0.01, 3.5),
}
# MuJoCo camera axes (x right, y up, looking along -z) -> RLBench's (x left, y up, +z).
_TO_RLBENCH = np.diag([-1.0, 1.0, -1.0])


@dataclass(frozen=True)
class ObservationSpec:
    """What a policy wants to see; only this is rendered.

    ``renderer``: auto (the run's ``--renderer``, else MJX-Warp wherever there is a GPU
    with warp-lang, else CPU), cpu or warp.  ``numpy``: host arrays; False keeps Warp's images on the device (JAX arrays).
    """

    cameras: tuple[str, ...] = ("front",)
    height: int = 128
    width: int = 128
    modalities: tuple[str, ...] = ("rgb",)
    renderer: str = "auto"
    numpy: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "modalities", tuple(self.modalities))
        unknown = set(self.modalities) - set(MODALITIES)
        if unknown:
            raise ValueError(f"unknown modalities {sorted(unknown)}; choose from {MODALITIES}")
        if not self.cameras or len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"cameras must be distinct and non-empty, got {self.cameras}")
        unknown = [c for c in self.cameras if c not in CAMERAS]
        if unknown:  # else the render fails later, in every task
            raise ValueError(f"unknown cameras {', '.join(map(repr, unknown))}; the scene's "
                             f"cameras are {', '.join(CAMERAS)}")
        if self.renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {self.renderer!r}")
        if self.height < 1 or self.width < 1:
            raise ValueError(f"bad resolution {self.height}x{self.width}")

    def wants(self, modality: str) -> bool:
        return modality in self.modalities

    @property
    def needs_depth(self) -> bool:
        return self.wants("depth") or self.wants("point_cloud")


@dataclass(frozen=True, eq=False)
class SceneLabels:
    """Names of segmentation ids: geom id -> name, and each of the task's named objects
    (X-ICM's display names) -> the geom ids that make it up."""

    geom_names: tuple[str, ...]
    objects: Mapping[str, tuple[int, ...]]

    @functools.cached_property
    def _lut(self) -> np.ndarray:
        lut = np.full(len(self.geom_names) + 1, -1, np.int32)
        for k, ids in enumerate(self.objects.values()):
            lut[np.asarray(ids, int) + 1] = k
        return lut

    def object_segmentation(self, segmentation: Any) -> np.ndarray:
        """Geom-id segmentation -> index into ``objects`` (its order), -1 elsewhere."""
        return self._lut[np.asarray(segmentation) + 1]

    def mask(self, segmentation: Any, name: str) -> np.ndarray:
        """Where the named object is seen."""
        return np.isin(np.asarray(segmentation), self.objects[name])


@dataclass(frozen=True)
class CameraObservation:
    """One camera of B worlds; modalities not requested are None (shapes: module docs)."""

    intrinsics: np.ndarray  # (3, 3)
    extrinsics: Any  # (B, 4, 4) camera-to-world
    near: float
    far: float
    rgb: Any = None
    depth: Any = None
    point_cloud: Any = None
    segmentation: Any = None


@dataclass(frozen=True)
class RLBenchObservation:
    """Observation of B worlds at one key-action step (fields: module docs)."""

    cameras: Mapping[str, CameraObservation]
    gripper_pose: np.ndarray  # (B, 7) x y z qx qy qz qw
    gripper_open: np.ndarray  # (B,) float32 1 / 0
    joint_positions: np.ndarray  # (B, 7)
    joint_velocities: np.ndarray  # (B, 7)
    gripper_joint_positions: np.ndarray  # (B, 2)
    instructions: tuple[str, ...]
    labels: SceneLabels = field(repr=False)

    @property
    def batch(self) -> int:
        return len(self.gripper_pose)

    def world(self, i: int) -> dict[str, Any]:
        """World i as RLBench's ``Observation`` fields (``front_rgb``, ``front_mask``,
        ..., ``misc`` with ``<camera>_camera_intrinsics/extrinsics/near/far``)."""
        out: dict[str, Any] = {}
        misc: dict[str, Any] = {}
        for name, cam in self.cameras.items():
            for key, value in (("rgb", cam.rgb), ("depth", cam.depth),
                               ("point_cloud", cam.point_cloud), ("mask", cam.segmentation)):
                if value is not None:
                    out[f"{name}_{key}"] = np.asarray(value[i])
            misc[f"{name}_camera_intrinsics"] = cam.intrinsics
            misc[f"{name}_camera_extrinsics"] = np.asarray(cam.extrinsics[i])
            misc[f"{name}_camera_near"], misc[f"{name}_camera_far"] = cam.near, cam.far
        out.update(gripper_pose=self.gripper_pose[i], gripper_open=float(self.gripper_open[i]),
                   joint_positions=self.joint_positions[i],
                   joint_velocities=self.joint_velocities[i],
                   gripper_joint_positions=self.gripper_joint_positions[i],
                   instruction=self.instructions[i], misc=misc)
        return out


# ---- camera geometry (pure; numpy or jax.numpy through `xp`) ------------------------------
def intrinsics(fovy_deg: float, height: int, width: int) -> np.ndarray:
    """RLBench-convention pinhole matrix (negative focal lengths) of a MuJoCo camera."""
    f = 0.5 * height / np.tan(np.deg2rad(fovy_deg) / 2.0)
    return np.array([[-f, 0.0, (width - 1) / 2.0], [0.0, -f, (height - 1) / 2.0],
                     [0.0, 0.0, 1.0]], np.float32)


def camera_to_world(pos: Any, mat: Any, xp: Any = np) -> Any:
    """(..., 4, 4) RLBench extrinsics from MuJoCo camera poses pos (..., 3), mat (..., 3, 3)."""
    rot = xp.asarray(mat) @ xp.asarray(_TO_RLBENCH, dtype=xp.asarray(mat).dtype)
    top = xp.concatenate([rot, xp.asarray(pos)[..., :, None]], axis=-1)
    bottom = xp.broadcast_to(xp.asarray([0.0, 0.0, 0.0, 1.0], top.dtype), (*top.shape[:-2], 1, 4))
    return xp.concatenate([top, bottom], axis=-2).astype(xp.float32)


def point_cloud(depth: Any, intrinsic: np.ndarray, extrinsics: Any, xp: Any = np) -> Any:
    """Back-project depth (..., H, W) with RLBench-convention K and extrinsics (..., 4, 4)
    -> world points (..., H, W, 3)."""
    h, w = depth.shape[-2:]
    v, u = np.meshgrid(np.arange(h, dtype=np.float32), np.arange(w, dtype=np.float32),
                       indexing="ij")
    k = np.asarray(intrinsic, np.float32)
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1)
    rot = extrinsics[..., :3, :3].astype(xp.float32)
    t = extrinsics[..., None, :3, 3].astype(xp.float32)
    # (..., HW, 3) = rays (HW, 3) @ R^T: one batched matrix product (BLAS), not an einsum.
    world_rays = xp.asarray(rays.reshape(-1, 3)) @ xp.swapaxes(rot, -1, -2)
    points = depth.reshape(*depth.shape[:-2], -1, 1).astype(xp.float32) * world_rays + t
    return points.reshape(*depth.shape, 3)


def project(points: np.ndarray, intrinsic: np.ndarray, extrinsic: np.ndarray) -> np.ndarray:
    """World points (..., 3) -> pixel coordinates (..., 2) as (column u, row v)."""
    rot, t = extrinsic[:3, :3], extrinsic[:3, 3]
    cam = (np.asarray(points) - t) @ rot
    uv = cam[..., :2] / cam[..., 2:3] * np.diag(intrinsic)[:2] + intrinsic[:2, 2]
    return uv


# ---- scene labels --------------------------------------------------------------------------
def _frame_body(model: mujoco.MjModel, frame: str) -> tuple[int, np.ndarray]:
    """(body id, frame position in that body) of an observed frame (site or body)."""
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, frame)
    if site >= 0:
        return int(model.site_bodyid[site]), model.site_pos[site].copy()
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, frame), np.zeros(3)


@functools.cache
def scene_labels(scene: SceneModel) -> SceneLabels:
    """Segmentation names of a task scene.

    A named object is the rendered geoms (groups 0-2) of the body carrying its frame, not
    of the bodies below it (X-ICM names single CoppeliaSim shapes: "drawer" is the frame
    without its drawers).  When several named frames share one body, each geom goes to the
    frame nearest to it, so the objects stay disjoint."""
    m = scene.model
    names = []
    for g in range(m.ngeom):
        body = m.body(int(m.geom_bodyid[g])).name or "world"
        names.append(m.geom(g).name or f"{body}#{g}")
    frames = {name: _frame_body(m, frame) for name, frame in scene.task.objects.items()}
    objects: dict[str, list[int]] = {name: [] for name in frames}
    rendered = [g for g in range(m.ngeom) if m.geom_group[g] <= 2]
    for g in rendered:
        owners = [n for n, (b, _) in frames.items() if b == int(m.geom_bodyid[g])]
        if owners:
            dist = [np.linalg.norm(m.geom_pos[g] - frames[n][1]) for n in owners]
            objects[owners[int(np.argmin(dist))]].append(g)
    return SceneLabels(tuple(names), {n: tuple(ids) for n, ids in objects.items()})


CAMERA_ARRAYS = ("extrinsics", "rgb", "depth", "point_cloud", "segmentation")


def camera_constants(model: mujoco.MjModel, spec: ObservationSpec
                     ) -> dict[str, tuple[np.ndarray, float, float]]:
    """Per camera of `spec`: intrinsics, near, far."""
    out = {}
    for name in spec.cameras:
        cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
        near, far = RLBENCH_NEAR_FAR.get(name, (0.01, 4.5))
        out[name] = (intrinsics(float(model.cam_fovy[cam_id]), spec.height, spec.width), near, far)
    return out


def camera_observation(images: CameraImages, intrinsic: np.ndarray, near: float, far: float,
                       spec: ObservationSpec, xp: Any = np) -> CameraObservation:
    """Rendered images -> one camera's observation (depth clipped, point cloud built)."""
    extrinsics = camera_to_world(images.pos, images.mat, xp)
    depth = None if images.depth is None else xp.minimum(images.depth, far).astype(xp.float32)
    cloud = point_cloud(depth, intrinsic, extrinsics, xp) if spec.wants("point_cloud") else None
    return CameraObservation(
        intrinsics=intrinsic, extrinsics=extrinsics, near=near, far=far,
        rgb=images.rgb if spec.wants("rgb") else None,
        depth=depth if spec.wants("depth") else None, point_cloud=cloud,
        segmentation=images.segmentation if spec.wants("segmentation") else None)


# ---- X-ICM's object positions from segmented point clouds (xicm_reference.md §3.4) ------
def segmented_object_positions(observation: RLBenchObservation, world: int,
                               cameras: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """Per named object: the mean of its segmented points per camera, averaged over the
    cameras that see it (unweighted); objects no camera sees are omitted."""
    names = cameras or tuple(observation.cameras)
    out = {}
    for name, ids in observation.labels.objects.items():
        means = []
        for cam_name in names:
            cam = observation.cameras[cam_name]
            if cam.segmentation is None or cam.point_cloud is None:
                raise ValueError(f"camera {cam_name} lacks segmentation or point_cloud")
            mask = np.isin(np.asarray(cam.segmentation[world]), ids)
            if mask.any():
                means.append(np.asarray(cam.point_cloud[world])[mask].mean(axis=0))
        if means:
            out[name] = np.mean(means, axis=0)
    return out
