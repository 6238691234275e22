"""Backend parity: native MuJoCo (float64) against MJX with impl="jax" on CPU
(float32), on lamp_on at batch 1.

MJX-jax compiles slowly on CPU,
so the horizon is kept short."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from agnostos_mjx.physics import make_backend
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.sim import control
from agnostos_mjx.sim.world import FINGER_OPEN
from agnostos_mjx.tasks import get_task

NSTEP = 40
OBJECT_TOL = 1e-4  # m, and per quaternion component
ARM_TOL = 2e-3  # rad


@functools.cache
def native_episodes() -> Episodes:
    return Episodes(get_task("lamp_on"), "native")


def object_frames(layout):
    """Sensor slices of the task's observed frames (everything but the robot)."""
    return [(name, layout.slice(name)) for name in layout.names
            if name.endswith((".pos", ".quat")) and not name.startswith("tip.")]


@pytest.mark.slow  # an MJX compile
def test_native_and_mjx_jax_agree_on_a_short_arm_motion():
    """Per-world step counts, and from the same reset state (key 3), 40 physics steps (0.2 s) of the same
    joint targets towards the lamp switch's hover point, through each backend's
    `run`.  Object frames (mocap-carried lamp bodies) must agree within 1e-4
    (m, and per quaternion component up to sign) at every step, arm joint
    positions within 2e-3 rad at every step (float32 vs float64 contact-free
    arm dynamics; measured ~1.8e-3 max, 4e-4 at the end), and both must return
    sensordata of the same shape."""
    ep = native_episodes()
    env = ep.reset(jax.random.PRNGKey(3)[None], [0])
    layout = ep.scene.layout
    actions = ep.expert_actions(env)
    q0 = np.asarray(env.obs["arm_q"], np.float64)
    path, duration, status = control.plan_arm(
        ep.kin, q0, actions.pos[:, 0].astype(np.float64), actions.quat[:, 0].astype(np.float64))
    assert status[0] == control.Status.OK
    arm = control.arm_targets_at(path, duration, (np.arange(NSTEP) + 1) * ep.dt)
    ctrl = np.concatenate([arm, np.full((1, NSTEP, 1), FINGER_OPEN)], -1)

    # Three copies of the world: the full horizon, a shorter move of its own, frozen.
    steps = np.array([NSTEP, 15, 0])
    state = env.physics.rows(np.zeros(3, int))
    ctrl3 = np.repeat(ctrl, 3, axis=0)
    native_state, native_sens = ep.backend.run(state, ctrl3, steps)
    mjx_backend = make_backend("jax", ep.scene.model)
    mjx_state, mjx_sens = mjx_backend.run(state, ctrl3, steps)
    native_sens, mjx_sens = np.asarray(native_sens), np.asarray(mjx_sens)

    assert native_sens.shape == mjx_sens.shape == (3, NSTEP, ep.scene.model.nsensordata)
    np.testing.assert_allclose(np.asarray(mjx_state.mocap_pos), native_state.mocap_pos,
                               atol=OBJECT_TOL)
    np.testing.assert_allclose(np.asarray(mjx_state.mocap_quat), native_state.mocap_quat,
                               atol=OBJECT_TOL)
    frames = object_frames(layout)
    assert frames
    for name, sl in frames:
        a, b = native_sens[:2, ..., sl], mjx_sens[:2, ..., sl]
        err = np.abs(a - b)
        if name.endswith(".quat"):
            err = np.minimum(err, np.abs(a + b))
        assert err.max() < OBJECT_TOL, f"{name}: native {a[0, -1]} vs mjx-jax {b[0, -1]}"

    # A world past its own end is frozen: its state is that after its 15th step (as if it
    # had run alone), its sensor rows repeat the 15th; a world with no steps is untouched.
    alone_state, alone_sens = ep.backend.run(env.physics, ctrl[:, :15])
    for sens, st, tol in ((native_sens, native_state, 0.0), (mjx_sens, mjx_state, ARM_TOL)):
        np.testing.assert_allclose(np.asarray(st.qpos)[1], alone_state.qpos[0], atol=tol)
        np.testing.assert_allclose(np.asarray(st.ctrl)[1], ctrl[0, 14], atol=1e-6)
        np.testing.assert_allclose(sens[1, 15:], np.broadcast_to(sens[1, 14], (NSTEP - 15,
                                                                               sens.shape[-1])))
        np.testing.assert_allclose(np.asarray(st.qpos)[2], env.physics.qpos[0], atol=1e-6)
        np.testing.assert_allclose(np.asarray(st.ctrl)[2], env.physics.ctrl[0], atol=1e-6)
    np.testing.assert_array_equal(native_sens[1, :15], alone_sens[0])
    native_state = native_state.rows(np.array([0]))
    mjx_state = mjx_state.rows(np.array([0]))
    native_sens, mjx_sens = native_sens[:1], mjx_sens[:1]

    arm_q = layout.slice("arm_q")
    moved = np.abs(native_sens[0, -1, arm_q] - q0[0]).max()
    assert moved > 0.05, "the control plan should move the arm noticeably"
    assert np.abs(native_sens[..., arm_q] - mjx_sens[..., arm_q]).max() < ARM_TOL
    arm_qpos = ep.scene.arm_qpos
    assert np.abs(native_state.qpos[:, arm_qpos] - np.asarray(mjx_state.qpos)[:, arm_qpos]
                  ).max() < ARM_TOL


@pytest.mark.slow
@pytest.mark.mjx_cpu  # MJX-jax's own physics compiled on the CPU
def test_lamp_on_expert_succeeds_on_both_backends():
    """The lamp_on expert episode (key 0, batch 1) ends in SUCCESS on the native
    and the MJX-jax backend (about a minute of MJX compiles on CPU)."""
    outcomes = {}
    for backend in ("native", "jax"):
        ep = native_episodes() if backend == "native" else Episodes(get_task("lamp_on"), "jax")
        env = ep.reset(jax.random.PRNGKey(0)[None], [0])
        actions = ep.expert_actions(env)
        for k in range(actions.pos.shape[1]):
            env, _ = ep.step(env, jax.tree.map(lambda x, k=k: x[:, k], actions))
        outcomes[backend] = Outcome(int(env.outcome[0]))
    assert outcomes == {"native": Outcome.SUCCESS, "jax": Outcome.SUCCESS}


def test_warp_steps_run_with_the_garbage_collector_paused(monkeypatch):
    """A collection during Warp's graph capture can unload an XLA module and break the
    capture, so the warp path must run (and finish) its step with gc off; other
    backends leave gc alone."""
    import gc

    from agnostos_mjx.physics import CAPABILITIES
    from agnostos_mjx.physics.mjx_backend import MjxBackend, gc_paused

    ep = native_episodes()
    env = ep.reset(jax.random.PRNGKey(3)[None], [0])
    backend = MjxBackend(ep.scene.model, impl="jax")
    seen = []

    def fake_runner(state, ctrl, steps):
        seen.append(gc.isenabled())
        return state, ctrl

    monkeypatch.setattr(backend, "_runner", lambda batch, nstep: fake_runner)
    ctrl = np.zeros((1, 2, ep.scene.model.nu))
    backend.run(env.physics, ctrl)
    backend.capabilities = CAPABILITIES["warp"]  # a backend that captures CUDA graphs
    backend.run(env.physics, ctrl)
    assert seen == [True, False] and gc.isenabled()
    with pytest.raises(RuntimeError), gc_paused():  # restored after an error too
        raise RuntimeError
    assert gc.isenabled()
    gc.disable()
    try:
        with gc_paused():
            pass
        assert not gc.isenabled()  # a caller that had it off keeps it off
    finally:
        gc.enable()


def test_auto_backend_uses_warp_only_for_large_batches(monkeypatch):
    """Native threads beat MJX-warp below a few thousand
    worlds, so `auto` picks warp only from WARP_MIN_BATCH worlds and only where warp runs."""
    import agnostos_mjx.physics as physics

    monkeypatch.setattr(physics, "warp_available", lambda: True)
    assert physics.resolve_backend("auto", 75) == "native"
    assert physics.resolve_backend("auto") == "native"
    assert physics.resolve_backend("auto", physics.WARP_MIN_BATCH) == "warp"
    assert physics.resolve_backend("warp", 1) == "warp"
    monkeypatch.setattr(physics, "warp_available", lambda: False)
    assert physics.resolve_backend("auto", 10**6) == "native"
    with pytest.raises(ValueError, match="unknown backend"):
        physics.resolve_backend("mjx")


@pytest.mark.slow  # parity, as the rest of this file's slow tests
def test_device_reachability_matches_the_host_check():
    """The jitted reachability scan (MJX backends' reset on an accelerator) accepts and
    rejects the same scenes as the numpy check, including a key action out of reach."""

    ep = native_episodes()
    keys = jax.vmap(lambda e: jax.random.fold_in(jax.random.PRNGKey(0), e))(np.arange(6))
    env = ep.reset(keys, np.zeros(6, np.int32))
    actions = ep.expert_actions(env)
    pos = np.array(actions.pos)
    pos[3, 1] = [0.7, 0.5, 1.7]  # a corner of the bounds the arm cannot reach
    q = np.asarray(env.obs["arm_q"], np.float64)
    host = control.reachable(ep.kin, q, pos, actions.quat, actions.valid)
    device = jax.jit(functools.partial(control.reachable, ep.kin))(q, pos, actions.quat,
                                                                  actions.valid)
    np.testing.assert_array_equal(np.asarray(device), host)
    assert host.sum() == 5 and not host[3]
