"""`WarpRenderer`: the MJX ``impl="warp"`` batch ray-tracer (all worlds in one CUDA call),
`FixedCamLight`, the closed-form camera and light poses it renders from, and
`headlight_as_light`, which lights Warp's images as MuJoCo's OpenGL lights the CPU's.
Importing this module needs neither warp nor a GPU (they are imported when a renderer is
built)."""

from __future__ import annotations

import copy
import threading
from collections.abc import Sequence
from typing import Any, Self

import mujoco
import numpy as np

from agnostos_mjx.infra.gc_pause import gc_paused
from agnostos_mjx.render.common import CameraImages, camera_names, clip_planes, unknown_camera


def captured(program: Any, *args: Any) -> Any:
    """`program(*args)` run to its end with Python's garbage collector paused: Warp captures
    its kernels into a CUDA graph, and a collection meanwhile may free an old XLA program,
    whose unloading fails the capture (infra.gc_pause)."""
    import jax

    with gc_paused():
        return jax.block_until_ready(program(*args))


_preloading: threading.Thread | None = None


def preload() -> None:
    """Start loading MJX-Warp (mujoco_warp's kernel modules, Warp's CUDA start) on a thread,
    so that it overlaps a run's start instead of delaying its first observation; the first
    `WarpRenderer` waits for it.  For a run that has chosen the warp route."""
    global _preloading
    if _preloading is None:
        _preloading = threading.Thread(target=_load_warp, name="warp-preload", daemon=True)
        _preloading.start()


def _load_warp() -> None:
    """Import MJX-Warp and start Warp with the collector paused: each collection there
    also runs JAX's callback (infra.gc_pause; docs/performance.md)."""
    try:
        with gc_paused():
            import warp

            from agnostos_mjx.physics.quiet_mjx import mjx  # noqa: F401

            warp.init()
    except Exception:  # noqa: BLE001 - the renderer's own import reports it
        pass


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


# scenes/world.xml's inactive light that carries the headlight on Warp (headlight_as_light).
HEADLIGHT_LIGHT = "headlight"


def headlight_as_light(model: mujoco.MjModel) -> tuple[mujoco.MjModel, int]:
    """A copy of ``model`` whose headlight is its light `HEADLIGHT_LIGHT`, and that light's id.

    MuJoCo's OpenGL renderer places the headlight once per scene update
    (``mjv_updateScene`` -> ``mjv_makeLights``, at the scene's camera) and
    ``mjv_updateCamera`` does not move it, so `CpuRenderer` lights every camera of a
    ``render_views`` call with the headlight of the call's *first* camera.  MuJoCo Warp
    lights each camera with its own headlight, so only the first camera agreed.  Warp's
    headlight is switched off here and the scene's inactive placeholder light turned into a
    directional light with the headlight's colours, which `WarpRenderer.pose` aims along
    the first camera's view.  A model without the placeholder, or without a headlight, is
    returned unchanged with id -1 (each camera then keeps Warp's own headlight)."""
    light = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_LIGHT, HEADLIGHT_LIGHT)
    if light < 0 or not model.vis.headlight.active:
        return model, -1
    head = model.vis.headlight
    m = copy.copy(model)
    m.vis.headlight.active = 0
    m.light_active[light] = True
    m.light_type[light] = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
    m.light_castshadow[light] = False
    m.light_ambient[light] = head.ambient
    m.light_diffuse[light] = head.diffuse
    m.light_specular[light] = head.specular
    return m, light


class WarpRenderer:
    """MJX-Warp batch ray-tracer: all worlds of an ``mjx.Data`` batch in one GPU call.

    ``nworld`` is fixed by the render context. ``cameras`` limits which cameras are rendered
    (default: all); ``depth`` and ``segmentation`` add those buffers to the context (they cost
    nothing measurable). The render methods take a batch's state (qpos, mocap_pos,
    mocap_quat, leading axis ``nworld``) and pose it on the device (`pose`). Colours come
    from the mjx.Model (``mjx_model``, default ``put_model`` of the renderer's `model`) or
    per world from ``geom_rgba`` [B, ngeom, 4].
    Lighting is `CpuRenderer`'s: the headlight of the first of ``cameras`` lights them all
    (`headlight_as_light`; a given ``mjx_model`` must be ``put_model(renderer.model)``).
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

        if _preloading is not None:
            _preloading.join()
        from agnostos_mjx.physics.base import for_warp
        from agnostos_mjx.physics.quiet_mjx import mjx

        model = for_warp(model)
        model, self._headlight = headlight_as_light(model)
        self.width, self.height, self.nworld = int(width), int(height), int(nworld)
        self.camera_names = tuple(cameras) if cameras is not None else camera_names(model)
        for cam in self.camera_names:
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, cam) < 0:
                raise unknown_camera(model, cam)
        self._model = model
        self._first_cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA,
                                            self.camera_names[0])
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

        self._buffers_fn = _buffers
        self._views_fn = _views
        make = lambda _: mjx.make_data(  # noqa: E731
            self._model, impl="warp", naconmax=64 * self.nworld, njmax=256)
        self._template = jax.jit(jax.vmap(make))(jnp.arange(self.nworld))  # state replaced
        self._programs: dict[str, Any] = {}
        self._camlight = FixedCamLight(model) if FixedCamLight.supports(model) else None

    @property
    def model(self) -> mujoco.MjModel:
        """The MjModel Warp renders: the caller's, lit as `CpuRenderer` lights it."""
        return self._model

    def pose(self, qpos: Any, mocap_pos: Any, mocap_quat: Any) -> Any:
        """The template with this state, posed for rendering (traceable: use inside a jit).

        Kinematics and the cameras' and lights' poses when they are all fixed to bodies
        (every task scene), else a full ``forward``.  The template enters the program as a
        constant: as an argument, every call cost several times the render itself on the
        GPU (docs/performance.md)."""
        import jax
        import jax.numpy as jnp

        from agnostos_mjx.physics.quiet_mjx import mjx

        mx = self.mx
        f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        d = self._template.replace(qpos=f32(qpos), mocap_pos=f32(mocap_pos),
                                    mocap_quat=f32(mocap_quat))
        if self._camlight is None:
            d = jax.vmap(lambda d: mjx.forward(mx, d))(d)
            cam_xpos, cam_xmat = d.cam_xpos, d.cam_xmat
            light_xpos, light_xdir = d._impl.light_xpos, d._impl.light_xdir
        else:
            d = jax.vmap(lambda d: mjx.kinematics(mx, d))(d)
            cam_xpos, cam_xmat, light_xpos, light_xdir = self._camlight(d.xpos, d.xmat, jnp)
        if self._headlight >= 0:  # the first camera's headlight, as mjv_makeLights places it
            cam = self._first_cam
            light_xpos = light_xpos.at[..., self._headlight, :].set(cam_xpos[..., cam, :])
            light_xdir = light_xdir.at[..., self._headlight, :].set(-cam_xmat[..., cam, :, 2])
        return d.tree_replace({"cam_xpos": cam_xpos, "cam_xmat": cam_xmat,
                               "_impl.light_xpos": light_xpos, "_impl.light_xdir": light_xdir})

    def _program(self, name: str, body: Any) -> Any:
        """The jitted program `name` (made once) of `body(pose(qpos, ...), geom_rgba)`."""
        import jax

        if self._rc is None:
            raise RuntimeError("WarpRenderer is closed")
        if name not in self._programs:
            self._programs[name] = jax.jit(
                lambda q, mp, mq, rgba: body(self.pose(q, mp, mq), rgba))
        return self._programs[name]

    def state_buffers(self, qpos: Any, mocap_pos: Any, mocap_quat: Any,
                      geom_rgba: Any = None) -> tuple[Any, Any, Any]:
        """The bare renderer from a state: pose, refit the BVH, trace; packed device buffers,
        for timing (what an observation costs before its images are unpacked)."""
        return captured(self._program("buffers", self._buffers_fn), qpos, mocap_pos,
                        mocap_quat, geom_rgba)

    def state_views(self, qpos: Any, mocap_pos: Any, mocap_quat: Any,
                    geom_rgba: Any = None) -> dict[str, CameraImages]:
        """Every camera of the context for a state (host or device arrays, leading axis
        ``nworld``) -> :class:`CameraImages` of device arrays."""
        if np.shape(qpos)[0] != self.nworld:
            raise ValueError(f"state batch {np.shape(qpos)[0]} != nworld {self.nworld}")
        return captured(self._program("views", self._views_fn), qpos, mocap_pos, mocap_quat,
                        geom_rgba)

    def views(self, data: Any, geom_rgba: Any = None) -> dict[str, CameraImages]:
        """The images of a posed ``data`` (traceable: use inside a jit, after `pose`)."""
        return self._views_fn(data, geom_rgba)

    def camera_id(self, camera: str) -> int:
        """Index of ``camera`` among the rendered cameras (what ``get_rgb`` expects)."""
        if camera not in self.camera_names:
            raise unknown_camera(self._model, camera)
        return self.camera_names.index(camera)

    def render(self, qpos: Any, mocap_pos: Any, mocap_quat: Any, camera: str,
               geom_rgba: Any = None) -> np.ndarray:
        """RGB of ``camera`` for every world of a state -> uint8 [B, H, W, 3]."""
        self.camera_id(camera)
        return np.asarray(self.state_views(qpos, mocap_pos, mocap_quat, geom_rgba)[camera].rgb)

    def close(self) -> None:
        """Drop the render context so its GPU buffers are released, once the renders already
        dispatched are done (JAX runs them asynchronously; without their context they fail)."""
        if self._rc is not None:
            import jax

            jax.effects_barrier()
        self._rc = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
