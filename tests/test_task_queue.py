"""--task-queue: processes take the next unclaimed task, longest first; claims are exclusive
and survive a resume with the process that holds the task's episodes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agnostos_mjx.evaluation.config import UsageError
from agnostos_mjx.evaluation.task_queue import (
    TaskQueue,
    balanced_shares,
    claim_order,
    expected_costs,
    expected_s,
    longest_first,
    prepare,
    split_by_seed,
    unit_task,
)
from agnostos_mjx.tasks import list_tasks


def test_longest_first_orders_by_expected_time_and_keeps_unknown_tasks_in_the_middle():
    names = ["close_fridge", "new_task", "place_cups", "lamp_on"]
    assert [names[i] for i in longest_first(names)] == [
        "place_cups", "new_task", "lamp_on", "close_fridge"]
    names = ["lamp_on", "straighten_rope", "put_toilet_roll_on_stand", "place_cups"]
    assert [names[i] for i in longest_first(names, "warp")] == [
        "put_toilet_roll_on_stand", "straighten_rope", "place_cups", "lamp_on"]
    assert longest_first(names, "jax") == longest_first(names, "warp")


def test_each_process_claims_its_balanced_share_first_then_the_rest_longest_first():
    names = list_tasks("unseen_level1") + list_tasks("unseen_level2")
    cost = expected_s(names)
    shares = balanced_shares(names, "native", 8)
    assert sorted(i for share in shares for i in share) == list(range(len(names)))
    # The 8 longest tasks start in 8 processes, and the shares' expected times differ by
    # less than the longest task (where the 3 longest could share one process before).
    assert sorted(share[0] for share in shares) == sorted(longest_first(names)[:8])
    loads = [sum(cost[i] for i in share) for share in shares]
    assert max(loads) - min(loads) < max(cost)
    # 3 tasks at once: a process takes from another share only what comes after its first 3.
    after3 = sorted((i for share in shares for i in share[3:]), key=longest_first(names).index)
    assert after3 and all(len(share) <= 4 for share in shares)
    for p, share in enumerate(shares):
        assert claim_order(names, "native", 8, p, overlap=3) == share + [
            i for i in after3 if i not in share]
    # One task at a time: a process that runs out takes the others' later tasks, longest
    # first, never a task its process starts first.
    later = sorted((i for share in shares for i in share[1:]), key=longest_first(names).index)
    for p, share in enumerate(shares):
        order = claim_order(names, "native", 8, p, overlap=1)
        assert order == share + [i for i in later if i not in share]
    assert claim_order(names, "native", 1, 0) == longest_first(names)


def test_a_task_longer_than_two_mean_shares_splits_by_seed():
    names = list_tasks("unseen_level1") + list_tasks("unseen_level2")
    # 16 processes: straighten_rope (123 of ~632 expected s) is 3.1 mean shares; on 8 it is
    # 1.6 and runs whole, alone in its process.
    units = split_by_seed(names, "native", 16, [0, 1, 2])
    assert [u for u in units if "@" in u] == [f"straighten_rope@{s}" for s in (0, 1, 2)]
    assert len(units) == len(names) + 2
    assert split_by_seed(names, "native", 8, [0, 1, 2]) == names
    assert unit_task("straighten_rope@2") == ("straighten_rope", 2)
    assert unit_task("lamp_on") == ("lamp_on", None)
    # Its units share its expected time; the others keep theirs.
    cost = dict(zip(units, expected_s(units)))
    assert cost["straighten_rope@0"] * 3 == expected_s(["straighten_rope"])[0]
    assert cost["lamp_on"] == expected_s(["lamp_on"])[0]
    assert sum(cost.values()) == pytest.approx(sum(expected_s(names)))
    # More processes split more; one process or one seed splits nothing.
    assert sum("@" in u for u in split_by_seed(names, "native", 32, [0, 1, 2])) > 3
    assert split_by_seed(names, "native", 1, [0, 1, 2]) == names
    assert split_by_seed(names, "native", 16, [0]) == names
    # The balanced shares then start the rope's seeds in three processes.
    shares = balanced_shares(units, "native", 16)
    firsts = [units[share[0]] for share in shares]
    assert {f"straighten_rope@{s}" for s in (0, 1, 2)} <= set(firsts)


def test_the_costs_file_keeps_the_claim_orders_and_thus_the_records():
    """The costs live in task_costs.json (tools/task_cost.py --write); these are the orders
    its shipped numbers give, which the processes' claims and so the records follow."""
    names = list_tasks("unseen_level1") + list_tasks("unseen_level2")
    costs = expected_costs()
    assert set(costs) == {"native", "warp"} and costs["native"]["straighten_rope"] == 123
    assert [claim_order(names, "native", 8, p, overlap=3) for p in range(8)] == [
        [18, 2], [21, 19, 8, 2], [14, 11, 7, 2], [0, 5, 6, 2], [12, 10, 4, 2],
        [22, 1, 13, 2], [15, 17, 20, 2], [9, 16, 3, 2]]
    assert [claim_order(names, "warp", 16, p)[:2] for p in range(16)] == [
        [0, 7], [1, 7], [10, 7], [12, 7], [14, 7], [18, 7], [15, 7], [9, 7], [19, 7], [5, 8],
        [16, 2], [22, 4], [20, 3], [11, 17], [6, 13], [21, 7]]
    assert [claim_order(list_tasks("seen"), "native", 4, p)[:3] for p in range(4)] == [
        [17, 16, 7], [5, 4, 1], [3, 9, 12], [2, 8, 6]]
    assert sum(expected_s(names)) == 633 and sum(expected_s(names, "warp")) == 757


def test_the_queue_reads_its_costs_without_jax():
    """Launchers import the queue before anything heavy: it must not pull in JAX."""
    import subprocess
    import sys

    code = ("import sys; from agnostos_mjx.evaluation.task_queue import expected_s; "
            "expected_s(['lamp_on']); print('jax' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "False"


def test_a_task_goes_to_one_process_only(tmp_path: Path):
    a, b = TaskQueue(tmp_path, 0), TaskQueue(tmp_path, 1)
    assert a.claim("lamp_on") and not b.claim("lamp_on")
    assert b.claim("lamp_off") and not a.claim("lamp_off")
    assert a.held(["lamp_off", "lamp_on", "open_drawer"]) == ["lamp_on"]
    assert a.claim("lamp_on")  # its own claim again: still its task
    assert (a.mine, b.mine) == (["lamp_on"], ["lamp_off"])
    assert (tmp_path / "lamp_on").read_text() == "0"


def test_claimed_runs_the_job_only_for_its_owner(tmp_path: Path):
    started = []

    def job(name):
        started.append(name)
        yield "future"
        return [name]

    a, b = TaskQueue(tmp_path, 0), TaskQueue(tmp_path, 1)
    mine = a.claimed("lamp_on", job("lamp_on"))
    assert next(mine) == "future"
    with pytest.raises(StopIteration) as stop:
        mine.send(None)
    assert stop.value.value == ["lamp_on"]
    with pytest.raises(StopIteration) as stop:  # b finds lamp_on taken: the job never starts
        next(b.claimed("lamp_on", job("lamp_on again")))
    assert stop.value.value == [] and started == ["lamp_on"]


def test_prepare_empties_the_queue_and_keeps_resumed_tasks_with_their_process(tmp_path: Path):
    queue, out = tmp_path / "queue", tmp_path / "run"
    queue.mkdir()
    (queue / "stale").write_text("3")
    for i, task in ((0, "lamp_off"), (1, "lamp_on"), (2, "open_drawer")):
        (out / f"proc-{i}").mkdir(parents=True)
        (out / f"proc-{i}" / "episodes.jsonl").write_text(
            json.dumps({"task": task, "seed": 0, "episode": 0}) + "\n")
    # A seed of lamp_on ran in process 0 as a unit of its own (split_by_seed).
    with (out / "proc-0" / "episodes.jsonl").open("a") as f:
        f.write(json.dumps({"task": "lamp_on", "seed": 2, "episode": 0}) + "\n")
    assert prepare(queue, out, processes=2) == {
        "lamp_off": 0, "lamp_off@0": 0, "lamp_on": 0, "lamp_on@2": 0, "lamp_on@0": 1}
    assert sorted(f.name for f in queue.iterdir()) == [
        "lamp_off", "lamp_off@0", "lamp_on", "lamp_on@0", "lamp_on@2"]
    assert not TaskQueue(queue, 0).claim("lamp_on@0") and TaskQueue(queue, 1).claim("lamp_on@0")
    assert TaskQueue(queue, 0).held(["lamp_on", "lamp_on@0", "lamp_on@2"]) == [
        "lamp_on", "lamp_on@2"]
    # proc-2 is not part of this launch: its task is free again
    assert TaskQueue(queue, 0).claim("open_drawer")


def test_a_missing_queue_folder_is_a_usage_error(tmp_path: Path):
    with pytest.raises(UsageError, match="no such folder"):
        TaskQueue(tmp_path / "missing", 0)


def test_a_process_imports_only_the_tasks_it_runs(tmp_path: Path):
    """Task modules are imported when their job starts (run._steps_of): a process of a task
    queue that claims one task of the main job's 23 imports that one (each module's `jnp`
    constants run op by op on a GPU at import).  The names are checked without importing:
    a wrong one is still a usage error before anything runs."""
    import subprocess
    import sys

    code = """
import sys
from agnostos_mjx.evaluation.config import parse_config
from agnostos_mjx.evaluation.protocol import select_tasks
from agnostos_mjx.evaluation.run import _steps_of
names = select_tasks(parse_config(["--tasks", "unseen"]))
job = _steps_of("lamp_on", None, [], None, None)
loaded = sorted(m for m in sys.modules if m.startswith("agnostos_mjx.tasks.")
                and m.rsplit(".", 1)[1] in names)
print(len(names), loaded)
try:
    next(job)
except Exception:
    pass
print(sorted(m for m in sys.modules if m.startswith("agnostos_mjx.tasks.")
             and m.rsplit(".", 1)[1] in names))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert out[0] == "23 []", out
    assert out[1] == "['agnostos_mjx.tasks.lamp_on']", out
    with pytest.raises(UsageError, match="unknown task 'lamp_onn'"):
        from agnostos_mjx.evaluation.config import parse_config
        from agnostos_mjx.evaluation.protocol import select_tasks

        select_tasks(parse_config(["--tasks", "lamp_on,lamp_onn"]))
