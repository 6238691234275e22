"""How an episode ended: one code per world, stored in episode records by its label."""

from __future__ import annotations

import enum

from agnostos_mjx.sim.control import Status


class Outcome(enum.IntEnum):
    """Codes are stored in records: new codes go last so stored codes keep their meaning."""

    RUNNING = 0
    SUCCESS = 1
    MAX_STEPS = 2
    OUT_OF_WORKSPACE = 3
    UNREACHABLE = 4
    INVALID_ACTION = 5
    FAILURE_CONDITION = 6
    NO_ACTION = 7  # the policy had nothing valid to execute (e.g. bad LLM output)
    POLICY_ERROR = 8  # the policy raised
    BAD_LLM_OUTPUT = 9  # the LLM's answer held no valid 7-integer action
    LLM_ERROR = 10  # an LLM request still failed after its retries
    REMOTE_ERROR = 11  # the policy server refused, dropped the connection or raised
    REMOTE_TIMEOUT = 12  # the policy server did not answer within the timeout
    BAD_REMOTE_OUTPUT = 13  # the server's answer could not be read as a key action

    @property
    def label(self) -> str:
        return self.name.lower()


# The planner's verdict on a key action -> how the episode ends when it is not OK.
STATUS_OUTCOME = {
    Status.OUT_OF_WORKSPACE: Outcome.OUT_OF_WORKSPACE,
    Status.UNREACHABLE: Outcome.UNREACHABLE,
    Status.INVALID_ACTION: Outcome.INVALID_ACTION,
}


def is_done(outcome, stop_at_success: bool):
    """Which worlds are finished.  Evaluation ends an episode at its first success (X-ICM
    stops mid-path); demonstrations run the expert to its end, as RLBench records them.
    Works on numpy and JAX arrays alike."""
    done = outcome != Outcome.RUNNING
    return done if stop_at_success else done & (outcome != Outcome.SUCCESS)


def phase_end(steps, success_at, failure_at, stop_at_success: bool, xp):
    """The step at which each world's phase ended: its success when episodes stop there,
    else its failure, else its last step (`success_at`/`failure_at`: -1 when none)."""
    return xp.where((success_at >= 0) & stop_at_success, success_at,
                    xp.where(failure_at >= 0, failure_at, steps - 1))
