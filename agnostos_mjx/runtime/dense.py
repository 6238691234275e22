"""One dense control step for B worlds: the counterpart of the key action for policies that
act at a fixed rate (LeRobot-style ACT / diffusion policies at 10-50 Hz), written once for
every backend over the same `Phases` boundary as runtime/key_action.py.

    IK (computed by the caller: control.dense_ik, warm-started at the current joints, no
    Cartesian path planner)
    ->  one control period of physics: the arm's joint targets interpolated linearly from
        the last command to the IK goal, the finger target moving toward the commanded
        opening at the gripper's rate (no separate gripper phase; opening drops grasps
        first)
    ->  grasp attach when a closing command completes (RLBench's proximity test, as the
        key action attaches after its gripper phase)
    ->  outcomes: a world whose action is not valid ends with NO_ACTION; a non-finite target
        INVALID_ACTION, one the IK cannot reach from the current joints UNREACHABLE (the
        key action's planner verdicts; a target outside the action bounds is clipped into
        them, see control.dense_ik, so OUT_OF_WORKSPACE does not occur); success / failure
        conditions checked at every physics step; MAX_STEPS once a world has used the
        step budget (`DenseControl.max_steps` control steps).

The state's `key_actions` counts the control steps executed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from agnostos_mjx.runtime.key_action import (
    Phases,
    StepSpec,
    _phase,
    _with_welds,
    begin_action,
    end_action,
)
from agnostos_mjx.runtime.outcome import is_done
from agnostos_mjx.runtime.state import EnvState, StepResult
from agnostos_mjx.sim import control
from agnostos_mjx.sim.actions import KeyActions

log = logging.getLogger(__name__)

DEFAULT_CONTROL_HZ = 20.0  # RLBench's and LIBERO's observation rate
# The default budget: the task's key-action budget (25 for every task) x 2 s, an upper
# bound of the expert's mean key action (1.2-2.1 s per seen task): 50 s, 1000 control steps
# at 20 Hz, which covers the longest oracle episode of any seen task (place_cups, 44.5 s).
SECONDS_PER_KEY_ACTION = 2.0
GRIPPER_TOL = 1e-6  # m: finger targets this close are equal (float32 on the device)


@dataclass(frozen=True)
class DenseControl:
    """The control period (physics steps) and the step budget (control steps) of a run."""

    period_steps: int
    max_steps: int

    def __post_init__(self) -> None:
        if self.period_steps < 1 or self.max_steps < 1:
            raise ValueError(f"a dense control period and budget of at least one step, got "
                             f"{self.period_steps} physics steps and {self.max_steps} steps")

    @classmethod
    def at(cls, hz: float, dt: float, max_key_actions: int, max_steps: int | None = None
           ) -> DenseControl:
        """The control of `hz` at physics timestep `dt`: a period of round(1 / (hz dt))
        steps (a warning when that is not exactly 1 / hz); the budget `max_steps`, default
        `max_key_actions` x SECONDS_PER_KEY_ACTION at `hz`."""
        if not hz > 0:
            raise ValueError(f"the control rate must be positive, got {hz}")
        period = max(1, round(1.0 / (hz * dt)))
        if abs(period * dt * hz - 1.0) > 1e-6:
            log.warning("--control-hz %g: the control period is %d physics steps of %g s "
                        "(%.4g Hz)", hz, period, dt, 1.0 / (period * dt))
        if max_steps is None:
            max_steps = round(max_key_actions * SECONDS_PER_KEY_ACTION / (period * dt))
        return cls(period, max_steps)


def dense_action(spec: StepSpec, phases: Phases, state: EnvState, targets: KeyActions,
                 plan: tuple, ctl: DenseControl) -> tuple[EnvState, tuple[StepResult, ...]]:
    """Execute one control period (`ctl`) per world toward `targets` (tip pose, gripper
    open amount, valid), with `plan` = (joint goal (B, 7), status (B,)) from
    control.dense_ik; finished worlds ignore theirs.  Returns the new state and the
    phase's per-step record."""
    xp = phases.xp
    stop = state.stop_at_success
    q_goal, status = plan
    state, active = begin_action(phases, state, targets.valid, status)
    records: list[StepResult] = []

    # The gripper: the finger target moves toward the commanded opening at the gripper's
    # rate; an opening command drops the grasps first, as the key action's gripper phase.
    period_s = ctl.period_steps * spec.dt
    start = state.gripper
    goal = xp.where(active, control.finger_target(xp.asarray(targets.gripper)), start)
    end = control.gripper_toward(start, goal, period_s)
    opening = active & (end > start + GRIPPER_TOL)
    state = _with_welds(spec, phases, state, state.attached & ~opening[:, None])

    # The arm: from the last joint command to the IK goal, linearly over the period.
    arm0 = state.physics.ctrl[:, :7]
    q_goal = xp.where(active[:, None], xp.asarray(q_goal, arm0.dtype), arm0)

    def ctrl_at(t):
        s = ((t + 1) / ctl.period_steps).astype(arm0.dtype)[None, :, None]
        arm = arm0[:, None] + s * (q_goal - arm0)[:, None]
        finger = control.gripper_toward(start[:, None], goal[:, None], (t + 1) * spec.dt)
        return xp.concatenate([arm, finger[..., None].astype(arm.dtype)], -1)

    state = _phase(spec, phases, state, ctl.period_steps * active, ctrl_at, records)
    # A closing command that arrived this period grasps what lies between the fingers.
    closed = active & (end < start - GRIPPER_TOL) & (xp.abs(end - goal) < GRIPPER_TOL) \
        & ~is_done(state.outcome, stop)
    state = state.replace(gripper=xp.where(active, end, state.gripper))
    return end_action(spec, phases, state, closed, ctl.max_steps), tuple(records)

