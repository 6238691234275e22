"""`ThreadedCpuRenderer`: several `CpuRenderer` s, each in its own persistent thread,
rendering contiguous chunks of the worlds in parallel; `cpu_renderer` picks it or a plain
CpuRenderer from `render_threads()` (``AGNOSTOS_RENDER_THREADS``)."""

from __future__ import annotations

import atexit
import queue
import threading
from collections.abc import Sequence
from concurrent.futures import Future
from typing import Any, Self

import mujoco
import numpy as np

from agnostos_mjx.infra.settings import RENDER_THREADS, usable_cores
from agnostos_mjx.render.common import CameraImages, camera_names, clip_planes, unknown_camera
from agnostos_mjx.render.cpu import CpuRenderer

RENDER_THREADS_ENV = RENDER_THREADS.name
MAX_RENDER_THREADS = 8


def render_threads() -> int:
    """Threads for CPU rendering: ``AGNOSTOS_RENDER_THREADS`` if set (>= 1), else the usable
    cores (CPU affinity) capped at ``MAX_RENDER_THREADS``."""
    threads = RENDER_THREADS.get_int()
    if threads is not None:
        return max(1, threads)
    return max(1, min(usable_cores(), MAX_RENDER_THREADS))


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
            raise unknown_camera(self._model, camera)
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
