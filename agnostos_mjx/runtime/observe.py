"""What policies see of a batch: RLBench observations (observation.py's types) rendered
for the worlds of an EnvState.  The `Observer` owns the renderers of one runner (GL
contexts and Warp kernels are costly, so they are made once and reused), with one route
per renderer: MuJoCo's OpenGL renderer on CPU threads, MJX-Warp's batch ray tracer on a GPU
(beside any physics backend: the worlds' state goes to the device).
"""

from __future__ import annotations

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from agnostos_mjx.infra.host_copy import to_numpy
from agnostos_mjx.physics.capabilities import RenderRoute
from agnostos_mjx.runtime.observation import (
    CAMERA_ARRAYS,
    CameraObservation,
    ObservationSpec,
    RLBenchObservation,
    camera_constants,
    camera_observation,
    scene_labels,
)
from agnostos_mjx.runtime.state import EnvState
from agnostos_mjx.sim.world import FINGER_OPEN, SceneModel
from agnostos_mjx.tasks.base import Task

GRIPPER_OPEN_THRESHOLD = 0.95  # PerAct fork: gripper_open = open amount > 0.95


# What a world that has ended sees on either route, unrendered (its depth: the far plane).
BLANK = {"pos": 0.0, "mat": np.eye(3), "rgb": 0, "segmentation": -1}


def blank_ended(view: Any, live: Any, far: float) -> Any:
    """`view` (device CameraImages of B worlds) with the worlds that have ended (`live`
    False) blank, as the CPU route leaves them: the same look on both routes."""
    from agnostos_mjx.render import CameraImages

    def keep(x: Any, blank: Any) -> Any:
        if x is None:
            return None
        mask = live.reshape(live.shape + (1,) * (x.ndim - 1))
        return jnp.where(mask, x, jnp.asarray(blank, x.dtype))

    return CameraImages(pos=keep(view.pos, BLANK["pos"]), mat=keep(view.mat, BLANK["mat"]),
                        rgb=keep(view.rgb, BLANK["rgb"]), depth=keep(view.depth, far),
                        segmentation=keep(view.segmentation, BLANK["segmentation"]))


class Observer:
    """Renders and assembles observations of one task's worlds; owns its renderers."""

    def __init__(self, task: Task, scene: SceneModel, backend_name: str,
                 renderer: str = "auto"):
        """`renderer`: the run's route (``--renderer``); "auto" leaves it to each spec's,
        and an "auto" spec to the machine (physics.resolve_renderer)."""
        self.task = task
        self.scene = scene
        self.backend_name = backend_name
        self.run_renderer = renderer
        self._renderers: dict[tuple, Any] = {}
        self._programs: dict[tuple, Any] = {}  # (spec, batch) -> jitted warp observation
        self.render_s = 0.0  # seconds spent rendering observations, for the run's time split
        self.frames = 0  # camera frames rendered (one camera of one world)

    # ---- the routes -------------------------------------------------------------------
    def route(self, spec: ObservationSpec) -> RenderRoute:
        """Where `spec` renders: the run's renderer when it names one, else the spec's, else
        the machine's (physics.render_route)."""
        from agnostos_mjx.physics import render_route

        name = self.run_renderer if self.run_renderer != "auto" else spec.renderer
        return render_route(name, self.backend_name)

    def cpu_renderer(self, spec: ObservationSpec) -> Any:
        """The cached OpenGL renderer of `spec`'s size, its worlds split over
        render_threads() threads (AGNOSTOS_RENDER_THREADS)."""
        from agnostos_mjx.render import cpu_renderer, render_threads

        threads = render_threads()
        key: tuple = ("cpu", spec.height, spec.width, threads)
        if key not in self._renderers:
            self._renderers[key] = cpu_renderer(self.scene.model, spec.width, spec.height,
                                                samples=0, threads=threads)
        return self._renderers[key]

    def warp_renderer(self, spec: ObservationSpec, nworld: int) -> Any:
        """The cached MJX-Warp renderer of `spec` for `nworld` worlds."""
        from agnostos_mjx.render import WarpRenderer

        key = self._warp_key(spec, nworld)
        if key not in self._renderers:
            self._renderers[key] = WarpRenderer(
                self.scene.model, nworld, spec.width, spec.height, cameras=spec.cameras,
                depth=spec.needs_depth, segmentation=spec.wants("segmentation"))
        return self._renderers[key]

    def render_views(self, state: EnvState, spec: ObservationSpec) -> dict[str, Any]:
        """The raw images of `spec` for every world of `state` on its route (no point
        clouds yet; the tools that compare the routes and time the bare renderer use it)."""
        p = state.physics
        if self.route(spec).on_device:
            renderer = self.warp_renderer(spec, len(p.qpos))
            return renderer.state_views(p.qpos, p.mocap_pos, p.mocap_quat,
                                        jnp.asarray(state.geom_rgba, jnp.float32))
        return self._cpu_views(state, spec)

    def _cpu_views(self, state: EnvState, spec: ObservationSpec) -> dict[str, Any]:
        """The CPU renderer's images of the worlds still running; a world that has ended
        acts no more, so it gets blank images (and an identity camera pose) unrendered."""
        from agnostos_mjx.render import CameraImages, clip_planes

        renderer = self.cpu_renderer(spec)
        p = state.physics
        rows = np.nonzero(~np.asarray(state.done, bool))[0]
        rgba = state.geom_rgba
        every = len(rows) == state.batch
        pick = (lambda x: np.asarray(x)) if every else (lambda x: np.asarray(x)[rows])
        views = renderer.render_views(
            pick(p.qpos), pick(p.mocap_pos), pick(p.mocap_quat), spec.cameras,
            pick(rgba) if rgba is not None and np.ndim(rgba) == 3 else rgba, rgb=spec.wants("rgb"),
            depth=spec.needs_depth, segmentation=spec.wants("segmentation"))
        if every:
            return views

        def scatter(x: Any, blank: Any) -> Any:
            if x is None:
                return None
            out = np.empty((state.batch, *x.shape[1:]), x.dtype)
            out[...] = blank
            out[rows] = x
            return out

        far = clip_planes(self.scene.model)[1]
        return {name: CameraImages(pos=scatter(v.pos, BLANK["pos"]),
                                   mat=scatter(v.mat, BLANK["mat"]),
                                   rgb=scatter(v.rgb, BLANK["rgb"]), depth=scatter(v.depth, far),
                                   segmentation=scatter(v.segmentation, BLANK["segmentation"]))
                for name, v in views.items()}

    def _warp_cameras(self, state: EnvState, spec: ObservationSpec
                      ) -> dict[str, CameraObservation]:
        """Every camera of `spec` on MJX-Warp as one device program: pose (kinematics and
        camera poses), trace, then depth clipping, extrinsics and point clouds; numpy arrays
        when the spec asks for them."""
        from agnostos_mjx.infra.sharding import pad
        from agnostos_mjx.render.warp import captured

        p = state.physics
        n = len(p.qpos)
        nworld = self._warp_worlds(spec, n)
        renderer = self.warp_renderer(spec, nworld)
        constants = camera_constants(self.scene.model, spec)
        key = (spec, nworld)
        if key not in self._programs:
            blank_far = renderer.far

            def observe_all(qpos: Any, mocap_pos: Any, mocap_quat: Any, rgba: Any,
                            live: Any) -> dict[str, dict[str, Any]]:
                views = renderer.views(renderer.pose(qpos, mocap_pos, mocap_quat), rgba)
                out = {}
                for name, (k, near, far) in constants.items():
                    view = blank_ended(views[name], live, blank_far)
                    cam = camera_observation(view, k, near, far, spec, jnp)
                    out[name] = {f: getattr(cam, f) for f in CAMERA_ARRAYS}
                return out

            self._programs[key] = jax.jit(observe_all)
        live = ~np.asarray(state.done, bool)
        state_arrays = pad((p.qpos, p.mocap_pos, p.mocap_quat, state.geom_rgba, live), nworld)
        arrays = captured(self._programs[key], *state_arrays)
        if spec.numpy:  # through pinned host memory, all arrays at once
            arrays = to_numpy(arrays)
        if nworld != n:
            arrays = jax.tree.map(lambda x: x[:n], arrays)
        return {name: CameraObservation(intrinsics=k, near=near, far=far, **arrays[name])
                for name, (k, near, far) in constants.items()}

    def _warp_worlds(self, spec: ObservationSpec, n: int) -> int:
        """The world count to render `n` worlds of `spec` with: the smallest Warp renderer
        already built for at least `n` (the rest padded), else `n`.  A render context is
        built for a fixed count, and building one with its program costs seconds: a
        smaller batch (the last chunk, an export's retries) reuses a larger one."""
        kind = self._warp_key(spec, 0)[:-1]
        return min((k[-1] for k in self._renderers if k[:-1] == kind and k[-1] >= n), default=n)

    @staticmethod
    def _warp_key(spec: ObservationSpec, nworld: int) -> tuple:
        """A Warp renderer's key among the cached ones: what its context renders, then how
        many worlds."""
        return ("warp", spec.height, spec.width, spec.cameras, spec.needs_depth,
                spec.wants("segmentation"), nworld)

    # ---- observations -----------------------------------------------------------------
    def gripper_open(self, state: EnvState) -> np.ndarray:
        """RLBench's gripper_open flag from the finger opening."""
        return (np.asarray(state.obs["finger_q"])[:, 0] / FINGER_OPEN) > GRIPPER_OPEN_THRESHOLD

    def proprioception(self, state: EnvState) -> dict[str, np.ndarray]:
        """RLBench's low-dimensional fields of every world (see observation.py)."""
        obs = state.obs
        quat = np.asarray(obs["tip.quat"], np.float32)
        addr = self.scene.qpos_address
        fingers = [addr["finger_left"], addr["finger_right"]]
        return {
            "gripper_pose": np.concatenate([np.asarray(obs["tip.pos"], np.float32),
                                            quat[:, [1, 2, 3, 0]]], axis=1),
            "gripper_open": np.asarray(self.gripper_open(state), np.float32),
            "joint_positions": np.asarray(obs["arm_q"], np.float32),
            "joint_velocities": np.asarray(obs["arm_qd"], np.float32),
            "gripper_joint_positions": np.asarray(state.physics.qpos, np.float32)[:, fingers],
        }

    def observe(self, state: EnvState, spec: ObservationSpec) -> RLBenchObservation:
        """Render and assemble `spec`'s observation of every world of `state`."""
        t = time.perf_counter()
        if self.route(spec).on_device:
            cameras = self._warp_cameras(state, spec)
            self.frames += state.batch * len(spec.cameras)
        else:
            views = self._cpu_views(state, spec)
            cameras = {name: camera_observation(views[name], k, near, far, spec)
                       for name, (k, near, far) in camera_constants(self.scene.model,
                                                                     spec).items()}
            self.frames += int(np.sum(~np.asarray(state.done, bool))) * len(spec.cameras)
        self.render_s += time.perf_counter() - t
        return RLBenchObservation(
            cameras=cameras, **self.proprioception(state),
            instructions=tuple(self.task.descriptions(int(v))[0] for v in state.variation),
            labels=scene_labels(self.scene))

    def render(self, state: EnvState, camera: str = "front", width: int = 128,
               height: int = 128, worlds: np.ndarray | None = None) -> np.ndarray:
        """RGB frames (B, H, W, 3) of one camera for every world, or (len(worlds), ...) for
        the `worlds` given, with each world's colours (the CPU renderer, multisampled as
        RLBench's images).  Each world renders alone, so a subset's frames are the same."""
        from agnostos_mjx.render import CpuRenderer

        key = ("frames", width, height)
        if key not in self._renderers:
            for old in [k for k in self._renderers if k[0] == "frames"]:
                self._renderers.pop(old).close()
            self._renderers[key] = CpuRenderer(self.scene.model, width, height)
        p = state.physics
        pick = (lambda x: x) if worlds is None else (lambda x: x[np.asarray(worlds)])
        rgba = state.geom_rgba
        if rgba is not None and np.ndim(rgba) == 3:
            rgba = pick(np.asarray(rgba))
        return self._renderers[key].render(pick(np.asarray(p.qpos)), pick(np.asarray(p.mocap_pos)),
                                           pick(np.asarray(p.mocap_quat)), camera, rgba)

    def close(self) -> None:
        """Free every renderer made so far (GL contexts, Warp buffers)."""
        for renderer in self._renderers.values():
            close = getattr(renderer, "close", None)
            if close is not None:
                close()
        self._renderers.clear()
        self._programs.clear()
