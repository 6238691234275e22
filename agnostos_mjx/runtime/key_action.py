"""One key action for B worlds, written once for every backend.

    plan (IK, Cartesian or joint path; computed by the caller: numpy next to native MuJoCo,
          one compiled program shared by every task next to MJX)
    ->  arm phase: move along the path, then hold so the arm comes to rest
    ->  gripper phase, for worlds whose gripper command changes (opening drops grasps first)
    ->  grasp attach (RLBench's proximity test; weld poses from the kinematics)
    ->  outcomes (no action, planner verdicts, success / failure, max key actions)

Pure functions over numpy or jax.numpy (`phases.xp`): the host path runs them as Python
over numpy arrays, the MJX path traces them into one device program.  The only
backend-specific piece is `phases` (runtime/phase.py): `run_phase(state, steps, ctrl_at)`
runs world w for steps[w] physics steps under the controls `ctrl_at(t)` and reports when
each world's success and failure conditions first held; `poses(physics, worlds)` gives
body frames for the grasp welds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from agnostos_mjx.runtime.outcome import STATUS_OUTCOME, Outcome, is_done, phase_end
from agnostos_mjx.runtime.state import EnvState, StepResult
from agnostos_mjx.sim import control
from agnostos_mjx.sim.actions import KeyActions
from agnostos_mjx.sim.math3d import quat_conj, quat_mul, quat_rotate


@dataclass(frozen=True)
class StepSpec:
    """What a key action needs of the scene and task, frozen at the runner's start."""

    arm_q: slice  # sensor columns of the arm's 7 joint positions
    dt: float  # physics step, s
    max_key_actions: int
    # one world: (carry, sensor row, attached, variation) -> (carry, success, failure)
    condition_step: Callable
    # batched (data (B, S), attached (B, G)) -> which graspables lie in the attach volume
    attach: Callable | None
    hand_body: int
    graspable_bodies: tuple[int, ...]
    weld_ids: tuple[int, ...]
    # batched (rgba, initial data, data, attached, variation) -> rgba with state colours
    repaint: Callable


class Phases(Protocol):
    """The physics boundary of a key action (runtime/phase.py has the two kinds)."""

    xp: Any  # numpy or jax.numpy: the array module the key action runs over

    def run_phase(self, state: EnvState, steps, ctrl_at: Callable
                  ) -> tuple[EnvState, Any, Any, StepResult | None]:
        """Step world w for steps[w] steps under ctrl_at(t) ((T,) step indices ->
        (B, T, nu)); return the state (physics, latest sensor row at each world's end,
        condition carries), the first success and failure step (-1: none; a failure after
        the success is not reported) and, on the host, the phase's per-step record."""
        ...

    def poses(self, physics, worlds) -> tuple[Any, Any]:
        """Body positions (B, nbody, 3) and quaternions (B, nbody, 4) of `worlds` (B,)."""
        ...


def key_action(spec: StepSpec, phases: Phases, state: EnvState, actions: KeyActions,
               plan: tuple) -> tuple[EnvState, tuple[StepResult, ...]]:
    """Execute one key action per world (`actions`, planned as `plan` = (path, duration,
    status)); a world whose action is not valid ends with Outcome.NO_ACTION and finished
    worlds ignore theirs.  Returns the new state and the phases' per-step records."""
    xp = phases.xp
    stop = state.stop_at_success
    path, duration, status = plan
    state, active = begin_action(phases, state, actions.valid, status)
    records: list[StepResult] = []

    # Arm phase: move along the path, then hold so the arm comes to rest; each world for
    # its own move's (bucketed) length.
    q0 = state.data[:, spec.arm_q]
    steps = control.bucket_steps(duration + control.SETTLE_TIME, spec.dt) * active
    path = xp.where(active[:, None, None], path, q0[:, None])
    duration = xp.maximum(duration, 1e-3)
    gripper = state.gripper

    def arm_ctrl(t):
        arm = control.arm_targets_at(path, duration, (t + 1) * spec.dt)
        grip = xp.broadcast_to(gripper[:, None, None], (*arm.shape[:2], 1)).astype(arm.dtype)
        return xp.concatenate([arm, grip], -1)

    state = _phase(spec, phases, state, steps, arm_ctrl, records)

    # Gripper phase, only for worlds whose gripper command changes.
    target = control.finger_target(xp.asarray(actions.gripper))
    moving = active & ~is_done(state.outcome, stop) & (xp.abs(target - state.gripper) > 1e-4)
    opening = moving & (target > state.gripper)
    state = _with_welds(spec, phases, state, state.attached & ~opening[:, None])
    hold = state.physics.ctrl[:, :7]
    start, goal = state.gripper, xp.where(moving, target, state.gripper)

    def grip_ctrl(t):
        finger = control.gripper_target_at(start[:, None], goal[:, None], (t + 1) * spec.dt)
        arm = xp.broadcast_to(hold[:, None], (*finger.shape, hold.shape[-1]))
        return xp.concatenate([arm, finger[..., None].astype(hold.dtype)], -1)

    gripper_steps = control.bucket_steps(control.GRIPPER_TIME, spec.dt)
    state = _phase(spec, phases, state, gripper_steps * moving, grip_ctrl, records)
    closing = moving & ~opening & ~is_done(state.outcome, stop)
    state = state.replace(gripper=xp.where(moving, target, state.gripper))
    return end_action(spec, phases, state, closing, spec.max_key_actions), tuple(records)


def begin_action(phases: Phases, state: EnvState, valid, status) -> tuple[EnvState, Any]:
    """Outcomes before an action runs: NO_ACTION for a running world without a valid
    action, the planner's verdict (`status`) for one it cannot execute; the others are
    `active` and counted (key_actions).  Returns (state, active)."""
    xp = phases.xp
    running = state.outcome == Outcome.RUNNING
    done = is_done(state.outcome, state.stop_at_success)
    valid = xp.asarray(valid, bool)
    outcome = xp.where(~done & ~valid & running, Outcome.NO_ACTION, state.outcome)
    active = ~done & valid
    bad = active & (status != control.Status.OK)
    for code, reason in STATUS_OUTCOME.items():
        outcome = xp.where(bad & (status == code), reason, outcome)
    active = active & ~bad
    return state.replace(outcome=outcome, key_actions=state.key_actions + active), active


def end_action(spec: StepSpec, phases: Phases, state: EnvState, closing, budget: int
               ) -> EnvState:
    """After an action: the worlds whose gripper just `closing` closed grasp what lies in
    the attach volume (RLBench's grasp on close), and a running world that has used the
    `budget` of actions ends with MAX_STEPS."""
    xp = phases.xp
    if spec.attach is not None:
        hits = xp.asarray(spec.attach(state.data, state.attached))
        state = _with_welds(spec, phases, state, state.attached | (hits & closing[:, None]))
    over = (state.outcome == Outcome.RUNNING) & (state.key_actions >= budget)
    return state.replace(outcome=xp.where(over, Outcome.MAX_STEPS, state.outcome))


def _phase(spec: StepSpec, phases: Phases, state: EnvState, steps, ctrl_at: Callable,
           records: list) -> EnvState:
    """One phase through the boundary, then its outcomes, step counts and state colours."""
    xp = phases.xp
    new, success_at, failure_at, record = phases.run_phase(state, steps, ctrl_at)
    if record is not None:
        records.append(record)
    active = steps > 0
    end = phase_end(steps, success_at, failure_at, state.stop_at_success, xp)
    outcome = xp.where(success_at >= 0, Outcome.SUCCESS,
                       xp.where(failure_at >= 0, Outcome.FAILURE_CONDITION, state.outcome))
    sim_steps = state.sim_steps + xp.where(active, end + 1, 0).astype(state.sim_steps.dtype)
    rgba = spec.repaint(new.geom_rgba, new.initial_data, new.data, new.attached, new.variation)
    return new.replace(outcome=outcome, sim_steps=sim_steps, geom_rgba=rgba)


def _set(xp, array, index: tuple, value):
    """`array` with array[index] = value, without changing `array` (numpy or JAX)."""
    if xp is np:
        out = np.array(array, copy=True)
        out[index] = value
        return out
    return array.at[index].set(value)


def _with_welds(spec: StepSpec, phases: Phases, state: EnvState, attached) -> EnvState:
    """Grasp welds on for `attached`; a newly attached object keeps its current pose
    relative to the hand (RLBench's grasp)."""
    if not spec.weld_ids:
        return state.replace(attached=attached)
    xp = phases.xp
    newly = attached & ~state.attached
    xpos, xquat = phases.poses(state.physics, newly.any(1))
    hp, hq = xpos[:, spec.hand_body], xquat[:, spec.hand_body]
    eq_data, eq_active = state.physics.eq_data, state.physics.eq_active
    for g, (body, eq) in enumerate(zip(spec.graspable_bodies, spec.weld_ids)):
        rel_p = quat_rotate(quat_conj(hq), xpos[:, body] - hp)
        rel_q = quat_mul(quat_conj(hq), xquat[:, body])
        weld = xp.concatenate([xp.zeros_like(rel_p), rel_p, rel_q, xp.ones_like(rel_p[:, :1])],
                              -1).astype(eq_data.dtype)
        row = eq_data[:, eq, :11]
        eq_data = _set(xp, eq_data, (slice(None), eq, slice(0, 11)),
                       xp.where(newly[:, g, None], weld, row))
        eq_active = _set(xp, eq_active, (slice(None), eq), attached[:, g])
    physics = state.physics.replace(eq_data=eq_data, eq_active=eq_active)
    return state.replace(physics=physics, attached=attached)
