"""Dense control (runtime/dense.py, evaluation/dense.py, the dense-replay policy) on native
MuJoCo at tiny batch: a replay of the expert's dense demo solves a seen task, relative rows
equal absolute ones, chunks run K rows then ask again, outcomes of bad targets, the step
budget, the device program against the host path, and the command line's errors."""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pytest

from agnostos_mjx import eval as ev
from agnostos_mjx.evaluation.config import UsageError
from agnostos_mjx.evaluation.dense import DenseDriver, PolicyAnswerError, as_chunk, check_answer
from agnostos_mjx.policies.base import Policy, Round
from agnostos_mjx.policies.dense_replay import DenseReplayPolicy
from agnostos_mjx.policies.learned_options import DenseReplayOptions
from agnostos_mjx.runtime.dense import DenseControl
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.sim.actions import KeyActions
from agnostos_mjx.tasks import SEEN, UNSEEN_LEVEL1, UNSEEN_LEVEL2
from tests.conftest import episodes_for

TASK = "turn_tap"  # a seen task with a short demo (3 key actions, about 90 control steps)


def _reset(b: int):
    ep = episodes_for(TASK)
    keys = jax.vmap(lambda e: jax.random.fold_in(jax.random.PRNGKey(0), e))(np.arange(b))
    return ep, ep.reset(keys, np.arange(b, dtype=np.int32) % ep.task.num_variations)


def _replay(ep, env, policy, ctl: DenseControl, steps: int | None = None, execute=None):
    driver = DenseDriver(execute, policy.relative)
    view = Round.for_policy(policy, ep, env, [""] * env.batch)
    for _ in range(steps or ctl.max_steps):
        if env.done.all():
            break
        gen = driver.next(policy, view.at(env), env)
        try:
            while True:
                next(gen)
        except StopIteration as stop:
            target = stop.value
        env, _ = ep.step_dense(env, target, ctl)
    return env, driver


@pytest.fixture(scope="module")
def replayed():
    """Two worlds of turn_tap, the replay policy reset on them."""
    ep, env = _reset(2)
    policy = DenseReplayPolicy()
    policy.reset(Round.for_policy(policy, ep, env, ["", ""]))
    return ep, env, policy


@pytest.mark.slow
def test_replay_of_the_dense_demo_solves_a_seen_task(replayed) -> None:
    ep, env, policy = replayed
    ctl = DenseControl.at(20, ep.dt, ep.task.max_key_actions)
    assert (ctl.period_steps, ctl.max_steps) == (10, 1000)
    assert policy.demo_success.all()
    out, driver = _replay(ep, env, policy, ctl)
    assert [Outcome(int(o)) for o in out.outcome] == [Outcome.SUCCESS] * 2
    # about one control step per demo frame (the replay lags the demo by a few)
    assert (out.key_actions <= policy.frames + 5).all() and driver.queries == out.key_actions.max()
    assert (out.sim_steps <= 10 * out.key_actions).all()


def test_relative_rows_reach_the_same_targets_as_absolute_ones(replayed) -> None:
    ep, env, policy = replayed
    ctl = DenseControl(10, 1000)
    absolute, _ = _replay(ep, env, policy, ctl, steps=25)
    rel = DenseReplayPolicy(DenseReplayOptions(relative=True))
    rel.pose, rel.gripper, rel.frames = policy.pose, policy.gripper, policy.frames
    relative, _ = _replay(ep, env, rel, ctl, steps=25)
    np.testing.assert_array_equal(relative.outcome, absolute.outcome)
    np.testing.assert_array_equal(relative.key_actions, absolute.key_actions)
    np.testing.assert_allclose(relative.data, absolute.data, atol=1e-6)


def test_chunks_run_k_rows_open_loop_then_ask_again() -> None:
    class Counting(Policy):
        name, action_modes, calls = "counting", ("dense",), 0

        def act(self, view) -> KeyActions:
            self.calls += 1
            h = 5
            pos = np.zeros((2, h, 3)) + 100 * self.calls + np.arange(h)[None, :, None]
            return KeyActions(pos, np.tile([1.0, 0, 0, 0], (2, h, 1)), np.ones((2, h)),
                              np.ones((2, h), bool), end_reason=np.array([0, self.calls]))

    policy = Counting()
    driver, env = DenseDriver(3, False), SimpleNamespace(batch=2)
    rows, reasons = [], []
    for _ in range(7):
        gen = driver.next(policy, None, env)
        with pytest.raises(StopIteration) as stop:
            next(gen)
        rows.append(stop.value.value.pos[0, 0])
        reasons.append(int(stop.value.value.end_reason[1]))
    assert policy.calls == driver.queries == 3
    assert rows == [100, 101, 102, 200, 201, 202, 300]
    assert reasons == [1, 1, 1, 2, 2, 2, 3]  # a chunk's end_reason goes with each of its rows


def test_answers_of_other_shapes_are_one_line_errors() -> None:
    """One checker for both action modes: rows (B, ...) always, chunks (B, H, ...) in dense
    mode; anything else names the shapes expected and given, in one line."""
    row = KeyActions(np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)), np.ones(2),
                     np.ones(2, bool))
    chunk = KeyActions(*(np.repeat(np.asarray(x)[:, None], 4, 1) for x in
                         (row.pos, row.quat, row.gripper, row.valid)))
    assert check_answer(row, 2, "p") == 0 and check_answer(chunk, 2, "p", chunks=True) == 4
    assert as_chunk(row, 2, "p").pos.shape == (2, 1, 3)
    bad = {"pos (2, 4)": row._replace(pos=np.zeros((2, 4))),
           "quat (4,)": row._replace(quat=np.array([1.0, 0, 0, 0])),  # broadcast silently
           "gripper (1,)": row._replace(gripper=np.ones(1)),
           "pos (3, 3)": row._replace(pos=np.zeros((3, 3)))}
    for got, answer in bad.items():
        for chunks in (False, True):
            with pytest.raises(PolicyAnswerError, match=re.escape(got)) as e:
                check_answer(answer, 2, "mine", chunks)
            assert str(e.value).startswith("policy mine answered pos ") and "\n" not in str(e.value)
            assert "expected KeyActions of pos (B, 3), quat (B, 4) wxyz, gripper (B,), valid (B,)" \
                in str(e.value) and str(e.value).endswith("B = 2 worlds")
    with pytest.raises(PolicyAnswerError, match=r"pos \(2, 4, 3\).*expected KeyActions of pos "
                                                r"\(B, 3\).*valid \(B,\), B = 2"):
        check_answer(chunk, 2, "mine")  # a chunk in key-action mode
    with pytest.raises(PolicyAnswerError, match="policy mine answered tuple, not KeyActions"):
        check_answer((row.pos, row.quat), 2, "mine")
    assert check_answer(row._replace(end_reason=np.array([0, 7])), 2, "p") == 0
    for reason in (np.array([7]), np.array([0.0, 7.0]), np.int32(7)):  # (B,) integers only
        for answer, chunks in ((row, False), (chunk, True)):
            with pytest.raises(PolicyAnswerError, match=r"end_reason .*expected None or "
                                                        r"\(2,\) integer Outcome codes"):
                check_answer(answer._replace(end_reason=reason), 2, "mine", chunks)
    assert isinstance(PolicyAnswerError("x"), UsageError)  # eval.py prints it in one line


def test_a_chunked_replay_gives_the_one_row_replay(replayed) -> None:
    """The replay's chunk rows follow the control steps executed, so any --execute
    replays the same demo: the episodes end alike."""
    ep, env, policy = replayed
    ctl = DenseControl(10, 1000)
    one, _ = _replay(ep, env, policy, ctl, steps=30)
    chunked = DenseReplayPolicy(DenseReplayOptions(chunk=4))
    chunked.pose, chunked.gripper, chunked.frames = policy.pose, policy.gripper, policy.frames
    out, driver = _replay(ep, env, chunked, ctl, steps=30, execute=3)
    assert driver.queries == 10
    np.testing.assert_array_equal(out.data, one.data)


def test_bad_targets_end_with_the_planner_verdicts_and_the_budget_with_max_steps() -> None:
    ep, env = _reset(5)
    obs = env.obs
    pos = np.array(obs["tip.pos"], np.float64)
    quat = np.array(obs["tip.quat"], np.float64)
    pos[1, 0] -= 0.05  # a reachable step
    pos[2, 0] = np.nan
    pos[4] = (0.69, 0.49, 1.75)  # inside the bounds, out of the arm's reach
    valid = np.array([True, True, True, False, True])
    ctl = DenseControl(10, 2)
    hold = KeyActions(pos, quat, np.ones(5), valid)
    env, _ = ep.step_dense(env, hold, ctl)
    assert [Outcome(int(o)) for o in env.outcome] == [
        Outcome.RUNNING, Outcome.RUNNING, Outcome.INVALID_ACTION, Outcome.NO_ACTION,
        Outcome.UNREACHABLE]
    assert env.key_actions.tolist() == [1, 1, 0, 0, 0]
    assert env.sim_steps.tolist() == [10, 10, 0, 0, 0]
    env, _ = ep.step_dense(env, hold, ctl)
    assert Outcome(int(env.outcome[0])) == Outcome.MAX_STEPS and env.key_actions[0] == 2


def test_dense_ik_clips_targets_into_the_bounds_and_gets_off_joint_limits() -> None:
    """A target outside the action bounds is the clipped target (the demos' own frames
    leave the box by fractions of a millimetre); a target the plain step stalls on at a
    joint limit (a reach_and_drag demo frame, 5.4 mm off) is solved by the limit-aware
    step from the same warm start."""
    from agnostos_mjx.sim import control

    kin = episodes_for(TASK).kin
    q0 = np.array([[0.06066866, -0.07606204, 0.08721349, -2.73897765, -1.67886055,
                    3.20776158, -2.22980038]])
    pos = np.array([[0.0795984, 0.13964653, 0.90512973]])
    quat = np.array([[0.1317151, 0.51603287, 0.83179581, 0.15645108]])
    q, status = control.dense_ik(kin, q0, pos, quat)
    assert status.tolist() == [control.Status.OK] and q[0, 6] == pytest.approx(kin.lower[6])
    _, pe, re = control._descend_np(kin, q0, np.arange(1), pos, quat / np.linalg.norm(quat),
                                    1, control.DENSE_IK_ITERS, restart=False)
    assert pe[0] > control.IK_POS_TOL  # the plain step alone stalls there
    out = pos + [[0.0, 0.5, 0.0]]
    clipped = np.clip(out, *map(np.array, control.ACTION_BOUNDS))
    for a, b in zip(control.dense_ik(kin, q0, out, quat), control.dense_ik(kin, q0, clipped, quat)):
        np.testing.assert_array_equal(a, b)


def test_the_gripper_moves_at_its_rate() -> None:
    """The gripper moves at its rate (a full close in 0.18 s: 4 control periods of 50 ms)
    and back when opened; nothing lies between the fingers, so nothing is grasped."""
    ep, env = _reset(1)
    obs = env.obs
    pos, quat = np.asarray(obs["tip.pos"], np.float64), np.asarray(obs["tip.quat"], np.float64)
    ctl = DenseControl(10, 100)
    grips = []
    for g in (0.0, 0.0, 0.0, 0.0, 1.0):
        env, _ = ep.step_dense(env, KeyActions(pos, quat, np.array([g]), np.ones(1, bool)), ctl)
        grips.append(round(float(env.gripper[0]) / 0.04, 4))
    assert grips == [0.7222, 0.4444, 0.1667, 0.0, 0.2778]
    assert not env.attached.any() and Outcome(int(env.outcome[0])) == Outcome.RUNNING


@pytest.mark.slow  # the device boundary runs in the default suite in test_key_action
def test_device_program_matches_host_path_on_native_physics(replayed) -> None:
    """The dense step's device program (DevicePhases stepping MuJoCo's C physics through
    host callbacks, IK in JAX) against the host path: same outcomes, poses within 1 cm."""
    from agnostos_mjx.physics.callback import callback_physics

    ep, env, policy = replayed
    ctl = DenseControl(10, 1000)
    host, _ = _replay(ep, env, policy, ctl, steps=40)
    physics = callback_physics(ep.scene.model, 2)
    dev = env
    view = Round.for_policy(policy, ep, env, ["", ""])
    for _ in range(40):
        dev = ep.dense_on_device(dev, policy.act(view.at(dev)), ctl, physics=physics)
    np.testing.assert_array_equal(dev.outcome, host.outcome)
    np.testing.assert_array_equal(dev.key_actions, host.key_actions)
    for key in ("tip.pos", *(f"{f}.pos" for f in ep.task.observed_frames)):
        if key in ep.scene.layout.names:
            assert np.abs(np.asarray(dev.obs[key]) - np.asarray(host.obs[key])).max() < 0.01


def test_the_replay_acts_on_the_export_frames() -> None:
    """The replay's frames are the export's (data/expert_frames.py): the proprioception of
    the rendered frames, bit for bit, at every K physics steps."""
    from agnostos_mjx.data.expert_frames import episode_observations, proprio_frames
    from agnostos_mjx.runtime.observation import ObservationSpec

    ep, env = _reset(1)
    spec = ObservationSpec(cameras=("front",), height=8, width=8, renderer="cpu")
    _, rendered, keys = episode_observations(ep, env.replace(stop_at_success=False), spec, 10)
    _, proprio, keys2 = proprio_frames(ep, env.replace(stop_at_success=False), 10)
    assert keys == keys2 and len(rendered[0]) == len(proprio[0]) > 50
    for a, b in zip(rendered[0], proprio[0]):
        for field in ("gripper_pose", "gripper_open", "joint_positions"):
            np.testing.assert_array_equal(a[field], b[field])


def _one_line_error(capsys: pytest.CaptureFixture) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and "Traceback" not in err
    return err


@pytest.mark.parametrize("args, expected", [
    (["--policy", "oracle", "--action-mode", "dense"],
     "policy oracle acts in keyaction mode, not dense"),
    (["--policy", "dense-replay"], "policy dense-replay acts in dense mode, not keyaction"),
    (["--policy", "oracle", "--execute", "3"], "--execute: only with --action-mode dense"),
    (["--policy", "dense-replay", "--action-mode", "dense", "--policy-arg", "chunk=0"],
     "--policy-arg chunk=0: must be an integer >= 1"),
])
def test_cli_errors(args: list[str], expected: str, tmp_path: Path,
                    capsys: pytest.CaptureFixture) -> None:
    assert ev.main([*args, "--tasks", TASK, "--quiet", "--out", str(tmp_path / "r")]) == 2
    assert expected in _one_line_error(capsys)
    with pytest.raises(SystemExit) as exc:
        ev.main(["--action-mode", "sparse"])
    assert exc.value.code == 2 and "invalid choice: 'sparse'" in capsys.readouterr().err


def test_cli_dense_replay_records_the_mode_and_budget(tmp_path: Path) -> None:
    out = tmp_path / "r"
    assert ev.main(["--policy", "dense-replay", "--action-mode", "dense", "--tasks", TASK,
                    "--seeds", "0", "--episodes", "1", "--batch", "1", "--backend", "native",
                    "--policy-arg", "chunk=4", "--execute", "3", "--dense-steps", "500",
                    "--quiet", "--out", str(out)]) == 0
    (record,) = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert record["success"] and record["action_mode"] == "dense"
    assert record["step_budget"] == 500 and record["control_hz"] == 20.0
    assert record["policy_info"]["demo_success"]
    config = json.loads((out / "results.json").read_text())["config"]["protocol"]
    assert config["action_mode"] == "dense" and config["execute"] == 3


def test_a_served_policy_drives_dense_control_over_http(tmp_path: Path) -> None:
    """The remote adapters work in dense mode: each answer row (OpenVLA's 7-D delta) is one
    control step's target; the budget ends the episode as max_steps."""
    from agnostos_mjx.remote.server import JsonNumpyServer

    asked: list[dict] = []
    up = np.array([0.0, 0.0, 0.005, 0.0, 0.0, 0.0, 1.0])  # 5 mm up per control step
    out = tmp_path / "r"
    with JsonNumpyServer(infer=lambda obs: asked.append(obs) or up) as server:
        assert ev.main(["--policy", "remote", "--policy-url", server.url, "--policy-arg",
                        "preset=openvla", "--policy-arg", "height=32", "--policy-arg",
                        "width=32", "--action-mode", "dense", "--dense-steps", "4",
                        "--tasks", TASK, "--seeds", "0", "--episodes", "1", "--batch", "1",
                        "--backend", "native", "--quiet", "--out", str(out)]) == 0
    (record,) = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert record["outcome"] == "max_steps" and record["key_actions"] == 4
    assert record["sim_steps"] == 40 and len(asked) == 4


def _hold(env) -> KeyActions:
    obs = env.obs
    b = env.batch
    return KeyActions(np.asarray(obs["tip.pos"], np.float32), np.asarray(obs["tip.quat"],
                                                                         np.float32),
                      np.ones(b, np.float32), np.ones(b, bool))


@pytest.mark.slow
def test_dense_device_program_traces_with_the_documented_shapes() -> None:
    """The dense step's MJX program traces to an EnvState of the input's shapes and dtypes
    (no compile, no physics: a cheap guard for the default suite; the slow test below runs
    it)."""
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    ep = Episodes(get_task(TASK), "jax")
    env = _reset(2)[1]  # reset natively: the same scene and shapes, no MJX compile
    ctl = DenseControl(10, 100)
    program = ep.dense_program(2, ctl)
    acts = jax.tree.map(jax.numpy.asarray, _hold(env))
    dev = env.to_device()
    plan = jax.eval_shape(ep.device_plans.dense_ik, dev.data[:, ep.spec.arm_q], acts.pos, acts.quat)
    out = jax.eval_shape(program, dev, acts, plan)
    assert (jax.tree.map(lambda x: (x.shape, x.dtype), out)
            == jax.tree.map(lambda x: (x.shape, x.dtype), dev))


@pytest.mark.slow
@pytest.mark.mjx_cpu  # MJX-jax's own physics compiled on the CPU
def test_dense_device_step_matches_host_path_on_mjx() -> None:
    """MJX-jax's own physics (slow: mostly compiling): the replay's
    first 40 control steps on the device program and on the host path (record=True) end
    alike."""
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    ep = Episodes(get_task(TASK), "jax")
    env = ep.reset(jax.random.split(jax.random.PRNGKey(0), 2), np.zeros(2, np.int32))
    policy = DenseReplayPolicy()
    view = Round.for_policy(policy, ep, env, ["", ""])
    policy.reset(view)
    ctl = DenseControl(10, 1000)
    host, dev = env, env
    for _ in range(40):
        host, _ = ep.step_dense(host, policy.act(view.at(host)), ctl, record=True)
        dev, _ = ep.step_dense(dev, policy.act(view.at(dev)), ctl)
    np.testing.assert_array_equal(dev.outcome, host.outcome)
    np.testing.assert_array_equal(dev.key_actions, host.key_actions)
    assert np.abs(np.asarray(dev.obs["tip.pos"]) - np.asarray(host.obs["tip.pos"])).max() < 0.01


@pytest.mark.slow  # 41 tasks x the whole dense budget
@pytest.mark.parametrize("name", sorted(SEEN + UNSEEN_LEVEL1 + UNSEEN_LEVEL2))
def test_a_gripper_held_still_solves_no_task(name: str) -> None:
    """A policy that holds the gripper where it starts, open, for the whole dense budget
    succeeds on no task: nothing in a scene drifts into its success state by itself (a USB
    stick once crept out of its port and fell within 6,000 physics steps)."""
    ep = episodes_for(name)
    keys = jax.random.split(jax.random.PRNGKey(0), 1)
    env = ep.reset(keys, np.zeros(1, np.int32))
    ctl = DenseControl.at(20.0, ep.dt, ep.task.max_key_actions)
    target = _hold(env)
    for _ in range(ctl.max_steps):
        env, _ = ep.step_dense(env, target, ctl)
        if env.done.all():
            break
    assert int(env.outcome[0]) != Outcome.SUCCESS, f"{name} solved by holding still"
