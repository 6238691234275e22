"""The policy interface: the oracle solves a task, a plug-in loads from 'module:attr'."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agnostos_mjx.tasks import get_task

# isort: split
from agnostos_mjx.eval import main
from agnostos_mjx.policies import Policy, Round, make_policy, no_actions
from agnostos_mjx.policies.oracle import OraclePolicy
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.sim.actions import KeyActions


class InvalidPolicy(Policy):
    """A plug-in with nothing to execute: every world ends with NO_ACTION."""

    name = "invalid"

    def act(self, view: Round) -> KeyActions:
        return no_actions(view.batch)


def _lamp_on(batch: int = 2):
    runner = Episodes(get_task("lamp_on"), "native")
    keys = np.stack([np.asarray([0, i], np.uint32) for i in range(batch)])
    return runner, runner.reset(keys, np.zeros(batch, np.int32))


def test_oracle_solves_lamp_on() -> None:
    runner, env = _lamp_on()
    policy = make_policy("oracle")
    assert isinstance(policy, OraclePolicy) and policy.privileged
    view = Round.for_policy(policy, runner, env, ["turn on the light"] * 2)
    policy.reset(view)
    for _ in range(runner.task.max_key_actions):
        if env.done.all():
            break
        env, _ = runner.step(env, policy.act(view.at(env)))
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
    view = Round(FakeEpisodes(), None, ["", ""], privileged=True)
    policy.reset(view)
    first = policy.act(view)
    assert first.valid.tolist() == [True, False] and first.gripper[0] == 1
    second = policy.act(view)
    assert second.valid.tolist() == [True, False] and second.gripper[0] == 3
    assert policy.act(view).valid.tolist() == [False, False]


def test_make_policy_forms_and_errors() -> None:
    assert isinstance(make_policy(f"{__name__}:InvalidPolicy"), InvalidPolicy)  # a class
    assert make_policy(f"{__name__}:INSTANCE") is INSTANCE  # an instance
    assert make_policy(f"{__name__}:make_oracle").name == "oracle"  # a factory
    with pytest.raises(KeyError, match="oracle"):
        make_policy("no_such_policy")
    with pytest.raises(ImportError):
        make_policy(f"{__name__}:Missing")
    with pytest.raises(TypeError, match="not an agnostos_mjx.policies.Policy"):
        make_policy(f"{__name__}:NotAPolicy")  # the old duck-typed form
    with pytest.raises(TypeError, match="must override act"):
        type("Empty", (Policy,), {})


class NotAPolicy:
    name = "not"

    def reset(self, episodes, env, instructions):
        pass

    def act(self, episodes, env):
        return no_actions(len(env.outcome))


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


class MinimalPolicy(Policy):
    """Only `act`: every other part of the contract is the base class's default."""

    def act(self, view: Round) -> KeyActions:
        return no_actions(view.batch)


class FullPolicy(Policy):
    """Every optional part of the contract, each recording that the evaluator used it."""

    name = "full"

    def __init__(self, log: dict) -> None:
        from agnostos_mjx.runtime.observation import ObservationSpec

        self.log = log
        self.observation_spec = ObservationSpec(cameras=("front",), height=16, width=16,
                                                modalities=("rgb",), renderer="cpu")

    def reset(self, view: Round) -> None:
        self.log.setdefault("seeds", []).extend(view.episode_seeds)

    def act(self, view: Round) -> KeyActions:
        raise AssertionError("the evaluator must use act_steps")

    def act_steps(self, view: Round):
        import concurrent.futures

        self.log["observation_worlds"] = view.observation.batch
        self.log["gripper_pose"] = view.proprioception["gripper_pose"].shape
        future: concurrent.futures.Future = concurrent.futures.Future()
        future.set_result(None)
        yield future
        # Why no world gets an action travels with the answer (B = 2 here).
        return no_actions(view.batch)._replace(
            end_reason=np.array([Outcome.LLM_ERROR, Outcome.BAD_LLM_OUTPUT], np.int32))

    def episode_info(self, world: int) -> dict:
        return {"world": world}

    def report(self) -> dict:
        return {"llm": {"requests": 0, "calls": self.log.setdefault("reports", 0) + 1}}


FULL_LOG: dict = {}


def make_full() -> FullPolicy:
    return FullPolicy(FULL_LOG)


class PeekingPolicy(Policy):
    """Reads the simulator without declaring it."""

    def act(self, view: Round) -> KeyActions:
        view.env.outcome  # noqa: B018 - the access under test
        return no_actions(view.batch)


def _evaluate(policy: str, tmp_path: Path) -> dict:
    from agnostos_mjx.evaluation.config import EvalConfig
    from agnostos_mjx.evaluation.run import evaluate

    return evaluate(EvalConfig.of(policy=f"{__name__}:{policy}", tasks="lamp_on", seeds=[3],
                                  episodes=2, batch=2, backend="native", quiet=True,
                                  out=str(tmp_path / "run")))


def test_defaults_of_a_minimal_policy(tmp_path: Path) -> None:
    """A policy with only `act` runs; the base class's defaults stand in for the rest."""
    policy = MinimalPolicy()
    assert not policy.interleaves() and policy.observation_spec is None
    assert not policy.privileged and policy.action_modes == ("keyaction",)
    assert policy.episode_info(0) is None and policy.report() == {}
    assert policy.fork() is not policy
    runner, env = _lamp_on()
    view = Round.for_policy(policy, runner, env, ["", ""], episode_seeds=[1, 2])
    policy.reset(view)
    steps = policy.act_steps(view)
    with pytest.raises(StopIteration) as stop:  # act blocks: nothing to wait on
        next(steps)
    assert stop.value.value.valid.tolist() == [False, False]
    assert stop.value.value.end_reason is None  # plain no_action
    assert no_actions(2, Outcome.LLM_ERROR).end_reason.tolist() == [Outcome.LLM_ERROR] * 2
    results = _evaluate("MinimalPolicy", tmp_path)
    assert [r["outcome"] for r in results["episodes"]] == ["no_action"] * 2
    assert all(r["policy"] == f"{__name__}:MinimalPolicy" for r in results["episodes"])
    assert all("policy_info" not in r for r in results["episodes"])
    assert "llm" not in results and "remote" not in results


def test_a_round_shows_the_simulator_to_privileged_policies_only(tmp_path: Path) -> None:
    """Instructions, seeds, running worlds, key actions and proprioception for every policy;
    the runner and state only where declared; an observation only where a spec is."""
    from agnostos_mjx.policies import PrivilegedAccessError

    runner, env = _lamp_on()
    view = Round(runner, env, ["a", "b"], [7, 8])
    assert view.instructions == ("a", "b") and view.episode_seeds == (7, 8)
    assert view.running.tolist() == [True, True] and view.key_actions.tolist() == [0, 0]
    np.testing.assert_array_equal(view.proprioception["gripper_pose"][:, :3],
                                  np.asarray(env.obs["tip.pos"], np.float32))
    for part in ("env", "episodes"):
        with pytest.raises(PrivilegedAccessError, match="privileged = True"):
            getattr(view, part)
    with pytest.raises(ValueError, match="observation_spec"):
        view.observation  # noqa: B018
    privileged = Round(runner, env, ["a", "b"], privileged=True).at(env)
    assert privileged.env is env and privileged.episodes is runner
    with pytest.raises(ValueError, match="2 instructions but 1 episode seeds"):
        Round(runner, env, ["a", "b"], [1])
    # In a run, a peek without the declaration is the policy's error, recorded as such.
    results = _evaluate("PeekingPolicy", tmp_path)
    assert [r["outcome"] for r in results["episodes"]] == ["policy_error"] * 2


def test_the_evaluator_uses_every_optional_part(tmp_path: Path) -> None:
    """Observation (rendered to the spec), per-episode seeds, act_steps, end reasons,
    episode info and the report all reach the run's records and results."""
    from agnostos_mjx.evaluation.protocol import policy_seed

    FULL_LOG.clear()
    log = FULL_LOG
    results = _evaluate("make_full", tmp_path)
    assert log["seeds"] == [policy_seed(3, 0), policy_seed(3, 1)]
    assert log["observation_worlds"] == 2 and log["gripper_pose"] == (2, 7)
    episodes = results["episodes"]
    assert [r["outcome"] for r in episodes] == ["llm_error", "bad_llm_output"]
    assert [r["policy_info"] for r in episodes] == [{"world": 0}, {"world": 1}]
    assert results["llm"]["calls"] >= 1


@pytest.mark.parametrize("module", ["agnostos_mjx.sim.actions", "agnostos_mjx.policies",
                                    "agnostos_mjx.policies.learned_options",
                                    "agnostos_mjx.remote.options"])
def test_the_policy_contract_imports_neither_jax_nor_mujoco(module: str) -> None:
    """A policy (or a client of a served one) writes its `act` against the contract and
    `KeyActions` without loading the simulator's libraries; the built-in policies' options
    load without them too (checked and listed before JAX starts)."""
    code = f"import sys, {module}; print(sorted({{'jax', 'mujoco'}} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.strip() == "[]", out.stdout


def test_key_actions_are_a_pytree() -> None:
    """JAX maps over KeyActions (the runtime converts and vmaps them) with no registration."""
    import jax

    acts = KeyActions(np.zeros((2, 3)), np.ones((2, 4)), np.ones(2), np.ones(2, bool))
    doubled = jax.tree.map(lambda x: 2 * x, acts)
    assert isinstance(doubled, KeyActions) and doubled.quat.shape == (2, 4)
    assert len(jax.tree.leaves(acts)) == 4 and doubled.end_reason is None  # an empty subtree
    reasoned = acts._replace(end_reason=np.array([0, 3], np.int32))
    assert len(jax.tree.leaves(reasoned)) == 5
    assert jax.jit(lambda a: a.pos)(acts).shape == (2, 3)


# ---- options of the built-in policies (--policy-arg) --------------------------------------
def free_kwargs_factory(**kwargs) -> Policy:
    policy = InvalidPolicy()
    policy.kwargs = kwargs
    return policy


def test_policy_args_fill_a_built_in_policys_typed_options() -> None:
    """--policy-arg pairs become the policy's options dataclass: types coerced where the
    meaning is plain (an int for a float, a number for text, JSON text for an object) and
    checked; a user policy's factory still gets them as free keyword arguments."""
    from agnostos_mjx.policies.base import options_type
    from agnostos_mjx.policies.options import OptionsError, parse_options
    from agnostos_mjx.remote.options import PRESET

    remote = parse_options(options_type("remote"), {
        "timeout_s": 5, "url": "ws://h:1", "keys": '{"image": "front_rgb"}',
        "gripper_threshold": None, "height": 32}, "remote")
    assert remote.timeout_s == 5.0 and isinstance(remote.timeout_s, float)
    assert remote.keys == {"image": "front_rgb"} and remote.width is PRESET
    assert remote.adapter_options() == {"height": 32, "gripper_threshold": None}
    timing = parse_options(options_type("timing"), {"cameras": "front", "size": 64}, "timing")
    assert (timing.cameras, timing.size, timing.chunk) == ("front", 64, 1)
    assert parse_options(options_type("dense-replay"), {"every": 4}, "x").every == 4
    assert parse_options(options_type("reference-vla"), {"checkpoint": 7}, "x").checkpoint == "7"
    for args, message in (({"relative": "yes"}, 'relative="yes": expected true or false'),
                          ({"every": None}, "every=null: expected an integer or text"),
                          ({"chunk": 0}, "chunk=0: must be an integer >= 1")):
        with pytest.raises(OptionsError, match=re.escape(message)):
            parse_options(options_type("dense-replay"), args, "dense-replay")
    with pytest.raises(OptionsError, match="takes no --policy-arg model; its options: none"):
        make_policy("oracle", model="qwen")  # make_policy parses as the command line does
    with pytest.raises(OptionsError, match="objects=pixels: must be one of"):
        options_type("xicm")(objects="pixels")  # built directly: checked alike
    assert options_type(f"{__name__}:free_kwargs_factory") is None
    assert make_policy(f"{__name__}:free_kwargs_factory", model="qwen", k=[1]).kwargs == {
        "model": "qwen", "k": [1]}


def test_xicm_and_retrieval_options_come_from_their_flags() -> None:
    """X-ICM's and retrieval's own flags fill their options (XicmOptions.from_config), the
    --policy-arg pairs override them; --policy-url fills a served policy's url only."""
    from agnostos_mjx.evaluation.config import parse_config, resolve_policy

    flags = ["--selection", "text", "--memory", "m.npz", "--ddim-steps", "20", "--llm-url",
             "http://x/v1", "--llm-model", "m", "--num-demos", "5", "--llm-timeout", "30",
             "--llm-concurrency", "2", "--llm-server-kind", "llamacpp", "--out", "run"]
    spec, xicm, _ = resolve_policy(parse_config(["--policy", "xicm", *flags]))
    assert spec == "xicm" and {k: xicm[k] for k in (
        "selection", "memory", "sample_steps", "llm_url", "llm_model", "num_demos",
        "timeout_s", "concurrency", "server_kind", "llm_cache")} == {
        "selection": "text", "memory": "m.npz", "sample_steps": 20, "llm_url": "http://x/v1",
        "llm_model": "m", "num_demos": 5, "timeout_s": 30.0, "concurrency": 2,
        "server_kind": "llamacpp", "llm_cache": str(Path("run") / "llm_cache")}
    _, xicm, _ = resolve_policy(parse_config(
        ["--policy", "xicm", *flags, "--policy-arg", "num_demos=3"]))
    assert xicm["num_demos"] == 3  # --policy-arg wins over the flag
    _, retrieval, note = resolve_policy(parse_config(flags[:6]))  # auto without an LLM
    assert retrieval == {"selection": "text", "memory": "m.npz", "sample_steps": 20}
    assert "retrieval baseline" in note
    url = ["--policy-url", "ws://h:1"]
    assert resolve_policy(parse_config(["--policy", "remote", *url]))[1]["url"] == "ws://h:1"
    assert resolve_policy(parse_config(["--policy", "oracle", *url]))[1] == {}


def test_policy_arg_help_lists_the_options(capsys: pytest.CaptureFixture) -> None:
    """``--policy-arg help`` prints the policy's options (eval and serve alike) and exits 0,
    loading no policy; for a user policy, the signature its pairs go to."""
    from agnostos_mjx import serve

    assert main(["--policy", "timing", "--policy-arg", "help"]) == 0
    out = capsys.readouterr().out
    assert "--policy timing options" in out and "  size=128  (an integer) image" in out
    assert serve.main(["--policy", "xicm", "--policy-arg", "help=1"]) == 0
    out = capsys.readouterr().out
    assert "num_demos=18" in out and "(--num-demos)" in out
    assert main(["--policy", f"{__name__}:free_kwargs_factory", "--policy-arg", "help"]) == 0
    assert "keyword arguments: (**kwargs)" in capsys.readouterr().out
