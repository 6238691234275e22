"""RGB rendering of named cameras for a batch of worlds.

Two implementations behind one small interface (``width``, ``height``, ``camera_names``,
``camera_id``, ``render``, ``close`` and context-manager use):

* :class:`CpuRenderer` - native ``mujoco.Renderer`` (OpenGL, offscreen), one world at a time.
  Works on any machine with a headless GL (Mesa EGL or OSMesa); the evaluation path on CPU.
  ``render(qpos, mocap_pos, mocap_quat, camera, geom_rgba=None)`` takes numpy state arrays.
* :class:`ThreadedCpuRenderer` - N CpuRenderers, each owned by its own persistent thread
  (an OpenGL context is current in one thread only), splitting the worlds of a
  ``render_views`` call into N contiguous chunks rendered in parallel (MuJoCo and llvmpipe
  release the GIL); results are byte-identical to one CpuRenderer. :func:`cpu_renderer`
  builds it with :func:`render_threads` threads, or a plain CpuRenderer when that is 1.
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

import atexit
import copy
import importlib
import queue
import threading
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Self

import jax
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
            raise _unknown_camera(self._model, camera)
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


RENDER_THREADS_ENV = "AGNOSTOS_RENDER_THREADS"
MAX_RENDER_THREADS = 8


def render_threads() -> int:
    """Threads for CPU rendering: ``AGNOSTOS_RENDER_THREADS`` if set (>= 1), else the usable
    cores (CPU affinity) capped at ``MAX_RENDER_THREADS``."""
    env = os.environ.get(RENDER_THREADS_ENV, "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ValueError(f"{RENDER_THREADS_ENV} must be an integer, got {env!r}") from None
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # no sched_getaffinity (macOS)
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_RENDER_THREADS))


def _serve(tasks: queue.SimpleQueue, ready: Future, args: tuple) -> None:
    """Worker thread body: build a CpuRenderer here, run ``fn(renderer)`` tasks until None,
    then free it here. Holds no reference to the ThreadedCpuRenderer (it can be collected)."""
    try:
        renderer = CpuRenderer(*args)
    except BaseException as err:
        ready.set_exception(err)
        return
    ready.set_result(renderer)
    try:
        while (task := tasks.get()) is not None:
            future, fn = task
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(fn(renderer))
                except BaseException as err:  # re-raised in the caller by future.result()
                    future.set_exception(err)
    finally:
        renderer.close()
        _WORKER_QUEUES.pop(threading.current_thread(), None)


_EXIT_HOOK: list[bool] = []


class _RenderWorker:
    """One persistent daemon thread owning one CpuRenderer (built, used, freed in it)."""

    def __init__(self, name: str, args: tuple) -> None:
        self._tasks: queue.SimpleQueue = queue.SimpleQueue()
        ready: Future = Future()
        self.thread = threading.Thread(target=_serve, args=(self._tasks, ready, args),
                                       name=name, daemon=True)
        self.thread.start()
        self.renderer: CpuRenderer = ready.result()  # re-raises a failed build
        if not _EXIT_HOOK:
            atexit.register(_stop_workers_at_exit)
            _EXIT_HOOK.append(True)
        _WORKER_QUEUES[self.thread] = self._tasks

    def submit(self, fn: Any) -> Future:
        future: Future = Future()
        self._tasks.put((future, fn))
        return future

    def stop(self, wait: bool = True) -> None:
        """Ask the thread to free its renderer and end; join it unless ``wait`` is False."""
        self._tasks.put(None)
        if wait and self.thread is not threading.current_thread():
            self.thread.join()


_WORKER_QUEUES: dict[threading.Thread, queue.SimpleQueue] = {}  # every worker not yet ended


def _stop_workers_at_exit() -> None:
    """Free every worker's GL context and end its thread, renderer closed or not.

    Registered when the first worker has made its context, i.e. after mujoco registered its
    EGL display's termination: exit hooks run last-registered first, so the contexts are
    freed while the display exists (otherwise daemon threads freeing them race the
    interpreter's shutdown and print tracebacks)."""
    for thread, tasks in list(_WORKER_QUEUES.items()):
        tasks.put(None)
        thread.join(timeout=10)


class ThreadedCpuRenderer:
    """``threads`` :class:`CpuRenderer` s rendering contiguous chunks of the worlds in parallel.

    Each renderer is built, used and freed inside its own persistent worker thread (a
    one-thread executor), because its OpenGL context can be current in one thread only.
    :meth:`render_views` has CpuRenderer's signature and gives byte-identical results (every
    world is rendered exactly as one CpuRenderer would); a worker's exception is re-raised in
    the caller as is. ``threads=None`` takes :func:`render_threads`; with one thread a plain
    CpuRenderer is used in the calling thread, with no worker threads. :meth:`close` frees the
    GL contexts and joins the threads.
    """

    def __init__(self, model: mujoco.MjModel, width: int = 128, height: int = 128,
                 samples: int | None = None, threads: int | None = None) -> None:
        self.threads = render_threads() if threads is None else max(1, int(threads))
        self.width, self.height = int(width), int(height)
        self._model = model
        self._nmocap, self._ngeom = int(model.nmocap), int(model.ngeom)
        self.camera_names = camera_names(model)
        self.near, self.far = clip_planes(model)
        self._local: CpuRenderer | None = None
        self._workers: list[_RenderWorker] = []
        self._closed = False
        if self.threads == 1:
            self._local = CpuRenderer(model, width, height, samples)
            return
        try:
            for i in range(self.threads):  # one at a time: GL context creation stays serial
                self._workers.append(
                    _RenderWorker(f"cpu-render-{i}", (model, width, height, samples)))
        except BaseException:
            self.close()
            raise

    def camera_id(self, camera: str) -> int:
        """Camera id of a camera name; ValueError listing the model's cameras if unknown."""
        cam_id = mujoco.mj_name2id(self._model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if cam_id < 0:
            raise _unknown_camera(self._model, camera)
        return cam_id

    def render(self, qpos: np.ndarray, mocap_pos: np.ndarray | None,
               mocap_quat: np.ndarray | None, camera: str,
               geom_rgba: np.ndarray | None = None) -> np.ndarray:
        """Render ``camera`` for B worlds -> uint8 [B, H, W, 3] (as :meth:`CpuRenderer.render`)."""
        return self.render_views(qpos, mocap_pos, mocap_quat, (camera,), geom_rgba)[camera].rgb

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
        """As :meth:`CpuRenderer.render_views`, the worlds split over the worker threads."""
        if self._closed:
            raise RuntimeError("ThreadedCpuRenderer is closed")
        flags = {"rgb": rgb, "depth": depth, "segmentation": segmentation}
        if self._local is not None:
            return self._local.render_views(qpos, mocap_pos, mocap_quat, cameras, geom_rgba,
                                            **flags)
        # Checked here so that errors name the whole batch, not a chunk.
        for c in cameras:
            self.camera_id(c)
        qpos = np.asarray(qpos, dtype=np.float64)
        if qpos.ndim != 2 or qpos.shape[1] != self._model.nq:
            raise ValueError(f"qpos must be [B, {self._model.nq}], got {qpos.shape}")
        n = qpos.shape[0]
        shapes = {"mocap_pos": (n, self._nmocap, 3), "mocap_quat": (n, self._nmocap, 4),
                  "geom_rgba": (n, self._ngeom, 4)}
        arrays = {"mocap_pos": mocap_pos, "mocap_quat": mocap_quat, "geom_rgba": geom_rgba}
        for name, x in arrays.items():
            if x is not None:
                arrays[name] = x = np.asarray(x, dtype=np.float64)
                if x.shape != shapes[name]:
                    raise ValueError(f"{name} must be {shapes[name]}, got {x.shape}")
        bounds = np.linspace(0, n, min(self.threads, max(n, 1)) + 1).astype(int)
        futures: list[Future] = []
        for worker, lo, hi in zip(self._workers, bounds[:-1], bounds[1:], strict=False):
            part = {k: None if x is None else x[lo:hi] for k, x in arrays.items()}
            futures.append(worker.submit(
                lambda r, q=qpos[lo:hi], p=part: r.render_views(
                    q, p["mocap_pos"], p["mocap_quat"], cameras, p["geom_rgba"], **flags)))
        parts = [f.result() for f in futures]  # re-raises the first failing chunk's error
        if len(parts) == 1:
            return parts[0]
        join = lambda field, name: (  # noqa: E731
            None if getattr(parts[0][name], field) is None
            else np.concatenate([getattr(p[name], field) for p in parts]))
        return {name: CameraImages(**{f: join(f, name) for f in
                                      ("pos", "mat", "rgb", "depth", "segmentation")})
                for name in cameras}

    def close(self) -> None:
        """Free every GL context (each in its own thread) and join the worker threads."""
        self._stop(wait=True)

    def _stop(self, wait: bool) -> None:
        self._closed = True
        if self._local is not None:
            self._local.close()
        workers, self._workers = self._workers, []
        for worker in workers:
            worker.stop(wait)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        # Never blocks: garbage collection may run anywhere (e.g. holding an import lock).
        try:
            self._stop(wait=False)
        except Exception:  # interpreter shutdown
            pass


def cpu_renderer(model: mujoco.MjModel, width: int = 128, height: int = 128,
                 samples: int | None = None, threads: int | None = None
                 ) -> CpuRenderer | ThreadedCpuRenderer:
    """A CPU renderer using ``threads`` threads (None: :func:`render_threads`): a plain
    :class:`CpuRenderer` for one thread, else a :class:`ThreadedCpuRenderer`."""
    n = render_threads() if threads is None else max(1, int(threads))
    if n == 1:
        return CpuRenderer(model, width, height, samples)
    return ThreadedCpuRenderer(model, width, height, samples, threads=n)


class FixedCamLight:
    """Camera and light poses of a scene whose cameras and lights are all fixed to a body.

    ``mj_camlight`` in closed form: a pose is the body's pose composed with the camera's
    (light's) local one.  Warp's ``kinematics`` does not pose cameras and lights and MJX's
    ``camlight`` is JAX-only, so without this the warp observation ran a full ``forward``
    (contacts, constraints, solver) only to place five cameras.  Works on numpy or JAX
    arrays with any leading batch axes (``xp``)."""

    def __init__(self, model: mujoco.MjModel) -> None:
        moving = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i)
                  for i in range(model.ncam) if model.cam_mode[i] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED]
        moving += [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_LIGHT, i)
                   for i in range(model.nlight)
                   if model.light_mode[i] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED]
        if moving:
            raise ValueError(f"cameras/lights not fixed to their body: {moving}")
        self.cam_body = np.asarray(model.cam_bodyid, np.int32)
        self.cam_pos = np.asarray(model.cam_pos, np.float32)
        mats = np.zeros((model.ncam, 9))
        for i in range(model.ncam):
            mujoco.mju_quat2Mat(mats[i], model.cam_quat[i])
        self.cam_mat = mats.reshape(-1, 3, 3).astype(np.float32)
        self.light_body = np.asarray(model.light_bodyid, np.int32)
        self.light_pos = np.asarray(model.light_pos, np.float32)
        self.light_dir = np.asarray(model.light_dir, np.float32)

    @staticmethod
    def supports(model: mujoco.MjModel) -> bool:
        fixed = mujoco.mjtCamLight.mjCAMLIGHT_FIXED
        return bool(np.all(model.cam_mode == fixed) and np.all(model.light_mode == fixed))

    def __call__(self, xpos: Any, xmat: Any, xp: Any = np) -> tuple[Any, Any, Any, Any]:
        """Body poses (..., nbody, 3), (..., nbody, 3, 3) -> cam_xpos, cam_xmat, light_xpos,
        light_xdir as MuJoCo's Data holds them."""
        def place(body: np.ndarray, local: np.ndarray) -> Any:
            return xpos[..., body, :] + (xmat[..., body, :, :] @ xp.asarray(local)[..., None])[..., 0]

        cam_xmat = xmat[..., self.cam_body, :, :] @ xp.asarray(self.cam_mat)
        light_xdir = (xmat[..., self.light_body, :, :]
                      @ xp.asarray(self.light_dir)[..., None])[..., 0]
        return (place(self.cam_body, self.cam_pos), cam_xmat,
                place(self.light_body, self.light_pos), light_xdir)


class WarpRenderer:
    """MJX-Warp batch ray-tracer: all worlds of an ``mjx.Data`` batch in one GPU call.

    ``nworld`` is fixed by the render context. ``cameras`` limits which cameras are rendered
    (default: all); ``depth`` and ``segmentation`` add those buffers to the context (they cost
    nothing measurable on an H100). ``data`` passed to the render methods must be a warp-impl
    batch (leading axis ``nworld``) on which forward/kinematics already ran (cam_xpos,
    geom_xpos are read). Colours come from the mjx.Model (``mjx_model``, default
    ``put_model(model, impl="warp")``) or per world from ``geom_rgba`` [B, ngeom, 4].
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        nworld: int,
        width: int = 128,
        height: int = 128,
        cameras: Sequence[str] | None = None,
        mjx_model: Any = None,
        depth: bool = False,
        segmentation: bool = False,
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
        self.near, self.far = clip_planes(model)
        self.depth, self.segmentation = bool(depth), bool(segmentation)
        self.mx = mjx_model if mjx_model is not None else mjx.put_model(model, impl="warp")
        self._rc: Any = mjx.create_render_context(
            mjm=model,
            nworld=self.nworld,
            cam_res=(self.width, self.height),
            cam_active=list(self.camera_names),
            render_rgb=True,
            render_depth=self.depth,
            render_seg=self.segmentation,
            use_textures=bool(model.ntex),  # match CpuRenderer's look; free without textures
            use_shadows=False,
        )
        mx, rc = self.mx, self._rc.pytree()  # closed over: passing mx to jit is slow
        cam_ids = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, c)
                            for c in self.camera_names])
        far = self.far

        def _buffers(d: Any, rgba: Any) -> tuple[Any, Any, Any]:
            """Bare renderer: refit the BVH and trace every camera of every world."""
            m, axes = mx, None
            if rgba is not None:  # per-world colours: a batched model field
                m = mx.tree_replace({"geom_rgba": rgba})
                axes = jax.tree.map(lambda _: None, mx).tree_replace({"geom_rgba": 0})
            d = jax.vmap(mjx.refit_bvh, in_axes=(axes, 0, None))(m, d, rc)
            if self.segmentation:
                rgb, dep, seg, _ = jax.vmap(mjx.render_with_segmentation,
                                            in_axes=(axes, 0, None))(m, d, rc)
            else:
                (rgb, dep, _), seg = jax.vmap(mjx.render, in_axes=(axes, 0, None))(m, d, rc), None
            return rgb, dep, seg

        def _views(d: Any, rgba: Any) -> dict[str, CameraImages]:
            rgb, dep, seg = _buffers(d, rgba)
            views = {}
            for i, name in enumerate(self.camera_names):
                img = jnp.round(mjx.get_rgb(rc, i, rgb) * 255.0).astype(jnp.uint8)
                metres = None
                if self.depth:  # planar depth in metres; 0 where no geom was hit
                    raw = mjx.get_depth(rc, i, dep, far)[..., 0] * far
                    metres = jnp.where(raw > 0.0, raw, far).astype(jnp.float32)
                labels = mjx.get_segmentation(rc, i, seg).astype(jnp.int32) if seg is not None \
                    else None
                views[name] = CameraImages(pos=d.cam_xpos[:, cam_ids[i]],
                                           mat=d.cam_xmat[:, cam_ids[i]].reshape(-1, 3, 3),
                                           rgb=img, depth=metres, segmentation=labels)
            return views

        self._buffers = jax.jit(_buffers)
        self._views_fn = _views
        self._views = jax.jit(_views)
        self._template: Any = None
        self._pose_jit: Any = None
        self._camlight = FixedCamLight(model) if FixedCamLight.supports(model) else None

    def template(self) -> Any:
        """A warp ``mjx.Data`` batch of ``nworld`` worlds, made once (its state is replaced)."""
        import jax
        import jax.numpy as jnp
        from mujoco import mjx

        if self._template is None:
            make = lambda _: mjx.make_data(self._model, impl="warp",  # noqa: E731
                                           naconmax=64 * self.nworld, njmax=256)
            self._template = jax.jit(jax.vmap(make))(jnp.arange(self.nworld))
        return self._template

    def pose(self, template: Any, qpos: Any, mocap_pos: Any, mocap_quat: Any) -> Any:
        """``template`` with this state, posed for rendering (traceable: use inside a jit).

        Kinematics and the cameras' and lights' poses when they are all fixed to bodies
        (every task scene), else a full ``forward``."""
        import jax
        import jax.numpy as jnp
        from mujoco import mjx

        mx = self.mx
        f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        d = template.replace(qpos=f32(qpos), mocap_pos=f32(mocap_pos), mocap_quat=f32(mocap_quat))
        if self._camlight is None:
            return jax.vmap(lambda d: mjx.forward(mx, d))(d)
        d = jax.vmap(lambda d: mjx.kinematics(mx, d))(d)
        cam_xpos, cam_xmat, light_xpos, light_xdir = self._camlight(d.xpos, d.xmat, jnp)
        return d.tree_replace({"cam_xpos": cam_xpos, "cam_xmat": cam_xmat,
                               "_impl.light_xpos": light_xpos, "_impl.light_xdir": light_xdir})

    def state_data(self, qpos: Any, mocap_pos: Any, mocap_quat: Any) -> Any:
        """A posed warp ``mjx.Data`` batch from host or device state arrays."""
        import jax

        if self._pose_jit is None:
            self._pose_jit = jax.jit(self.pose)
        return self._pose_jit(self.template(), qpos, mocap_pos, mocap_quat)

    def views(self, data: Any, geom_rgba: Any = None) -> dict[str, CameraImages]:
        """:meth:`render_views` without the checks (traceable: use inside a jit)."""
        return self._views_fn(data, geom_rgba)

    def camera_id(self, camera: str) -> int:
        """Index of ``camera`` among the rendered cameras (what ``get_rgb`` expects)."""
        if camera not in self.camera_names:
            raise _unknown_camera(self._model, camera)
        return self.camera_names.index(camera)

    def _check(self, data: Any) -> None:
        if self._rc is None:
            raise RuntimeError("WarpRenderer is closed")
        if data.qpos.shape[0] != self.nworld:
            raise ValueError(f"data batch {data.qpos.shape[0]} != nworld {self.nworld}")

    def render_buffers(self, data: Any, geom_rgba: Any = None) -> tuple[Any, Any, Any]:
        """The bare renderer (``refit_bvh`` + ``render``): packed device buffers, for timing."""
        self._check(data)
        return self._buffers(data, geom_rgba)

    def render_views(self, data: Any, geom_rgba: Any = None) -> dict[str, CameraImages]:
        """Every camera of the context -> :class:`CameraImages` of JAX device arrays."""
        self._check(data)
        return self._views(data, geom_rgba)

    def render_jax(self, data: Any, camera: str) -> Any:
        """Like :meth:`render` but returns the device array (no host copy)."""
        self.camera_id(camera)
        return self.render_views(data)[camera].rgb

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
