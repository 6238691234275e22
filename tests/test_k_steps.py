"""K physics steps per device-loop iteration (runtime/phase.py's `k_steps`; issue 26).

Every world steps K times in one physics call, the conditions are then checked over the K
sensor rows, and a world that ended inside the chunk is set back to its state at its own
end.  That must give the one-step loop's result bit for bit: outcomes, step counts (first
success / failure steps), the frozen worlds' states, sensors and condition carries.  Here
on MJX-jax's own physics (a small scene, so it compiles in seconds); tests/test_key_action.py
checks whole key actions of real tasks over native physics.  The direct MuJoCo Warp call
(physics/warp_chunk.py) is checked where warp-lang is installed.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from agnostos_mjx.physics.base import PhysicsState, StepData
from agnostos_mjx.physics.mjx_backend import MjxBackend
from agnostos_mjx.runtime.phase import DevicePhases
from agnostos_mjx.runtime.state import EnvState

SCENE = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <geom type="plane" size="2 2 .1"/>
    <body name="box" pos="0 0 0.2">
      <joint name="slide" type="slide" axis="1 0 0"/>
      <joint name="lift" type="slide" axis="0 0 1"/>
      <geom type="box" size=".05 .05 .05" mass="1"/>
    </body>
  </worldbody>
  <actuator><position joint="slide" kp="60" kv="4"/></actuator>
  <sensor><jointpos joint="slide"/><jointpos joint="lift"/><jointvel joint="slide"/></sensor>
</mujoco>
"""
# Per world: where the slide is driven, the phase's steps (one world does not move), the
# variation (which sets the success distance).  World 0 succeeds, world 1 fails (too fast),
# world 2 has no steps, world 3 runs out of steps, world 4 succeeds too.
GOALS = np.array([0.3, 1.5, 0.2, 0.05, 0.45], np.float32)
STEPS = np.array([60, 50, 0, 23, 47], np.int32)
VARIATIONS = np.array([0, 0, 1, 1, 1], np.int32)


def condition_step(count, row, attached, variation):
    """Success after the slide has stayed past its variation's mark for 3 steps; failure
    when the slide moves faster than 2 m/s.  The carry counts the steps past the mark."""
    past = row[0] > 0.12 + 0.05 * variation
    count = jnp.where(past, count + 1, 0)
    return count, count >= 3, jnp.abs(row[2]) > 2.0


def _state(model: mujoco.MjModel, b: int, stop_at_success: bool) -> EnvState:
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    tile = lambda x: jnp.asarray(np.repeat(np.asarray(x, np.float32)[None], b, 0))  # noqa: E731
    physics = PhysicsState(qpos=tile(d.qpos), qvel=tile(d.qvel), act=tile(d.act),
                           ctrl=tile(d.ctrl), mocap_pos=tile(d.mocap_pos),
                           mocap_quat=tile(d.mocap_quat),
                           eq_active=jnp.zeros((b, model.neq), bool),
                           eq_data=tile(model.eq_data), time=jnp.zeros(b, jnp.float32))
    zeros = jnp.zeros(b, jnp.int32)
    return EnvState(physics=physics, data=tile(d.sensordata), attached=jnp.zeros((b, 0), bool),
                    carry=zeros, variation=jnp.asarray(VARIATIONS), gripper=zeros,
                    outcome=zeros, key_actions=zeros, sim_steps=zeros, world_steps=zeros,
                    geom_rgba=zeros,
                    initial_data=tile(d.sensordata), layout=None,
                    stop_at_success=stop_at_success)


def ctrl_at(t: jax.Array) -> jax.Array:
    """(T,) step indices -> (B, T, nu): each world's goal, ramped in over 20 steps."""
    ramp = jnp.minimum(1.0, (t + 1) / 20.0)
    return (jnp.asarray(GOALS)[:, None] * ramp[None, :])[..., None]


def _run(dev, k: int, state: EnvState) -> dict:
    phases = DevicePhases(dev, condition_step, k)
    run = jax.jit(lambda s, n: phases.run_phase(s, n, ctrl_at)[:3])
    new, s_at, f_at = run(state, jnp.asarray(STEPS))
    out = {"success_at": s_at, "failure_at": f_at, "data": new.data, "carry": new.carry}
    out.update({f"physics.{f}": getattr(new.physics, f) for f in ("qpos", "qvel", "ctrl", "time")})
    return jax.tree.map(np.asarray, out)


@pytest.mark.slow
@pytest.mark.parametrize("stop_at_success", [True, False])
def test_k_steps_equal_one_step_on_mjx_jax(stop_at_success: bool) -> None:
    model = mujoco.MjModel.from_xml_string(SCENE)
    b = len(GOALS)
    dev = MjxBackend(model, impl="jax").device_physics(b)
    state = _state(model, b, stop_at_success)
    one = _run(dev, 1, state)
    # the scene does what the comments above say, so each kind of end is covered
    assert one["success_at"][0] >= 0 and one["failure_at"][0] < 0
    assert one["failure_at"][1] >= 0
    assert one["success_at"][2] < 0 and one["failure_at"][2] < 0
    assert one["success_at"][3] < 0 and one["failure_at"][3] < 0
    assert one["success_at"][4] >= 0
    ends = [one["success_at"][0], one["failure_at"][1], one["success_at"][4]]
    assert any(e % 3 != 2 for e in ends) and any(e % 4 != 3 for e in ends)  # mid-chunk ends
    np.testing.assert_array_equal(one["physics.qpos"][2], np.asarray(state.physics.qpos[2]))
    np.testing.assert_allclose(one["physics.time"][3], STEPS[3] * model.opt.timestep, rtol=1e-5)
    for k in (3, 4) if stop_at_success else (4,):
        many = _run(dev, k, state)
        for name, value in one.items():
            np.testing.assert_array_equal(many[name], value, err_msg=f"K={k}: {name}")


@pytest.mark.slow
def test_direct_warp_chunk_equals_its_single_steps_and_native_physics() -> None:
    """MuJoCo Warp stepped K times in one FFI call (on this CPU: Warp's CPU kernels, built
    on first use in about a minute) equals K calls of one step bit for bit, and follows
    MuJoCo's C physics and kinematics."""
    pytest.importorskip("warp")
    from agnostos_mjx.physics.warp_chunk import warp_chunk

    model = mujoco.MjModel.from_xml_string(SCENE)
    b, k = len(GOALS), 5
    state = _state(model, b, True).physics
    chunk = warp_chunk(model, b, 64 * b, 64)
    ctrl = jnp.swapaxes(ctrl_at(jnp.arange(k)), 0, 1)
    start = lambda s: StepData.start(s, model.nsensordata)  # noqa: E731
    last, rows = jax.jit(lambda s, u: chunk(start(s), u))(state, ctrl)
    d = start(state)
    one_by_one = []
    for i in range(k):
        d, row = jax.jit(lambda d, u: chunk(d, u))(d, ctrl[i:i + 1])
        one_by_one.append(np.asarray(row.qpos[0]))
    np.testing.assert_array_equal(np.stack(one_by_one), np.asarray(rows.qpos))
    np.testing.assert_array_equal(np.asarray(d.qpos), np.asarray(last.qpos))
    native = mujoco.MjData(model)
    mujoco.mj_forward(model, native)
    for i in range(k):
        native.ctrl[:] = np.asarray(ctrl[i, 0])
        mujoco.mj_step(model, native)
    np.testing.assert_allclose(np.asarray(rows.qpos[-1, 0]), native.qpos, atol=1e-5)
    np.testing.assert_allclose(np.asarray(rows.sensordata[-1, 0]), native.sensordata, atol=1e-4)
    # the body frames from MuJoCo Warp's kinematics (the welds' poses) at the last state
    xpos, xquat = jax.jit(chunk.poses)(last)
    mujoco.mj_kinematics(model, native)
    np.testing.assert_allclose(np.asarray(xpos[0]), native.xpos, atol=1e-5)
    np.testing.assert_allclose(np.asarray(xquat[0]), native.xquat, atol=1e-5)
