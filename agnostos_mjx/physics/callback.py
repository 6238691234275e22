"""Native MuJoCo behind the device boundary (`DevicePhysics`) through `jax.pure_callback`.

The key action's device program (runtime/phase.py's DevicePhases: a while loop of physics
steps with the conditions checked after each) normally steps MJX.  On a CPU, compiling
MJX-jax's step into that program costs minutes per task (docs/performance.md), so this module lets the same program step MuJoCo's C physics instead, one host
callback per step: the device path's control flow (masks, freezing, in-loop conditions,
welds from the kinematics) then compiles in seconds and can be compared with the host path
in the default test suite.  Not a fast path: every step leaves the program.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from agnostos_mjx.physics.base import PhysicsState, StepData
from agnostos_mjx.physics.mjx_backend import DevicePhysics
from agnostos_mjx.physics.native import NativeBackend
from agnostos_mjx.sim.world import posed_data


def callback_physics(model: mujoco.MjModel, batch: int) -> DevicePhysics:
    """`DevicePhysics` of `batch` worlds whose step and kinematics run natively on the host."""
    native = NativeBackend(model, nthread=1)

    def host_state(d: StepData) -> PhysicsState:
        return PhysicsState(**{f: np.asarray(getattr(d, f), np.float64 if f != "eq_active" else bool)
                               for f in ("qpos", "qvel", "act", "ctrl", "mocap_pos",
                                         "mocap_quat", "eq_active", "eq_data", "time")})

    def step_on_host(d: StepData, ctrl: np.ndarray) -> tuple:
        state, sens = native.run(host_state(d), np.asarray(ctrl, np.float64)[:, None])
        out = (state.qpos, state.qvel, state.act, state.ctrl, state.time, sens[:, -1])
        return tuple(np.asarray(x, np.float32) for x in out)

    def poses_on_host(d: StepData) -> tuple:
        state = host_state(d)
        frames = [posed_data(model, state, w) for w in range(batch)]
        return (np.stack([f.xpos for f in frames]).astype(np.float32),
                np.stack([f.xquat for f in frames]).astype(np.float32))

    def load(state: PhysicsState) -> tuple[None, StepData]:
        return None, StepData.start(state, model.nsensordata)

    def step(m: None, d: StepData, ctrl: jax.Array) -> StepData:
        shapes = tuple(jax.ShapeDtypeStruct(x.shape, jnp.float32)
                       for x in (d.qpos, d.qvel, d.act, d.ctrl, d.time, d.sensordata))
        qpos, qvel, act, ctrl, time, sens = jax.pure_callback(step_on_host, shapes, d, ctrl)
        return d.replace(qpos=qpos, qvel=qvel, act=act, ctrl=ctrl, time=time, sensordata=sens)

    def poses(m: None, d: StepData) -> tuple[jax.Array, jax.Array]:
        shapes = (jax.ShapeDtypeStruct((batch, model.nbody, 3), jnp.float32),
                  jax.ShapeDtypeStruct((batch, model.nbody, 4), jnp.float32))
        return jax.pure_callback(poses_on_host, shapes, d)

    return DevicePhysics(load=load, step=step, poses=poses, save=lambda state, d: d.saved(state))
