"""Paired comparison of two evaluation folders (agnostos_mjx.compare), on hand-made runs."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import pytest

from agnostos_mjx import compare as cmp


def record(task, split, seed, episode, success, outcome=None, steps=100):
    return {"task": task, "split": split, "seed": seed, "episode": episode, "success": success,
            "outcome": outcome or ("success" if success else "max_steps"), "key_actions": 3,
            "sim_steps": steps}


def write_run(folder: Path, records, gz=False) -> Path:
    folder.mkdir(parents=True)
    text = "".join(json.dumps(r) + "\n" for r in records)
    if gz:
        with gzip.open(folder / "episodes.jsonl.gz", "wt") as f:
            f.write(text)
    else:
        (folder / "episodes.jsonl").write_text(text)
    return folder


@pytest.fixture
def runs(tmp_path):
    # lamp_on (level 1): seeds 0 and 1, two episodes each; A solves 3 of 4, B 2 of 4.
    a = [record("lamp_on", "unseen_level1", 0, 0, True), record("lamp_on", "unseen_level1", 0, 1, True),
         record("lamp_on", "unseen_level1", 1, 0, True), record("lamp_on", "unseen_level1", 1, 1, False),
         record("water_plants", "unseen_level2", 0, 0, False), record("water_plants", "unseen_level2", 0, 1, False),
         record("water_plants", "unseen_level2", 1, 0, False), record("water_plants", "unseen_level2", 1, 1, False),
         record("lamp_off", "unseen_level1", 0, 0, True)]  # only in A
    b = [record("lamp_on", "unseen_level1", 0, 0, True), record("lamp_on", "unseen_level1", 0, 1, False),
         record("lamp_on", "unseen_level1", 1, 0, False), record("lamp_on", "unseen_level1", 1, 1, True),
         record("water_plants", "unseen_level2", 0, 0, True), record("water_plants", "unseen_level2", 0, 1, False),
         record("water_plants", "unseen_level2", 1, 0, False, steps=99),
         record("water_plants", "unseen_level2", 1, 1, False, outcome="unreachable")]
    return write_run(tmp_path / "a", a), write_run(tmp_path / "b", b, gz=True)


def test_paired_numbers_match_hand_computed_values(runs):
    result = cmp.compare(*(cmp.load_episodes(r) for r in runs))
    assert (result["shared_episodes"], result["only_in_a"], result["only_in_b"]) == (8, 1, 0)
    lamp, water = result["tasks"]["lamp_on"], result["tasks"]["water_plants"]
    # A: seeds 100, 50 -> 75 (std 25); B: 50, 50 -> 50.
    assert (lamp["a"], lamp["a_std"], lamp["b"]) == (75.0, 25.0, 50.0)
    assert (lamp["only_a"], lamp["only_b"], lamp["identical"]) == (2, 1, 1)
    # B solves seed 0 episode 0 only: 50, 0 -> 25; two episodes end differently (steps, outcome).
    assert (water["a"], water["b"], water["only_a"], water["only_b"]) == (0.0, 25.0, 0, 1)
    assert water["identical"] == 1
    # Groups: per seed the mean over tasks, then over seeds (lamp_off is not shared).
    assert result["groups"]["Level-1"]["a"] == 75.0 and result["groups"]["Level-2"]["b"] == 25.0
    assert result["groups"]["All"]["a"] == pytest.approx((50 + 25) / 2)  # seeds: (100+0)/2, (50+0)/2


def test_cli_writes_table_and_json(runs, tmp_path, capsys):
    out = tmp_path / "cmp" / "diff.md"
    assert cmp.main([str(runs[0]), str(runs[1]), "--labels", "native,warp", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| lamp_on | unseen_level1 | 4 | 75.0 | 50.0 | -25.0 | 2 | 1 | 1 |" in text
    assert "2 of 8 shared episodes ended identically." in text
    assert out.read_text() == text
    assert json.loads(out.with_suffix(".json").read_text())["labels"] == ["native", "warp"]


def test_bad_folders_are_clear_errors(runs, tmp_path, capsys):
    assert cmp.main([str(runs[0]), str(tmp_path / "missing")]) == 2
    assert "no episodes.jsonl" in capsys.readouterr().err
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "episodes.jsonl").write_text("{not json\n")
    assert cmp.main([str(runs[0]), str(broken)]) == 2
    assert "unreadable" in capsys.readouterr().err
    other = write_run(tmp_path / "other", [record("close_fridge", "unseen_level1", 0, 0, True)])
    assert cmp.main([str(runs[0]), str(other)]) == 2
    assert "share no task" in capsys.readouterr().err
    assert cmp.main([str(runs[0]), str(runs[1]), "--labels", "onlyone"]) == 2


# ---------------------------------------------------------------------------------------
# Statistics section (agnostos_mjx.infra.stats)
# ---------------------------------------------------------------------------------------
LEVEL1 = ("lamp_on", "lamp_off", "close_fridge")
LEVEL2 = ("water_plants", "turn_oven_on")


def protocol_run(flip=(), seeds=(0, 1, 2), episodes=25, seen=False):
    """Records of 3 seeds x 25 episodes per task, successes from a fixed pattern (about a third
    of the episodes); tasks in `flip` have every outcome flipped."""
    tasks = [(t, "unseen_level1") for t in LEVEL1] + [(t, "unseen_level2") for t in LEVEL2]
    if seen:
        tasks.append(("reach_target", "seen"))
    out = []
    for i, (task, split) in enumerate(tasks):
        for seed in seeds:
            for ep in range(episodes):
                success = (ep * 7 + seed * 3 + i) % 11 < 4 - (task == "close_fridge") * 3
                out.append(record(task, split, seed, ep, success != (task in flip)))
    return out


def test_identical_runs_p_one_and_zero_width(tmp_path, capsys):
    a = write_run(tmp_path / "a", protocol_run(seen=True))
    b = write_run(tmp_path / "b", protocol_run(seen=True))
    json_path = tmp_path / "out" / "numbers.json"
    assert cmp.main([str(a), str(b), "--json", str(json_path)]) == 0
    text = capsys.readouterr().out
    st = json.loads(json_path.read_text())["statistics"]
    assert st["fully_paired"] and st["unpaired_episodes"] == 0 and st["significant"] == []
    assert all(r["p"] == 1.0 and r["only_a"] == r["only_b"] == 0 for r in st["tasks"].values())
    assert list(st["groups"]) == ["Level-1", "Level-2", "All", "Seen"]
    for g in st["groups"].values():
        assert g["pairing"] == "paired" and g["diff"] == g["diff_low"] == g["diff_high"] == 0.0
    assert "All 450 episodes pair up by (task, seed, episode)" in text
    assert "| All (unseen) | 5 | paired | " in text and "| +0.0 [+0.0, +0.0] |" in text
    assert "No task differs at p < 0.05" in text


def test_one_flipped_task_is_the_only_significant_one(tmp_path, capsys):
    a = write_run(tmp_path / "a", protocol_run())
    b = write_run(tmp_path / "b", protocol_run(flip=("close_fridge",)))
    assert cmp.main([str(a), str(b), "--labels", "base,new"]) == 0
    text = capsys.readouterr().out
    result = cmp.compare(cmp.load_episodes(a), cmp.load_episodes(b))
    st = result["statistics"]
    assert st["significant"] == ["close_fridge"]
    fridge = st["tasks"]["close_fridge"]
    assert (fridge["n_a"], fridge["only_a"] + fridge["only_b"]) == (75, 75)
    assert fridge["p"] < 1e-6 and fridge["b"] > fridge["a"]
    assert fridge["a_low"] < fridge["a"] < fridge["a_high"]
    marked = [line.split(" | ")[0].strip("| ") for line in text.splitlines()
              if line.endswith("| * |")]
    assert marked == ["close_fridge"]
    assert "p < 0.05: close_fridge (McNemar" in text
    # Level-1 holds the flipped task: its interval excludes 0; Level-2 is unchanged.
    l1, l2 = st["groups"]["Level-1"], st["groups"]["Level-2"]
    assert 0 < l1["diff_low"] <= l1["diff"] <= l1["diff_high"]
    assert l1["diff"] == pytest.approx((fridge["b"] - fridge["a"]) / 3)
    assert l2["diff"] == l2["diff_low"] == l2["diff_high"] == 0.0
    # Deterministic for a seed.
    again = cmp.compare(cmp.load_episodes(a), cmp.load_episodes(b))["statistics"]["groups"]
    assert again == st["groups"]


def test_runs_on_other_seeds_fall_back_to_unpaired(tmp_path, capsys):
    a = write_run(tmp_path / "a", protocol_run())
    b = write_run(tmp_path / "b", protocol_run(seeds=(3, 4, 5)))
    assert cmp.main([str(a), str(b)]) == 0
    text = capsys.readouterr().out
    assert "The runs share no episode" in text
    assert "**The runs are not fully paired:** 750 episodes are unpaired (375 only in a, " \
           "375 only in b; 0 paired)" in text
    assert "compared unpaired on each run's own episodes, without McNemar's test" in text
    st = cmp.compare(cmp.load_episodes(a), cmp.load_episodes(b))["statistics"]
    assert st["unpaired_tasks"] == list(LEVEL1 + LEVEL2) and st["significant"] == []
    assert all(r["pairing"] == "unpaired" and r["p"] is None for r in st["tasks"].values())
    assert "| lamp_on | unseen_level1 | unpaired | 75 / 75 |" in text
    assert "No McNemar test: no task has episodes both runs hold." in text
    assert all(g["pairing"] == "unpaired" for g in st["groups"].values())
    assert st["groups"]["All"]["diff_low"] < st["groups"]["All"]["diff_high"]


def test_partly_paired_runs_say_what_is_left_out(runs, capsys):
    assert cmp.main([str(runs[0]), str(runs[1])]) == 0
    text = capsys.readouterr().out
    st = cmp.compare(*(cmp.load_episodes(r) for r in runs))["statistics"]
    assert (st["fully_paired"], st["unpaired_episodes"], st["paired_episodes"]) == (False, 1, 8)
    assert st["tasks_only_in_a"] == ["lamp_off"] and list(st["tasks"]) == ["lamp_on", "water_plants"]
    lamp = st["tasks"]["lamp_on"]
    assert (lamp["only_a"], lamp["only_b"], lamp["p"]) == (2, 1, 1.0)
    assert st["tasks"]["water_plants"]["p"] == pytest.approx(1.0)  # 0 vs 1 discordant: p = 1
    assert "**The runs are not fully paired:** 1 episode is unpaired (1 only in a, 0 only in b" in text
    assert "- Only in a (not compared): lamp_off." in text


def test_missing_episodes_are_left_out_of_paired_tasks(tmp_path, capsys):
    full = protocol_run(flip=("close_fridge",))
    cut = [r for r in full if not (r["task"] == "lamp_on" and r["seed"] == 2 and r["episode"] >= 20)]
    a = write_run(tmp_path / "a", protocol_run())
    b = write_run(tmp_path / "b", cut)
    assert cmp.main([str(a), str(b)]) == 0
    text = capsys.readouterr().out
    assert "5 episodes are unpaired (5 only in a, 0 only in b; 370 paired)" in text
    assert "5 unpaired episodes of them left out of the statistics" in text
    st = cmp.compare(cmp.load_episodes(a), cmp.load_episodes(b))["statistics"]
    lamp = st["tasks"]["lamp_on"]
    assert (lamp["pairing"], lamp["n_a"], lamp["n_b"], lamp["left_out"]) == ("paired", 70, 70, 5)
    assert st["significant"] == ["close_fridge"] and st["unpaired_tasks"] == []
    assert st["groups"]["Level-1"]["pairing"] == "paired"
