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
    other = write_run(tmp_path / "other", [record("lamp_on", "unseen_level1", 7, 0, True)])
    assert cmp.main([str(runs[0]), str(other)]) == 2
    assert "share no" in capsys.readouterr().err
    assert cmp.main([str(runs[0]), str(runs[1]), "--labels", "onlyone"]) == 2
