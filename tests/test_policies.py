"""The policy interface: the oracle solves a task, a plug-in loads from 'module:attr'."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

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


class MinimalPolicy:
    """Only the required part of the contract: name, reset, act."""

    name = "minimal"

    def reset(self, episodes, env, instructions):
        self.batch = len(instructions)

    def act(self, episodes, env):
        return no_actions(self.batch)


class FullPolicy:
    """Every optional part of the contract, each recording that the evaluator used it."""

    name = "full"

    def __init__(self, log: dict) -> None:
        from agnostos_mjx.observation import ObservationSpec

        self.log = log
        self.observation_spec = ObservationSpec(cameras=("front",), height=16, width=16,
                                                modalities=("rgb",), renderer="cpu")

    def reset(self, episodes, env, instructions, episode_seeds=None):
        self.log.setdefault("seeds", []).extend(episode_seeds)
        self.end_reasons = np.zeros(len(instructions), np.int32)

    def act(self, episodes, env, observation=None):
        raise AssertionError("the evaluator must use act_steps")

    def act_steps(self, episodes, env, observation=None):
        import concurrent.futures

        self.log["observation_worlds"] = observation.batch
        future: concurrent.futures.Future = concurrent.futures.Future()
        future.set_result(None)
        yield future
        self.end_reasons[:] = Outcome.BAD_LLM_OUTPUT  # why no world gets an action
        return no_actions(len(self.end_reasons))

    def episode_info(self, world: int) -> dict:
        return {"world": world}

    def report(self) -> dict:
        return {"llm": {"requests": 0, "calls": self.log.setdefault("reports", 0) + 1}}


FULL_LOG: dict = {}


def make_full() -> FullPolicy:
    return FullPolicy(FULL_LOG)


def _evaluate(policy: str, tmp_path: Path) -> dict:
    from agnostos_mjx.evaluation.config import EvalConfig
    from agnostos_mjx.evaluation.run import evaluate

    return evaluate(EvalConfig(policy=f"{__name__}:{policy}", tasks="lamp_on", seeds=[3],
                               episodes=2, batch=2, backend="native", quiet=True,
                               out=str(tmp_path / "run")))


def test_adapter_defaults_of_a_minimal_policy(tmp_path: Path) -> None:
    """A policy with only name/reset/act runs; the adapter's defaults stand in for the rest."""
    from agnostos_mjx.policies.base import PolicyAdapter

    adapter = PolicyAdapter(MinimalPolicy())
    assert not adapter.interleaves and adapter.observation_spec() is None
    assert adapter.episode_info(0) is None and adapter.report() == {}
    assert adapter.copy().policy is not adapter.policy
    runner = Episodes(get_task("lamp_on"), "native")
    env = runner.reset(np.stack([np.asarray([0, i], np.uint32) for i in range(2)]),
                       np.zeros(2, np.int32))
    adapter.reset(runner, env, ["", ""], episode_seeds=[1, 2])  # not passed on
    steps = adapter.act_steps(runner, env)
    with pytest.raises(StopIteration) as stop:  # act blocks: nothing to wait on
        next(steps)
    assert stop.value.value.valid.tolist() == [False, False]
    assert adapter.end_reasons(env).tolist() == [0, 0]
    results = _evaluate("MinimalPolicy", tmp_path)
    assert [r["outcome"] for r in results["episodes"]] == ["no_action"] * 2
    assert all("policy_info" not in r for r in results["episodes"])
    assert "llm" not in results and "remote" not in results


def test_adapter_calls_every_optional_part(tmp_path: Path) -> None:
    """Observation (rendered to the spec), per-episode seeds, act_steps, end reasons,
    episode info and the report all reach the run's records and results."""
    from agnostos_mjx.evaluation.protocol import policy_seed

    FULL_LOG.clear()
    log = FULL_LOG
    results = _evaluate("make_full", tmp_path)
    assert log["seeds"] == [policy_seed(3, 0), policy_seed(3, 1)]
    assert log["observation_worlds"] == 2
    episodes = results["episodes"]
    assert [r["outcome"] for r in episodes] == ["bad_llm_output"] * 2
    assert [r["policy_info"] for r in episodes] == [{"world": 0}, {"world": 1}]
    assert results["llm"]["calls"] >= 1
