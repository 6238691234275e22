"""`CpuRenderer`: native ``mujoco.Renderer``-style offscreen OpenGL rendering (EGL or
OSMesa), one world at a time, RGB, depth and segmentation of any cameras."""

from __future__ import annotations

import copy
import importlib
from collections.abc import Sequence
from typing import Any, Self

import mujoco
import numpy as np

from agnostos_mjx.render.common import (
    GL_INSTALL_HINT,
    CameraImages,
    camera_names,
    clip_planes,
    gl_backend,
    unknown_camera,
)


def _gl_context_module() -> Any:
    """mujoco's gl_context module (its location moved in mujoco 4)."""
    try:
        from mujoco.rendering.classic import gl_context  # mujoco >= 4
    except ImportError:
        from mujoco import gl_context  # older layout
    return gl_context


def _fix_late_gl_context() -> None:
    """Point mujoco at the MUJOCO_GL backend if mujoco was imported before it was set.

    mujoco binds its offscreen GL context class at import; when another module imported
    mujoco first without MUJOCO_GL, that class is GLFW's (needs a display). Swapping the class
    in mujoco's gl_context module is what ``mujoco.Renderer`` looks up when it is built.
    """
    want = gl_backend()
    if want not in ("egl", "osmesa"):
        return
    gl_context = _gl_context_module()
    current = getattr(gl_context, "GLContext", None)
    if current is not None and current.__module__ == f"mujoco.{want}":
        return
    try:
        gl_context.GLContext = importlib.import_module(f"mujoco.{want}").GLContext
    except (ImportError, OSError, AttributeError) as err:
        raise RuntimeError(
            f"cannot load mujoco's {want} GL backend: {err}. {GL_INSTALL_HINT}"
        ) from err


def _linear_depth(buffer: np.ndarray, near: float, far: float) -> np.ndarray:
    """OpenGL reversed-Z depth buffer values -> metres (mujoco.Renderer's formula; float32
    keeps ~1e-7 relative precision with reversed Z, mujoco.Renderer's float64 is not needed)."""
    znear, zfar = np.float32(near), np.float32(far)
    c = np.float32(-0.5) * (-(zfar + znear) / (zfar - znear)) - np.float32(0.5)
    d = np.float32(-0.5) * (-(np.float32(2) * zfar * znear) / (zfar - znear))
    return d / (buffer + c)


class CpuRenderer:
    """Offscreen MuJoCo OpenGL renderer looping over worlds; shadows and reflections off.

    Works on a private copy of ``model`` (offscreen buffer enlarged, shadow map disabled,
    per-call ``geom_rgba`` written there and restored), so the caller's model is never touched.
    :meth:`render` gives one camera's RGB; :meth:`render_views` any cameras with RGB, depth
    and segmentation: per world the scene is built once and each camera costs one pass for
    RGB plus one (segmentation colours, depth read alongside) for depth and segmentation.
    """

    def __init__(self, model: mujoco.MjModel, width: int = 128, height: int = 128,
                 samples: int | None = None) -> None:
        """``samples``: multisampling (anti-aliasing) samples per pixel; None keeps the
        model's (4 in our scenes, what Episodes.render has always used); 0 renders one
        sample per pixel like MJX-Warp's ray tracer and ~3x faster on llvmpipe."""
        self.width, self.height = int(width), int(height)
        self._gl: Any = None
        self._con: Any = None
        m = copy.copy(model)
        m.vis.global_.offwidth = max(int(m.vis.global_.offwidth), self.width)
        m.vis.global_.offheight = max(int(m.vis.global_.offheight), self.height)
        m.vis.quality.shadowsize = 0  # the default 4096^2 shadow map costs ~20x on llvmpipe
        if samples is not None:
            m.vis.quality.offsamples = int(samples)
        self._model = m
        self._data = mujoco.MjData(m)
        self._rgba0 = m.geom_rgba.copy()
        self._mocap_pos0 = self._data.mocap_pos.copy()
        self._mocap_quat0 = self._data.mocap_quat.copy()
        self.camera_names = camera_names(m)
        self.near, self.far = clip_planes(m)
        _fix_late_gl_context()
        try:
            gl_context = _gl_context_module()
            self._gl = gl_context.GLContext(max(self.width, 1), max(self.height, 1))
            self._gl.make_current()
            self._con = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_150.value)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)
            self._con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        except Exception as err:  # GL failures surface as many exception types
            self.close()
            raise RuntimeError(
                f"no working OpenGL for MuJoCo rendering (MUJOCO_GL={gl_backend()!r}): "
                f"{type(err).__name__}: {err}. {GL_INSTALL_HINT}"
            ) from err
        self._scene = mujoco.MjvScene(m, maxgeom=10000)
        self._option = mujoco.MjvOption()
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        self._cameras: dict[int, mujoco.MjvCamera] = {}

    def camera_id(self, camera: str) -> int:
        """Camera id of a camera name; ValueError listing the model's cameras if unknown."""
        cam_id = mujoco.mj_name2id(self._model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if cam_id < 0:
            raise unknown_camera(self._model, camera)
        return cam_id

    def _camera(self, cam_id: int) -> mujoco.MjvCamera:
        if cam_id not in self._cameras:
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = cam_id
            self._cameras[cam_id] = cam
        return self._cameras[cam_id]

    def _pose(self) -> None:
        """Position stage only (what the scene needs), skipping collision and dynamics."""
        m, d = self._model, self._data
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_camlight(m, d)
        if m.nflex:
            mujoco.mj_flex(m, d)
        if m.ntendon:
            mujoco.mj_tendon(m, d)

    def render(
        self,
        qpos: np.ndarray,
        mocap_pos: np.ndarray | None,
        mocap_quat: np.ndarray | None,
        camera: str,
        geom_rgba: np.ndarray | None = None,
    ) -> np.ndarray:
        """Render ``camera`` for B worlds -> uint8 [B, H, W, 3].

        qpos [B, nq]; mocap_pos [B, nmocap, 3] and mocap_quat [B, nmocap, 4] (None: the model's
        defaults); geom_rgba [B, ngeom, 4] overrides colours per world (a geom with a material
        keeps the material colour only while its rgba is the default 0.5 0.5 0.5 1).
        """
        views = self.render_views(qpos, mocap_pos, mocap_quat, (camera,), geom_rgba)
        return views[camera].rgb

    def render_views(
        self,
        qpos: np.ndarray,
        mocap_pos: np.ndarray | None,
        mocap_quat: np.ndarray | None,
        cameras: Sequence[str],
        geom_rgba: np.ndarray | None = None,
        *,
        rgb: bool = True,
        depth: bool = False,
        segmentation: bool = False,
    ) -> dict[str, CameraImages]:
        """Render ``cameras`` for B worlds (arguments as :meth:`render`) -> camera name ->
        :class:`CameraImages` with the requested images and each world's camera pose."""
        if self._con is None:
            raise RuntimeError("CpuRenderer is closed")
        cam_ids = [self.camera_id(c) for c in cameras]
        m, d, scn, con, rect = self._model, self._data, self._scene, self._con, self._rect
        qpos = np.asarray(qpos, dtype=np.float64)
        if qpos.ndim != 2 or qpos.shape[1] != m.nq:
            raise ValueError(f"qpos must be [B, {m.nq}], got {qpos.shape}")
        nworld, h, w = qpos.shape[0], self.height, self.width
        pos = self._batched(mocap_pos, self._mocap_pos0, nworld, "mocap_pos")
        quat = self._batched(mocap_quat, self._mocap_quat0, nworld, "mocap_quat")
        rgba = None
        if geom_rgba is not None:
            rgba = self._batched(geom_rgba, self._rgba0, nworld, "geom_rgba")
        ncam = len(cam_ids)
        out_rgb = np.empty((ncam, nworld, h, w, 3), np.uint8) if rgb else None
        out_depth = np.empty((ncam, nworld, h, w), np.float32) if depth else None
        out_seg = np.empty((ncam, nworld, h, w), np.int32) if segmentation else None
        ids = np.empty((h, w, 3), np.uint8) if segmentation else None
        cam_pos = np.empty((ncam, nworld, 3))
        cam_mat = np.empty((ncam, nworld, 3, 3))
        seg_flags = (mujoco.mjtRndFlag.mjRND_SEGMENT, mujoco.mjtRndFlag.mjRND_IDCOLOR)
        self._gl.make_current()
        try:
            for i in range(nworld):
                d.qpos[:] = qpos[i]
                if m.nmocap:
                    d.mocap_pos[:] = pos[i]
                    d.mocap_quat[:] = quat[i]
                if rgba is not None:
                    m.geom_rgba[:] = rgba[i]
                self._pose()
                mujoco.mjv_updateScene(m, d, self._option, None, self._camera(cam_ids[0]),
                                       mujoco.mjtCatBit.mjCAT_ALL.value, scn)
                lut = self._segment_lut() if segmentation else None
                for c, cam_id in enumerate(cam_ids):
                    if c:
                        mujoco.mjv_updateCamera(m, d, self._camera(cam_id), scn)
                    cam_pos[c, i] = d.cam_xpos[cam_id]
                    cam_mat[c, i] = d.cam_xmat[cam_id].reshape(3, 3)
                    # Depth comes with the RGB pass unless a segmentation pass runs anyway.
                    depth_with_rgb = depth and rgb and not segmentation
                    if rgb:
                        mujoco.mjr_render(rect, scn, con)
                        mujoco.mjr_readPixels(out_rgb[c, i],
                                              out_depth[c, i] if depth_with_rgb else None, rect, con)
                    if segmentation or (depth and not rgb):
                        # Segmentation colours also give the more accurate depth (mujoco.Renderer).
                        for flag in seg_flags:
                            scn.flags[flag] = True
                        mujoco.mjr_render(rect, scn, con)
                        mujoco.mjr_readPixels(ids, out_depth[c, i] if depth else None, rect, con)
                        for flag in seg_flags:
                            scn.flags[flag] = False
                        if segmentation:
                            code = (ids[..., 0].astype(np.int32) | (ids[..., 1].astype(np.int32) << 8)
                                    | (ids[..., 2].astype(np.int32) << 16))
                            out_seg[c, i] = lut[np.minimum(code, len(lut) - 1)]
        finally:
            if rgba is not None:
                m.geom_rgba[:] = self._rgba0
        # OpenGL rows run bottom-up; images are top-down.
        flip = lambda a: None if a is None else np.ascontiguousarray(a[:, :, ::-1])  # noqa: E731
        out_rgb, out_seg = flip(out_rgb), flip(out_seg)
        if depth:
            out_depth = _linear_depth(out_depth[:, :, ::-1], self.near, self.far)
        return {
            name: CameraImages(
                pos=cam_pos[c], mat=cam_mat[c],
                rgb=None if out_rgb is None else out_rgb[c],
                depth=None if out_depth is None else out_depth[c],
                segmentation=None if out_seg is None else out_seg[c],
            )
            for c, name in enumerate(cameras)
        }

    def _segment_lut(self) -> np.ndarray:
        """Segmentation colour code -> geom id (-1: background or a non-geom object)."""
        scn = self._scene
        lut = np.full(scn.ngeom + 2, -1, np.int32)
        for g in scn.geoms[: scn.ngeom]:
            if g.segid >= 0 and g.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                lut[g.segid + 1] = g.objid
        return lut

    @staticmethod
    def _batched(x: np.ndarray | None, default: np.ndarray, n: int, name: str) -> np.ndarray:
        if x is None:
            return np.broadcast_to(default, (n, *default.shape))
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (n, *default.shape):
            raise ValueError(f"{name} must be {(n, *default.shape)}, got {x.shape}")
        return x

    def close(self) -> None:
        """Free the GL context now (mujoco warns that relying on __del__ is unreliable)."""
        if self._con is not None:
            if self._gl is not None:
                self._gl.make_current()
            self._con.free()
            self._con = None
        if self._gl is not None:
            self._gl.free()
            self._gl = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: GL may already be gone
            pass
