"""RGB rendering of named cameras for a batch of worlds.

Two implementations behind one small interface (``width``, ``height``, ``camera_names``,
``camera_id``, ``render``, ``close`` and context-manager use):

* :class:`CpuRenderer` - native ``mujoco.Renderer`` (OpenGL, offscreen), one world at a time.
  Works on any machine with a headless GL (Mesa EGL or OSMesa); the evaluation path on CPU.
  ``render(qpos, mocap_pos, mocap_quat, camera, geom_rgba=None)`` takes numpy state arrays.
* :class:`WarpRenderer` - MJX ``impl="warp"`` batch ray-tracer on a CUDA GPU.
  ``render(data, camera)`` takes an ``mjx.Data`` batch whose kinematics are up to date.

Headless GL selection (``MUJOCO_GL``): mujoco picks its GL backend when ``mujoco`` is first
imported, from ``MUJOCO_GL``. An existing ``MUJOCO_GL`` is always respected. Otherwise this
module sets it, before importing mujoco, to ``egl`` when libEGL is installed, else ``osmesa``
when libOSMesa is installed (a set ``PYOPENGL_PLATFORM`` must agree, because mujoco refuses to
mix the two); with neither it is set to "" and building a CpuRenderer raises a RuntimeError
naming the packages to install. If mujoco was already imported by someone else before
``MUJOCO_GL`` was set (so it bound GLFW, which needs a display), :class:`CpuRenderer` swaps
mujoco's offscreen GL context class to the MUJOCO_GL backend when it is built.
"""

from __future__ import annotations

import ctypes.util
import os

# Choose the headless GL before mujoco is imported (it reads MUJOCO_GL at import time).
# An existing MUJOCO_GL wins; else egl, then osmesa, whichever library is installed and agrees
# with PYOPENGL_PLATFORM if that is set (mujoco's egl/osmesa modules refuse a mismatch).
os.environ.setdefault(
    "MUJOCO_GL",
    next(
        (
            gl
            for gl, lib in (("egl", "EGL"), ("osmesa", "OSMesa"))
            if os.environ.get("PYOPENGL_PLATFORM", gl).strip().lower() == gl
            and ctypes.util.find_library(lib)
        ),
        "",
    ),
)

import copy
import importlib
from collections.abc import Sequence
from typing import Any, Self

import mujoco
import numpy as np

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


def _unknown_camera(model: mujoco.MjModel, camera: str) -> ValueError:
    return ValueError(f"unknown camera {camera!r}; model cameras: {list(camera_names(model))}")


def _fix_late_gl_context() -> None:
    """Point mujoco at the MUJOCO_GL backend if mujoco was imported before it was set.

    mujoco binds its offscreen GL context class at import; when another module imported
    mujoco first without MUJOCO_GL, that class is GLFW's (needs a display). Swapping the class
    in mujoco's gl_context module is what ``mujoco.Renderer`` looks up when it is built.
    """
    want = gl_backend()
    if want not in ("egl", "osmesa"):
        return
    try:
        from mujoco.rendering.classic import gl_context  # mujoco >= 4
    except ImportError:
        from mujoco import gl_context  # older layout
    current = getattr(gl_context, "GLContext", None)
    if current is not None and current.__module__ == f"mujoco.{want}":
        return
    try:
        gl_context.GLContext = importlib.import_module(f"mujoco.{want}").GLContext
    except (ImportError, OSError, AttributeError) as err:
        raise RuntimeError(
            f"cannot load mujoco's {want} GL backend: {err}. {GL_INSTALL_HINT}"
        ) from err


class CpuRenderer:
    """Offscreen ``mujoco.Renderer`` looping over worlds; shadows and reflections off for speed.

    Works on a private copy of ``model`` (offscreen buffer enlarged, shadow map disabled,
    per-call ``geom_rgba`` written there and restored), so the caller's model is never touched.
    """

    def __init__(self, model: mujoco.MjModel, width: int = 128, height: int = 128) -> None:
        self.width, self.height = int(width), int(height)
        self._renderer: Any = None
        m = copy.copy(model)
        m.vis.global_.offwidth = max(int(m.vis.global_.offwidth), self.width)
        m.vis.global_.offheight = max(int(m.vis.global_.offheight), self.height)
        m.vis.quality.shadowsize = 0  # the default 4096^2 shadow map costs ~20x on llvmpipe
        self._model = m
        self._data = mujoco.MjData(m)
        self._rgba0 = m.geom_rgba.copy()
        self._mocap_pos0 = self._data.mocap_pos.copy()
        self._mocap_quat0 = self._data.mocap_quat.copy()
        self.camera_names = camera_names(m)
        _fix_late_gl_context()
        try:
            self._renderer = mujoco.Renderer(m, height=self.height, width=self.width)
        except Exception as err:  # GL failures surface as many exception types
            raise RuntimeError(
                f"no working OpenGL for mujoco.Renderer (MUJOCO_GL={gl_backend()!r}): "
                f"{type(err).__name__}: {err}. {GL_INSTALL_HINT}"
            ) from err
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False

    def camera_id(self, camera: str) -> int:
        """Camera id of a camera name; ValueError listing the model's cameras if unknown."""
        cam_id = mujoco.mj_name2id(self._model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if cam_id < 0:
            raise _unknown_camera(self._model, camera)
        return cam_id

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
        if self._renderer is None:
            raise RuntimeError("CpuRenderer is closed")
        cam_id = self.camera_id(camera)
        m, d = self._model, self._data
        qpos = np.asarray(qpos, dtype=np.float64)
        if qpos.ndim != 2 or qpos.shape[1] != m.nq:
            raise ValueError(f"qpos must be [B, {m.nq}], got {qpos.shape}")
        nworld = qpos.shape[0]
        pos = self._batched(mocap_pos, self._mocap_pos0, nworld, "mocap_pos")
        quat = self._batched(mocap_quat, self._mocap_quat0, nworld, "mocap_quat")
        rgba = None
        if geom_rgba is not None:
            rgba = self._batched(geom_rgba, self._rgba0, nworld, "geom_rgba")
        out = np.empty((nworld, self.height, self.width, 3), dtype=np.uint8)
        try:
            for i in range(nworld):
                d.qpos[:] = qpos[i]
                if m.nmocap:
                    d.mocap_pos[:] = pos[i]
                    d.mocap_quat[:] = quat[i]
                if rgba is not None:
                    m.geom_rgba[:] = rgba[i]
                self._pose()
                self._renderer.update_scene(d, cam_id)
                self._renderer.render(out=out[i])
        finally:
            if rgba is not None:
                m.geom_rgba[:] = self._rgba0
        return out

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
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class WarpRenderer:
    """MJX-Warp batch ray-tracer: all worlds of an ``mjx.Data`` batch in one GPU call.

    ``nworld`` is fixed by the render context. ``cameras`` limits which cameras are rendered
    (default: all). ``data`` passed to :meth:`render` must be a warp-impl batch (leading axis
    ``nworld``) on which forward/kinematics already ran (cam_xpos, geom_xpos are read).
    Colours come from the mjx.Model (``mjx_model``, default ``put_model(model, impl="warp")``).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        nworld: int,
        width: int = 128,
        height: int = 128,
        cameras: Sequence[str] | None = None,
        mjx_model: Any = None,
    ) -> None:
        import jax  # lazy: keeps this module importable without warp/CUDA
        import jax.numpy as jnp
        from mujoco import mjx

        self.width, self.height, self.nworld = int(width), int(height), int(nworld)
        self.camera_names = tuple(cameras) if cameras is not None else camera_names(model)
        for cam in self.camera_names:
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, cam) < 0:
                raise _unknown_camera(model, cam)
        self._model = model
        self.mx = mjx_model if mjx_model is not None else mjx.put_model(model, impl="warp")
        self._rc: Any = mjx.create_render_context(
            mjm=model,
            nworld=self.nworld,
            cam_res=(self.width, self.height),
            cam_active=list(self.camera_names),
            render_rgb=True,
            render_depth=False,
            use_textures=bool(model.ntex),  # match CpuRenderer's look; free without textures
            use_shadows=False,
        )
        mx, rc = self.mx, self._rc.pytree()  # closed over: passing mx to jit is slow

        def _render(d: Any, cam_index: int) -> Any:
            d = jax.vmap(mjx.refit_bvh, in_axes=(None, 0, None))(mx, d, rc)
            rgb, _, _ = jax.vmap(mjx.render, in_axes=(None, 0, None))(mx, d, rc)
            img = mjx.get_rgb(rc, cam_index, rgb)  # float32 [B, H, W, 3] in [0, 1]
            return jnp.round(img * 255.0).astype(jnp.uint8)

        self._render = jax.jit(_render, static_argnums=1)

    def camera_id(self, camera: str) -> int:
        """Index of ``camera`` among the rendered cameras (what ``get_rgb`` expects)."""
        if camera not in self.camera_names:
            raise _unknown_camera(self._model, camera)
        return self.camera_names.index(camera)

    def render_jax(self, data: Any, camera: str) -> Any:
        """Like :meth:`render` but returns the device array (no host copy)."""
        if self._rc is None:
            raise RuntimeError("WarpRenderer is closed")
        if data.qpos.shape[0] != self.nworld:
            raise ValueError(f"data batch {data.qpos.shape[0]} != nworld {self.nworld}")
        return self._render(data, self.camera_id(camera))

    def render(self, data: Any, camera: str) -> np.ndarray:
        """Render ``camera`` for every world of ``data`` -> uint8 [B, H, W, 3]."""
        return np.asarray(self.render_jax(data, camera))

    def close(self) -> None:
        """Drop the render context so its GPU buffers are released."""
        self._rc = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def make_renderer(
    model: mujoco.MjModel, nworld: int, backend: str, width: int = 128, height: int = 128
) -> CpuRenderer | WarpRenderer:
    """WarpRenderer when ``backend == "warp"`` (GPU), otherwise CpuRenderer."""
    if backend == "warp":
        return WarpRenderer(model, nworld, width=width, height=height)
    return CpuRenderer(model, width=width, height=height)
