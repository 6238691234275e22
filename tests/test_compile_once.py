"""A run compiles a known set of programs: the composition of a batch (which worlds are
active, how many scenes a reset rejects) never changes a compiled shape (issue 13)."""

from __future__ import annotations

import collections
import contextlib
import json
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.sim.actions import KeyActions
from agnostos_mjx.tasks import get_task

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
COMPILE_EVENTS_TOOL = Path(__file__).resolve().parents[1] / "tools" / "compile_events.py"


@contextlib.contextmanager
def count_compiles():
    seen: list[str] = []

    def listener(event: str, duration: float, **_) -> None:
        if event == COMPILE_EVENT:
            seen.append(event)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def _keys(seed: int, n: int):
    return jax.vmap(lambda e: jax.random.fold_in(jax.random.PRNGKey(seed), e))(np.arange(n))


def test_batch_composition_compiles_nothing_new():
    ep = Episodes(get_task("close_fridge"), "native")  # rejects some scenes at reset
    b = 6
    with count_compiles() as warmup:  # every program of a reset and a key action
        env = ep.reset(_keys(0, b), np.zeros(b, np.int32))
        first = ep.expert_actions(env)
        step = KeyActions(*(np.asarray(x)[:, 0] for x in (first.pos, first.quat, first.gripper)),
                          np.ones(b, bool))
        ep.step(env, step)
    assert warmup, "the listener must see the first compiles"
    with count_compiles() as compiles:
        for seed in (1, 2, 3):  # other scenes, other numbers of rejected placements
            env = ep.reset(_keys(seed, b), np.zeros(b, np.int32))
            actions = ep.expert_actions(env)
            valid = np.arange(b) % seed != 0  # a different set of worlds acts each time
            pos, quat, grip = (np.asarray(x)[:, 0] for x in (actions.pos, actions.quat,
                                                              actions.gripper))
            ep.step(env, KeyActions(pos, quat, grip, valid))
    assert compiles == []


def test_ik_programs_are_shared_by_every_task():
    """The robot is the same in every scene, so the jitted planner and reachability check
    (most of a key action's compile time) are one program per run, not one per task."""
    from agnostos_mjx.sim import control

    kins = [Episodes(get_task(name), "native").kin for name in ("lamp_on", "stack_blocks")]
    assert kins[0] is not kins[1] and kins[0].fingerprint == kins[1].fingerprint
    for fn in (control.plan_arm, control.reachable):
        assert control.jit_for_robot(fn, kins[0]) is control.jit_for_robot(fn, kins[1])
    assert control.jit_for_robot(control.plan_arm, kins[0]) is not control.jit_for_robot(
        control.reachable, kins[0])


def test_phases_of_any_length_share_one_condition_program():
    """The host scans a phase's conditions in chunks of CONDITION_ROWS rows: phases of any
    length run one compiled program and find the same first success as one scan over all
    the rows."""
    from agnostos_mjx.runtime.phase import CONDITION_ROWS, HostPhases

    ep = Episodes(get_task("lamp_on"), "native")
    start = ep.reset(_keys(0, 3), np.zeros(3, np.int32))
    record: list = []
    ep.run_expert(start, record=record)
    assert start.stop_at_success is not None
    rows = [np.concatenate([getattr(r, f) for r in record], axis=1)
            for f in ("sensordata", "attached")]
    conditions = ep.programs[("conditions",)]
    whole = conditions(start.carry, *rows, np.ones(rows[0].shape[:2], bool), start.variation)
    assert (np.asarray(whole[1]) > CONDITION_ROWS).all(), "success must come after a chunk"
    phases = HostPhases(ep.backend, ep.scene.model, conditions)
    with count_compiles() as compiles:
        for t in (rows[0].shape[1], CONDITION_ROWS + 5, 40):
            valid = np.ones((3, t), bool)
            carry, s, f = phases._scan(start, rows[0][:, :t], rows[1][:, :t], valid)
            want = conditions(start.carry, rows[0][:, :t], rows[1][:, :t], valid,
                              start.variation)
            np.testing.assert_array_equal(s, np.asarray(want[1]))
            np.testing.assert_array_equal(f, np.asarray(want[2]))
            for x, y in zip(jax.tree.leaves(carry), jax.tree.leaves(want[0])):
                np.testing.assert_array_equal(x, np.asarray(y))
    # the whole-phase scans compile a program per length; the chunked one none after its first
    assert len(compiles) == 2


def _programs(tmp_path: Path, task: str, seeds: str) -> collections.Counter:
    """The programs an evaluation process lowers (compiled, or read from the persistent
    cache): the default policy, `task`, batches of 2 worlds, 2 episodes per seed."""
    out = tmp_path / f"{task}-{seeds}"
    subprocess.run([sys.executable, str(COMPILE_EVENTS_TOOL), "--json", str(out / "ev.json"),
                    "--", "--tasks", task, "--batch", "2", "--episodes", "2", "--seeds", seeds,
                    "--quiet", "--out", str(out)], check=True, capture_output=True, text=True)
    events = json.loads((out / "ev.json").read_text())["events"]
    return collections.Counter(e["fun"] for e in events
                               if e["event"] == "jaxpr_to_mlir_module_duration")


@pytest.mark.slow  # three evaluation processes
def test_a_task_batch_runs_at_most_8_programs_and_more_batches_no_more(tmp_path):
    """Reset (keys, placement, the settled scene's conditions and expert), the condition
    scan, the state colours or the grasp test, and the selection (instruction feature, the
    bank normalised once, one program from the frames to the scores) are all of a task's
    programs: 3 batches lower the same ones as 1."""
    one = _programs(tmp_path, "lamp_on", "0")
    assert sum(one.values()) <= 8, one
    assert _programs(tmp_path, "lamp_on", "0,1,2") == one
    grasping = _programs(tmp_path, "phone_on_base", "0")  # the grasp test, no state colours
    assert sum(grasping.values()) <= 8, grasping


@pytest.mark.slow  # compiles the jitted IK check on the CPU
def test_the_device_planners_reset_check_is_one_program_for_resets_and_tasks():
    """With the jitted planner (every GPU host's default) a reset's reachability check runs
    at the batch's size and at a multiple of REACH_STEPS key actions: re-sampling any number
    of scenes, other seeds and other tasks reuse one program (each size compiled one, 9 in
    this test), and the scenes kept are those of the check at each size."""
    lowered: list[str] = []

    def listener(event: str, duration: float, **kw) -> None:
        if event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            lowered.append(str(kw.get("fun_name")))

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        for name in ("close_fridge", "lamp_on"):  # close_fridge re-samples some scenes
            device = Episodes(get_task(name), "native", planner="device")
            for seed in range(3):
                device.reset(_keys(seed, 6), np.zeros(6, np.int32))
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert lowered.count("jit(reachable)") == 1, lowered

    ep = Episodes(get_task("close_fridge"), "native", planner="device")
    env = ep.reset(_keys(0, 6), np.zeros(6, np.int32))
    actions = ep.expert_actions(env)
    q = np.asarray(env.data[:, ep.spec.arm_q])
    unpadded = np.asarray(ep.plans.reachable(q, actions.pos, actions.quat, actions.valid))
    np.testing.assert_array_equal(ep.expert_reachable(env), unpadded)
    np.testing.assert_array_equal(ep.expert_reachable(env.replace(
        **{f: getattr(env, f)[:2] for f in ("data", "initial_data", "variation", "attached")})),
        unpadded[:2])
