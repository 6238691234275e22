"""The key action's device program (runtime/phase.py's DevicePhases) against its host
path (HostPhases, the recording path) on MJX-jax at tiny batch: same outcomes, poses within tolerance, and a
world frozen past its own end (issue 13).  MJX compiles on CPU take minutes per task, so
the per-task cases are slow tests; `python -m pytest -m slow tests/test_key_action.py`."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from agnostos_mjx.runtime.env import SETTLE_STEPS, Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.sim import control
from agnostos_mjx.sim.actions import KeyActions
from agnostos_mjx.tasks import get_task

POS_TOL = 0.01  # m: tip and object frames after the episode
STEP_TOL = 3  # physics steps: the success step may move by float32 round-off in the plan


def _keys(n: int):
    return jax.vmap(lambda e: jax.random.fold_in(jax.random.PRNGKey(0), e))(np.arange(n))


def _constructed_actions(ep: Episodes, env) -> list[KeyActions]:
    """The expert's key actions with two constructed cases: world 1 has nothing valid from
    its second action on (NO_ACTION, then frozen), world 2's first target is out of the
    workspace."""
    expert = ep.expert_actions(env)
    steps = []
    for k in range(expert.pos.shape[1]):
        pos, quat, grip, valid = (np.array(x[:, k]) for x in
                                  (expert.pos, expert.quat, expert.gripper, expert.valid))
        if k >= 1:
            valid[1] = False
        if k == 0:
            pos[2] = (0.2, 0.0, 2.5)
        steps.append(KeyActions(pos, quat, grip, valid))
    return steps


@pytest.mark.slow  # a trace of the whole device program
@pytest.mark.parametrize("task", ["lamp_on", "phone_on_base"])
def test_device_step_traces_with_the_documented_shapes(task):
    """The device program (with and without grasp welds) traces, at both stop modes, to an
    EnvState of the input's shapes and dtypes: a cheap guard for the default suite (no
    compile, no physics)."""
    ep = Episodes(get_task(task), "jax")
    env = ep.reset(_keys(2), np.zeros(2, np.int32))
    expert = ep.expert_actions(env)
    acts = KeyActions(*(jax.numpy.asarray(np.asarray(x)[:, 0]) for x in
                        (expert.pos, expert.quat, expert.gripper, expert.valid)))
    program = ep.device_program(2)
    for stop in (True, False):
        dev = env.replace(stop_at_success=stop).to_device()
        plan = jax.eval_shape(ep.device_plans.plan, dev.data[:, ep.spec.arm_q], acts.pos, acts.quat)
        out = jax.eval_shape(program, dev, acts, plan)
        shapes = jax.tree.map(lambda x: (x.shape, x.dtype), out)
        assert shapes == jax.tree.map(lambda x: (x.shape, x.dtype), dev)
        assert out.stop_at_success is stop


def _assert_same_episodes(ep: Episodes, host, dev) -> None:
    """The constructed batch ends alike on both paths: outcomes, key actions, grasps, step
    counts within STEP_TOL, tip and object frames within POS_TOL."""
    assert Outcome(int(host.outcome[0])) == Outcome.SUCCESS, "the expert world succeeds"
    assert Outcome(int(host.outcome[1])) == Outcome.NO_ACTION
    assert Outcome(int(host.outcome[2])) == Outcome.OUT_OF_WORKSPACE
    np.testing.assert_array_equal(dev.outcome, host.outcome)
    np.testing.assert_array_equal(dev.key_actions, host.key_actions)
    np.testing.assert_array_equal(dev.attached, host.attached)
    assert np.abs(dev.sim_steps - host.sim_steps).max() <= STEP_TOL
    # Native runs each world its own phase lengths; the device steps every world (a finished
    # one frozen) until the last one ends.
    assert (host.world_steps >= host.sim_steps).all()
    assert len(set(np.asarray(dev.world_steps).tolist())) == 1
    assert int(dev.world_steps[0]) >= int(np.max(dev.sim_steps))
    layout = ep.scene.layout
    for name in ("tip", *ep.task.observed_frames):
        key = f"{name}.pos"
        if key in layout.names:
            err = np.abs(np.asarray(dev.obs[key]) - np.asarray(host.obs[key])).max()
            assert err < POS_TOL, f"{ep.task.name}: {key} differs by {err:.4f} m"


def _run(ep: Episodes, env, steps: list[KeyActions], record: bool):
    history = []
    for action in steps:
        env, _ = ep.step(env, action, record=record)
        history.append(jax.tree.map(np.asarray, env.physics))
    return env, history


@pytest.mark.slow
@pytest.mark.mjx_cpu  # MJX-jax's own physics compiled on the CPU
@pytest.mark.parametrize("task", ["lamp_on", "phone_on_base", "open_drawer"])
def test_device_step_matches_host_path(task):
    ep = Episodes(get_task(task), "jax")
    b = 3
    env = ep.reset(_keys(b), np.zeros(b, np.int32))
    steps = _constructed_actions(ep, env)
    host, _ = _run(ep, env, steps, record=True)
    dev, history = _run(ep, env, steps, record=False)

    _assert_same_episodes(ep, host, dev)

    # Frozen worlds: world 1 never moves after its first key action, world 2 never moves,
    # and every world's clock stops at its own last step.
    for later in history[1:]:
        np.testing.assert_array_equal(later.qpos[1], history[0].qpos[1])
    np.testing.assert_array_equal(history[-1].qpos[2], env.physics.qpos[2].astype(np.float32))
    np.testing.assert_allclose(history[-1].time, (SETTLE_STEPS + dev.sim_steps) * ep.dt, atol=1e-4)


@pytest.mark.parametrize("task", ["lamp_on", *(pytest.param(t, marks=pytest.mark.slow)
                                              for t in ("phone_on_base", "open_drawer"))])
def test_device_program_matches_host_path_on_native_physics(task):
    """The key action's two boundaries (default suite): the device program (DevicePhases:
    while loop, in-loop conditions, frozen worlds, welds from traced kinematics) stepping
    MuJoCo's C physics through host callbacks, against the host path (HostPhases) on the
    same physics.  Same outcomes, key actions and grasps; poses within 1 cm.  MJX-jax's own
    physics is compared in the slow test above (its compile takes CPU-minutes per task)."""
    from agnostos_mjx.physics.callback import callback_physics

    ep = Episodes(get_task(task), "native")
    b = 3
    env = ep.reset(_keys(b), np.zeros(b, np.int32))
    steps = _constructed_actions(ep, env)
    host, _ = _run(ep, env, steps, record=False)
    physics = callback_physics(ep.scene.model, b)
    dev = env
    for action in steps:
        dev = ep.step_on_device(dev, action, physics=physics)

    _assert_same_episodes(ep, host, dev)


@pytest.mark.slow
def test_several_steps_per_iteration_change_nothing():
    """K masked physics steps per while-loop iteration (warp's host/device overlap) give
    the one-step program's result bit for bit: outcomes, step counts, frozen worlds and
    physics state (the device program over native physics, so it compiles in seconds)."""
    from agnostos_mjx.physics.callback import callback_physics

    ep = Episodes(get_task("phone_on_base"), "native")
    b = 3
    env = ep.reset(_keys(b), np.zeros(b, np.int32))
    steps = _constructed_actions(ep, env)[:3]
    physics = callback_physics(ep.scene.model, b)
    runs = {}
    for unroll in (1, 3):
        state = env
        for action in steps:
            state = ep.step_on_device(state, action, physics=physics, unroll=unroll)
        runs[unroll] = jax.tree.map(np.asarray, state)
    one, three = runs[1], runs[3]
    assert (one.sim_steps > 0).any()
    # Only the steps run differ: a K-step iteration runs up to K - 1 past the last end.
    assert (three.world_steps >= one.world_steps).all()
    one, three = (s.replace(world_steps=0) for s in (one, three))
    for a, b_ in zip(jax.tree.leaves(one), jax.tree.leaves(three), strict=True):
        np.testing.assert_array_equal(a, b_)


def test_planner_choice():
    """`--planner`: auto is the numpy planner on a CPU-only machine (the recorded results),
    the jitted float32 planner runs the same episodes next to native physics (same outcomes
    on an easy task; the paths differ by float32 rounding), and a bad name is refused."""
    from agnostos_mjx.runtime.env import resolve_planner

    assert resolve_planner("auto") == ("host" if jax.default_backend() == "cpu" else "device")
    with pytest.raises(ValueError, match="unknown planner"):
        resolve_planner("gpu")
    b = 3
    outcomes = {}
    for planner in ("host", "device"):
        ep = Episodes(get_task("lamp_on"), "native", planner=planner)
        assert ep.planner == planner
        env, _ = _run(ep, ep.reset(_keys(b), np.zeros(b, np.int32)),
                      _expert_steps(ep, ep.reset(_keys(b), np.zeros(b, np.int32))), False)
        outcomes[planner] = np.asarray(env.outcome)
    np.testing.assert_array_equal(outcomes["host"], outcomes["device"])
    assert (outcomes["host"] == Outcome.SUCCESS).all()
    # The device's Cartesian segments stop as the host's do (each world once within a tenth
    # of the tolerance): the same paths up to float32 rounding.
    start = ep.reset(_keys(b), np.zeros(b, np.int32))
    first = _expert_steps(ep, start)[0]
    q0 = np.asarray(start.data[:, ep.spec.arm_q], np.float64)
    host = control.plan_arm(ep.kin, q0, np.asarray(first.pos, np.float64),
                            np.asarray(first.quat, np.float64))
    device = control.jit_for_robot(control.plan_arm, ep.kin)(q0, first.pos, first.quat)
    np.testing.assert_array_equal(np.asarray(device[2]), host[2])
    np.testing.assert_allclose(np.asarray(device[0]), host[0], atol=1e-4)
    # Gathered (runtime/plan_rows.py): a task alone gets the call of its own rows, bit for
    # bit (tasks sharing calls: tests/test_eval.py, slow).
    from agnostos_mjx.infra.gather import send_alone

    alone = ep.plan_request(start, first)
    send_alone(alone)
    for a, b_ in zip(alone.result(), device, strict=True):
        np.testing.assert_array_equal(a, np.asarray(b_))


def _expert_steps(ep: Episodes, env) -> list[KeyActions]:
    expert = ep.expert_actions(env)
    return [jax.tree.map(lambda x, k=k: x[:, k], expert) for k in range(expert.pos.shape[1])]


@pytest.mark.slow  # a GPU host's property, checked here with the device planner's programs
def test_device_plans_of_a_seed_apart_equal_its_plans_in_the_whole_batch(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Episodes.plan_rows: a task's seeds that run apart (task_queue.split_by_seed) plan in
    calls of the run's --batch rows, padded, and get the plans they get in one batch of all
    seeds: a world's float32 plan moves with its program's shape (on a GPU), not with the
    rows beside it.  The reset's reachability check is padded alike."""
    from agnostos_mjx.infra.gather import send_alone
    from agnostos_mjx.runtime.plan_rows import GatheredPlanner

    whole = 6
    ep = Episodes(get_task("lamp_on"), "native", planner="device", plan_rows=whole)
    start = ep.reset(_keys(whole), np.zeros(whole, np.int32))
    first = _expert_steps(ep, start)[0]
    q0 = np.asarray(start.data[:, ep.spec.arm_q], np.float64)
    pos = np.asarray(first.pos, np.float64) + np.linspace(-0.02, 0.02, whole)[:, None]
    quat = np.asarray(first.quat, np.float64)
    planner = GatheredPlanner.for_robot(ep.kin)
    shapes: list[int] = []
    program = planner.plan
    monkeypatch.setattr(planner, "plan", lambda q, *a: shapes.append(len(q)) or program(q, *a))
    requests = [planner.submit(q0, pos, quat), planner.submit(q0[2:4], pos[2:4], quat[2:4], whole)]
    for r in requests:
        send_alone(r)
    for a, b in zip(requests[0].result(), requests[1].result(), strict=True):
        assert len(b) == 2
        np.testing.assert_array_equal(a[2:4], b)
    assert shapes == [whole, whole]
    # The reset's check of two worlds runs at the run's rows too, with the same verdicts.
    apart = Episodes(get_task("lamp_on"), "native", planner="device", plan_rows=whole)
    reset_apart = apart.reset(_keys(whole)[2:4], np.zeros(2, np.int32))
    checked: list[int] = []
    reachable = apart.plans.reachable
    monkeypatch.setattr(apart, "plans", dataclasses.replace(
        apart.plans, reachable=lambda q, *a: checked.append(len(q)) or reachable(q, *a)))
    np.testing.assert_array_equal(np.asarray(ep.expert_reachable(start))[2:4],
                                  apart.expert_reachable(reset_apart))
    assert checked == [whole]


@pytest.mark.slow  # a GPU host's property (the default device), compiled here on the CPU
def test_a_host_key_action_runs_its_helpers_on_the_cpu(monkeypatch):
    """Native physics runs on the CPU, so a host key action's jitted helpers (the condition
    scan, grasps) run there too, with the CPU as JAX's default device: on a GPU host they
    would otherwise queue behind every other program on the GPU.  The device planner, asked
    before the key action, keeps the default device."""
    from agnostos_mjx.runtime import env as env_module
    from agnostos_mjx.runtime.phase import host_device

    assert host_device() is None  # this CPU-only machine: the CPU is JAX's default already
    cpu = jax.local_devices(backend="cpu")[0]
    monkeypatch.setattr(env_module, "host_device", lambda: cpu)  # as on a GPU host
    b = 2
    ep = Episodes(get_task("lamp_on"), "native", planner="device")
    env = ep.reset(_keys(b), np.zeros(b, np.int32))
    seen: dict[str, list] = {"conditions": [], "planner": []}
    conditions, plan = ep.programs[("conditions",)], ep.plans.plan

    def spy(name, fn):
        return lambda *a: seen[name].append(jax.config.jax_default_device) or fn(*a)

    monkeypatch.setitem(ep.programs, ("conditions",), spy("conditions", conditions))
    monkeypatch.setattr(ep, "plans", dataclasses.replace(ep.plans, plan=spy("planner", plan)))
    env, _ = ep.step(env, _expert_steps(ep, env)[0])
    assert seen["planner"] == [None]
    assert seen["conditions"] and set(seen["conditions"]) == {cpu}
    # On a GPU host the CPU, unless JAX may not use it (JAX_PLATFORMS=cuda): then none.
    from agnostos_mjx.runtime import phase

    monkeypatch.setattr(phase.jax, "default_backend", lambda: "gpu")
    assert phase.host_device() == cpu

    def no_cpu(backend=None):
        raise RuntimeError("Unknown backend cpu")

    monkeypatch.setattr(phase.jax, "local_devices", no_cpu)
    assert phase.host_device() is None


def test_device_reset_and_step_are_pure_functions_a_user_can_jit():
    """Episodes.device_reset and device_step (issue 52): jitted by the caller, over native
    physics behind the device boundary (physics/callback.py, so it compiles in seconds),
    the reset gives the host reset's scenes (no scene re-sampled here) as the device state,
    and the key action the device program's result."""
    from agnostos_mjx.physics.callback import callback_physics

    ep = Episodes(get_task("lamp_on"), "native")
    b = 2
    keys, variations = _keys(b), np.zeros(b, np.int32)
    host = ep.reset(keys, variations).to_device()
    physics = callback_physics(ep.scene.model, b)
    state = jax.jit(ep.device_reset(b, physics=physics))(keys, variations)
    assert jax.tree.structure(state) == jax.tree.structure(host)
    for a, h in zip(jax.tree.leaves(state), jax.tree.leaves(host), strict=True):
        assert (a.shape, a.dtype) == (h.shape, h.dtype)
        np.testing.assert_allclose(np.asarray(a, float), np.asarray(h, float), atol=1e-4)
    first = jax.tree.map(lambda x: jax.numpy.asarray(x[:, 0]), ep.expert_actions(host.to_host()))
    plan = ep.device_plans.plan(state.data[:, ep.spec.arm_q], first.pos, first.quat)
    mine = jax.jit(ep.device_step(b, physics))(state, first, plan)
    want = ep.step_on_device(host.to_host(), first, physics=physics)
    np.testing.assert_array_equal(np.asarray(mine.outcome), want.outcome)
    np.testing.assert_array_equal(np.asarray(mine.sim_steps), want.sim_steps)
    np.testing.assert_allclose(np.asarray(mine.data), want.data, atol=1e-3)
