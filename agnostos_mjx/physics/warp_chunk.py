"""K MuJoCo Warp physics steps per JAX call: the device key action's fast path on a GPU.

MJX's `impl="warp"` step is one XLA FFI call per physics step, and every FFI call runs a
Python callback on the host before Warp replays its CUDA graph.  Here one FFI call
runs K steps: it copies the batch's state into a MuJoCo Warp `Data` kept on the device for
this (model, batch), steps it K times with per-step controls from a (K, B, nu) array, and
writes each step's state and sensor rows out.  On a GPU the whole call (copies, K steps,
records) is one CUDA graph, captured once per call site (graph mode WARP_STAGED, see
`_graph_mode`) and replayed.  It is faster per key action than `mjx.step`
(docs/performance.md), with native MuJoCo's outcomes where `mjx.step` in graph
mode WARP gave wrong ones.

The call is pure in its inputs: everything the next step depends on (qpos, qvel, time, the
solver's warm start, mocap poses, weld state and data) goes in, so the kept `Data` is only a
workspace (contacts, constraint rows, derived quantities are recomputed every step).
Scenes with actuator activations, sleeping or delay histories would carry more state and
are refused (`supported`), as MJX's own step then remains the path.
"""

import functools
import hashlib
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import warp as wp
from mujoco.mjx.third_party import mujoco_warp as mjw
from mujoco.mjx.third_party.mujoco_warp._src.types import vec12

from agnostos_mjx.physics.base import StepData, for_warp


def supported(model: mujoco.MjModel) -> str | None:
    """None when the K-step call carries all of `model`'s state, else why not."""
    if model.na:
        return "actuator activations"
    if model.opt.enableflags & mujoco.mjtEnableBit.mjENBL_SLEEP:
        return "sleeping"
    if getattr(model, "nhistory", 0):
        return "delay histories"
    return None


@wp.kernel
def _take_row(k: int, rows: wp.array3d(dtype=float), out: wp.array2d(dtype=float)):
    w, j = wp.tid()
    out[w, j] = rows[k, w, j]


@wp.kernel
def _put_row(k: int, src: wp.array2d(dtype=float), rows: wp.array3d(dtype=float)):
    w, j = wp.tid()
    rows[k, w, j] = src[w, j]


@wp.kernel
def _put_scalar_row(k: int, src: wp.array(dtype=float), rows: wp.array2d(dtype=float)):
    w = wp.tid()
    rows[k, w] = src[w]


def workspace(model: mujoco.MjModel, batch: int, naconmax: int, njmax: int) -> tuple[Any, Any]:
    """MuJoCo Warp's (Model, Data) for `batch` worlds of `model`, sized as the run sizes them
    (the kernels Warp builds depend on these sizes, so warp_build dry-runs the same)."""
    model = for_warp(model)
    mw = mjw.put_model(model, batch_sizes={"eq_data": batch} if model.neq else None)
    dw = mjw.put_data(model, mujoco.MjData(model), nworld=batch, naconmax=naconmax, njmax=njmax)
    return mw, dw


def steps_function(model: mujoco.MjModel, mw: Any, dw: Any, batch: int) -> Callable:
    """The function the K-step FFI call runs (a plain function: Warp reads its annotations)."""
    m, d, b = mw, dw, batch

    def steps(qpos: wp.array2d(dtype=float), qvel: wp.array2d(dtype=float),
              time: wp.array(dtype=float), warmstart: wp.array2d(dtype=float),
              ctrl: wp.array3d(dtype=float), mocap_pos: wp.array2d(dtype=wp.vec3),
              mocap_quat: wp.array2d(dtype=wp.quat), eq_active: wp.array2d(dtype=bool),
              eq_data: wp.array2d(dtype=vec12),
              qpos_rows: wp.array3d(dtype=float), qvel_rows: wp.array3d(dtype=float),
              time_rows: wp.array2d(dtype=float), sensor_rows: wp.array3d(dtype=float),
              warmstart_out: wp.array2d(dtype=float)):
        wp.copy(d.qpos, qpos)
        wp.copy(d.qvel, qvel)
        wp.copy(d.time, time)
        wp.copy(d.qacc_warmstart, warmstart)
        if model.nmocap:
            wp.copy(d.mocap_pos, mocap_pos)
            wp.copy(d.mocap_quat, mocap_quat)
        if model.neq:
            wp.copy(d.eq_active, eq_active)
            wp.copy(m.eq_data, eq_data)
        for k in range(ctrl.shape[0]):
            if model.nu:
                wp.launch(_take_row, dim=(b, model.nu), inputs=[k, ctrl, d.ctrl])
            mjw.step(m, d)
            wp.launch(_put_row, dim=(b, model.nq), inputs=[k, d.qpos, qpos_rows])
            wp.launch(_put_row, dim=(b, model.nv), inputs=[k, d.qvel, qvel_rows])
            wp.launch(_put_scalar_row, dim=b, inputs=[k, d.time, time_rows])
            wp.launch(_put_row, dim=(b, model.nsensordata), inputs=[k, d.sensordata, sensor_rows])
        wp.copy(warmstart_out, d.qacc_warmstart)

    return steps


def poses_function(model: mujoco.MjModel, mw: Any, dw: Any) -> Callable:
    """The function of the poses' FFI call: the body frames at the given qpos."""
    m, d = mw, dw

    def poses(qpos: wp.array2d(dtype=float), mocap_pos: wp.array2d(dtype=wp.vec3),
              mocap_quat: wp.array2d(dtype=wp.quat), xpos: wp.array2d(dtype=wp.vec3),
              xquat: wp.array2d(dtype=wp.quat)):
        wp.copy(d.qpos, qpos)
        if model.nmocap:
            wp.copy(d.mocap_pos, mocap_pos)
            wp.copy(d.mocap_quat, mocap_quat)
        mjw.kinematics(m, d)
        wp.copy(xpos, d.xpos)
        wp.copy(xquat, d.xquat)

    return poses


def model_digest(model: mujoco.MjModel) -> str:
    """A short hash of the compiled model's contents (the same scene gives the same digest
    in every process)."""
    buffer = np.empty(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    return hashlib.sha1(buffer.tobytes()).hexdigest()[:16]


def _named(fn: Callable, name: str) -> Callable:
    """`fn` under a name that is the same in every process for the same scene and sizes.

    Warp names an FFI target after the function's qualified name plus a per-process counter,
    and that name is part of the XLA program: with one shared qualname, a process's second
    scene got `..._1`, so the key-action programs differed with the order tasks ran in and
    JAX's persistent cache missed them in every new process.  A name per (scene, sizes) makes
    the counter 0 and the program the same in every process."""
    fn.__qualname__ = fn.__name__ = name
    return fn


class WarpChunk:
    """The K-step call for one scene and batch size (a device workspace of `batch` worlds).

    `__call__(d: StepData, ctrl (K, B, nu)) -> (StepData after the K steps, rows)`, rows a
    StepData whose qpos, qvel, act, ctrl, time and sensordata hold the values after each
    step along a leading K axis, as MJX's step would give them one step at a time."""

    def __init__(self, model: mujoco.MjModel, batch: int, naconmax: int, njmax: int,
                 graph_mode: str = "auto"):
        why = supported(model)
        if why:
            raise ValueError(f"the K-step Warp call does not carry {why}")
        self.model = model
        self.batch = batch
        self.mw, self.dw = workspace(model, batch, naconmax, njmax)
        mode = _graph_mode(graph_mode)
        key = f"{model_digest(model)}_{batch}_{naconmax}_{njmax}_{mode.name}"
        steps = _named(steps_function(model, self.mw, self.dw, batch), f"agnostos_steps_{key}")
        poses = _named(poses_function(model, self.mw, self.dw), f"agnostos_poses_{key}")
        self._call = wp.jax_callable(steps, num_outputs=5, graph_mode=mode, vmap_method=None)
        self._poses = wp.jax_callable(poses, num_outputs=2, graph_mode=mode, vmap_method=None)

    def _mocap(self, d: StepData) -> tuple[jax.Array, jax.Array]:
        # Zero-size arrays do not cross the FFI boundary; a scene without mocap bodies (or
        # welds) passes one dummy row that the call ignores.
        if self.model.nmocap:
            return d.mocap_pos, d.mocap_quat
        b = self.batch
        return jnp.zeros((b, 1, 3), jnp.float32), jnp.zeros((b, 1, 4), jnp.float32)

    def poses(self, d: StepData) -> tuple[jax.Array, jax.Array]:
        """(xpos (B, nbody, 3), xquat (B, nbody, 4)) at d's qpos, as mjx.kinematics gives."""
        dims = {"xpos": (self.batch, self.model.nbody), "xquat": (self.batch, self.model.nbody)}
        return tuple(self._poses(d.qpos, *self._mocap(d), output_dims=dims))

    def __call__(self, d: StepData, ctrl: jax.Array) -> tuple[StepData, StepData]:
        k, b, m = ctrl.shape[0], self.batch, self.model
        mocap_pos, mocap_quat = self._mocap(d)
        eq_active = d.eq_active if m.neq else jnp.zeros((b, 1), bool)
        eq_data = d.eq_data if m.neq else jnp.zeros((b, 1, 12), jnp.float32)
        dims = {"qpos_rows": (k, b, m.nq), "qvel_rows": (k, b, m.nv), "time_rows": (k, b),
                "sensor_rows": (k, b, m.nsensordata), "warmstart_out": (b, m.nv)}
        qpos, qvel, time, sens, warm = self._call(
            d.qpos, d.qvel, d.time, d.qacc_warmstart, ctrl, mocap_pos, mocap_quat, eq_active,
            eq_data, output_dims=dims)
        last = d.replace(qpos=qpos[-1], qvel=qvel[-1], ctrl=ctrl[-1], time=time[-1],
                         sensordata=sens[-1], qacc_warmstart=warm)
        acts = jnp.broadcast_to(d.act, (k, *d.act.shape))  # no activations (`supported`)
        return last, last.replace(qpos=qpos, qvel=qvel, act=acts, ctrl=ctrl, time=time,
                                  sensordata=sens)


def _graph_mode(name: str) -> Any:
    """How Warp replays the call's CUDA graph.  `auto`: WARP_STAGED on a GPU: the graph is
    captured once per call site against Warp's own staging buffers, and each call copies the
    (small) inputs in and outputs out.  Graph mode WARP instead captures anew for every new
    set of XLA buffer addresses, which the key action's program gets afresh at each run:
    a capture of K steps each time.  On a CPU Warp runs the call's kernels directly (NONE)."""
    if name == "auto":
        on_gpu = any(dev.platform == "gpu" for dev in jax.devices())
        name = "WARP_STAGED" if on_gpu else "NONE"
    return getattr(wp.JaxCallableGraphMode, name)


@functools.lru_cache(maxsize=32)
def warp_chunk(model: mujoco.MjModel, batch: int, naconmax: int, njmax: int,
               graph_mode: str = "auto") -> WarpChunk:
    """One workspace per (scene, batch size, graph mode) and process."""
    return WarpChunk(model, batch, naconmax, njmax, graph_mode)


__all__ = ["WarpChunk", "model_digest", "poses_function", "steps_function", "supported",
           "warp_chunk", "workspace"]
