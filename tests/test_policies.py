"""The policy interface: the oracle solves a task, a plug-in loads from 'module:attr'."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

# tasks before episode: importing episode first trips a world <-> tasks import cycle
from agnostos_mjx.tasks import get_task

# isort: split
from agnostos_mjx.eval import main
from agnostos_mjx.policies import Policy, make_policy, no_actions
from agnostos_mjx.policies.oracle import OraclePolicy
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.tasks.base import KeyActions


class InvalidPolicy:
    """A plug-in with nothing to execute: every world ends with NO_ACTION."""

    name = "invalid"

    def reset(self, episodes: Episodes, env, instructions: list[str]) -> None:
        self.batch = len(instructions)

    def act(self, episodes: Episodes, env) -> KeyActions:
        return no_actions(self.batch)


def test_oracle_solves_lamp_on() -> None:
    runner = Episodes(get_task("lamp_on"), "native")
    keys = np.stack([np.asarray([0, i], np.uint32) for i in range(2)])
    env = runner.reset(keys, np.zeros(2, np.int32))
    policy = make_policy("oracle")
    assert isinstance(policy, OraclePolicy) and isinstance(policy, Policy)
    policy.reset(runner, env, ["turn on the light"] * 2)
    for _ in range(runner.task.max_key_actions):
        if env.done.all():
            break
        env, _ = runner.step(env, policy.act(runner, env))
    assert (env.outcome == Outcome.SUCCESS).all(), [Outcome(o).label for o in env.outcome]


def test_oracle_skips_padding_then_runs_out() -> None:
    valid = np.array([[False, True, False, True], [False, False, False, False]])
    plan = KeyActions(pos=np.arange(24, dtype=np.float32).reshape(2, 4, 3),
                      quat=np.zeros((2, 4, 4), np.float32),
                      gripper=np.arange(8, dtype=np.float32).reshape(2, 4), valid=valid)

    class FakeEpisodes:
        def expert_actions(self, env):
            return plan

    policy = OraclePolicy()
    policy.reset(FakeEpisodes(), None, ["", ""])
    first = policy.act(None, None)
    assert first.valid.tolist() == [True, False] and first.gripper[0] == 1
    second = policy.act(None, None)
    assert second.valid.tolist() == [True, False] and second.gripper[0] == 3
    assert policy.act(None, None).valid.tolist() == [False, False]


def test_make_policy_forms_and_errors() -> None:
    assert isinstance(make_policy(f"{__name__}:InvalidPolicy"), InvalidPolicy)  # a class
    assert make_policy(f"{__name__}:INSTANCE") is INSTANCE  # an instance
    assert make_policy(f"{__name__}:make_oracle").name == "oracle"  # a factory
    with pytest.raises(KeyError, match="oracle"):
        make_policy("no_such_policy")
    with pytest.raises(ImportError):
        make_policy(f"{__name__}:Missing")


INSTANCE = InvalidPolicy()


def make_oracle() -> OraclePolicy:
    return OraclePolicy()


def test_plugin_policy_from_module_attr_ends_with_no_action(tmp_path: Path) -> None:
    out = tmp_path / "run"
    code = main(["--policy", f"{__name__}:InvalidPolicy", "--tasks", "lamp_on", "--seeds", "0",
                 "--episodes", "2", "--batch", "2", "--backend", "native", "--quiet",
                 "--out", str(out)])
    assert code == 0
    recs = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert len(recs) == 2
    assert all(r["outcome"] == "no_action" and not r["success"] for r in recs)
    assert all(r["policy"] == "invalid" and r["key_actions"] == 0 for r in recs)
    results = json.loads((out / "results.json").read_text())
    assert results["summary"]["tasks"]["lamp_on"]["outcomes"] == {"no_action": 2}
