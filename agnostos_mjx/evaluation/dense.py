"""Dense control in the evaluator (``--action-mode dense``): the policy's rows -> one target
per world per control step for `Episodes.step_dense`.

A dense policy's `act` returns one row per world (KeyActions of pos (B, 3), quat (B, 4),
gripper (B,), valid (B,)) or an action chunk (pos (B, H, 3), quat (B, H, 4), gripper
(B, H), valid (B, H)); its end_reason (B,), if any, goes with each of the chunk's rows.
The first ``--execute K`` rows of a chunk (default: all of them) run open loop, one per
control step, then the policy is asked again (the way LeRobot's ACT / diffusion policies and
openpi's clients execute chunks).  A policy that declares
``relative = True`` gives deltas: the target is the tip pose measured when the row starts
plus the row's position, the row's rotation composed on the left (math3d.apply_delta), so
the rows of a chunk chain through the poses actually reached.
"""

from __future__ import annotations

from collections.abc import Generator
from typing import TYPE_CHECKING, Any

import numpy as np

from agnostos_mjx.evaluation.config import EvalConfig, UsageError
from agnostos_mjx.policies.base import Policy, Round
from agnostos_mjx.sim.actions import KeyActions
from agnostos_mjx.sim.math3d import apply_delta

if TYPE_CHECKING:
    import concurrent.futures

    from agnostos_mjx.runtime.dense import DenseControl
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.state import EnvState


def check_action_mode(cfg: EvalConfig, policy: Policy) -> None:
    """A UsageError unless the policy acts in cfg's action mode and the dense options are
    only given with ``--action-mode dense``."""
    protocol = cfg.protocol
    if protocol.action_mode != "dense":
        given = [flag for flag, value in (("--control-hz", protocol.control_hz),
                                          ("--dense-steps", protocol.dense_steps),
                                          ("--execute", protocol.execute)) if value is not None]
        if given:
            raise UsageError(f"{', '.join(given)}: only with --action-mode dense")
    modes = policy.action_modes
    if (mode := protocol.action_mode) not in modes:
        raise UsageError(
            f"policy {policy.name} acts in {' and '.join(modes)} mode, not "
            f"{mode}: --action-mode {mode} needs a policy that declares "
            f"it (action_modes = (..., {mode!r}), see agnostos_mjx/policies/base.py)")


def dense_control(cfg: EvalConfig, runner: Episodes) -> DenseControl:
    """The control period and step budget of cfg for `runner`'s task."""
    from agnostos_mjx.runtime.dense import DEFAULT_CONTROL_HZ, DenseControl

    hz = DEFAULT_CONTROL_HZ if cfg.protocol.control_hz is None else cfg.protocol.control_hz
    return DenseControl.at(hz, runner.dt, runner.task.max_key_actions, cfg.protocol.dense_steps)


ROW_SHAPES = "pos (B, 3), quat (B, 4) wxyz, gripper (B,), valid (B,)"
CHUNK_SHAPES = "pos (B, H, 3), quat (B, H, 4) wxyz, gripper (B, H), valid (B, H)"


class PolicyAnswerError(UsageError):
    """A policy's answer in another form than its action mode takes: the policy's bug, the
    same in every batch, so the run stops with this one line (eval.py's UsageError)
    instead of ending every task's episodes as policy_error."""


def check_answer(actions: Any, batch: int, policy_name: str, chunks: bool = False) -> int:
    """The chunk length H of a policy's answer, 0 for one row per world; a
    PolicyAnswerError naming the shapes expected and given unless it is KeyActions of one
    row per world (or, with `chunks`, a chunk per world).  Checked here because a wrong
    shape otherwise broadcasts in the control code (an unbatched quaternion) or fails deep
    inside it.  An end_reason must be None or (B,) integer Outcome codes, whatever H."""
    expected = f"{ROW_SHAPES} or a chunk {CHUNK_SHAPES}" if chunks else ROW_SHAPES
    if not isinstance(actions, KeyActions):
        raise PolicyAnswerError(f"policy {policy_name} answered {type(actions).__name__}, "
                                f"not KeyActions of {expected}")
    got = [np.shape(x) for x in (actions.pos, actions.quat, actions.gripper, actions.valid)]
    h = got[0][1] if chunks and len(got[0]) == 3 else 0
    lead = (batch, h) if h else (batch,)
    if got != [(*lead, 3), (*lead, 4), lead, lead]:
        raise PolicyAnswerError(
            f"policy {policy_name} answered pos {got[0]}, quat {got[1]}, gripper {got[2]}, "
            f"valid {got[3]}; expected KeyActions of {expected}, B = {batch} worlds")
    reason = actions.end_reason
    if reason is not None and (np.shape(reason) != (batch,) or
                               not np.issubdtype(np.asarray(reason).dtype, np.integer)):
        raise PolicyAnswerError(
            f"policy {policy_name} answered end_reason {np.shape(reason)} "
            f"{np.asarray(reason).dtype}; expected None or ({batch},) integer Outcome codes")
    return h


def as_chunk(actions: KeyActions, batch: int, policy_name: str) -> KeyActions:
    """A dense policy's answer, checked (check_answer), as a chunk (B, H, ...) of numpy
    arrays (its end_reason, per world, as it is)."""
    h = check_answer(actions, batch, policy_name, chunks=True)
    rows = (np.asarray(actions.pos, np.float64), np.asarray(actions.quat, np.float64),
            np.asarray(actions.gripper, np.float64), np.asarray(actions.valid, bool))
    return KeyActions(*(rows if h else (x[:, None] for x in rows)),
                      end_reason=actions.end_reason)


class DenseDriver:
    """The rows a batch executes: asks the policy when its chunk is used up (after
    `execute` rows, default the whole chunk) and turns relative rows into targets."""

    def __init__(self, execute: int | None, relative: bool) -> None:
        self.execute = execute
        self.relative = relative
        self.chunk: KeyActions | None = None
        self.row = 0
        self.rows = 0
        self.queries = 0

    def next(self, policy: Policy, view: Round, env: EnvState
             ) -> Generator[concurrent.futures.Future, Any, KeyActions]:
        """This control step's target of every world (a generator over the futures the
        policy waits on, as Policy.act_steps); `view` is what the policy sees of `env`."""
        if self.chunk is None or self.row >= self.rows:
            answer = yield from policy.act_steps(view)
            self.chunk = as_chunk(answer, env.batch, policy.name)
            h = self.chunk.pos.shape[1]
            self.rows = h if self.execute is None else min(h, self.execute)
            self.row = 0
            self.queries += 1
        c, r = self.chunk, self.row
        self.row += 1
        pos, quat = c.pos[:, r], c.quat[:, r]
        if self.relative:
            obs = env.obs
            pos, quat = apply_delta(np.asarray(obs["tip.pos"], np.float64),
                                    np.asarray(obs["tip.quat"], np.float64), pos, quat)
        return KeyActions(pos, quat, c.gripper[:, r], c.valid[:, r], c.end_reason)
