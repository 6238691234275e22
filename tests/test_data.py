"""Demonstration bank: generation, storage round trip, resume, corruption,
re-execution of the stored key actions, and X-ICM's text form.  Tiny: two
seen tasks x two demos at 32 x 32 pixels."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from agnostos_mjx.data import BankError, DemoBank
from agnostos_mjx.data import generate as gen
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.sim.actions import KeyActions
from agnostos_mjx.tasks import get_task
from tests.conftest import TASKS, tiny_bank_config


def config(out: Path, demos: int = 2) -> gen.GenerateConfig:
    return tiny_bank_config(out, demos)


def test_round_trip(bank_dir):
    bank = DemoBank(bank_dir)
    assert bank.tasks == list(TASKS) and len(bank) == 4
    for name in TASKS:
        task = get_task(name)
        demos = list(bank.demos(name))
        assert [d.index for d in demos] == [0, 1]
        for d in demos:
            assert d.variation == d.index % task.num_variations
            assert d.instruction == task.descriptions(d.variation)[0]
            assert list(d.descriptions) == task.descriptions(d.variation)
            assert list(d.objects) == list(task.objects)
            assert 1 <= len(d.key_ints) <= 25 and d.key_ints.shape[1] == 7
            assert d.key_open[-1] in (0.0, 1.0) and d.sim_steps > 0
            first, last = d.frames["front"]
            assert first.shape == last.shape == (32, 32, 3) and first.dtype == np.uint8
            assert np.abs(first.astype(int) - last.astype(int)).mean() > 0.5, "nothing moved"
            assert d.trajectory.shape[1] == 8
            np.testing.assert_allclose(d.trajectory[d.keyframes, :3], d.key_pos, atol=1e-6)
    first, last, instructions, tasks = bank.frame_pairs()
    assert first.shape == (4, 32, 32, 3) and tasks == ["open_drawer"] * 2 + ["push_buttons"] * 2
    assert len(instructions) == 4


def test_text_form_is_xicm(bank_dir):
    demo = DemoBank(bank_dir).demo("push_buttons", 0)
    text = demo.text()
    pattern = (r"^\['instruction': push the \w+ button, \{'button': \[\d+, \d+, \d+\]\}\]>"
               r"\[(\[\d+, \d+, \d+, \d+, \d+, \d+, [01]\](, )?)+\], $")
    assert re.match(pattern, text), text
    # Press = gripper closed before descending; the last action sits lower than the first.
    assert demo.key_ints[0, 6] == 1 and demo.key_ints[-1, 6] == 0
    assert demo.key_ints[-1, 2] < demo.key_ints[0, 2]


@pytest.mark.slow
def test_stored_key_actions_re_execute_to_success(bank_dir):
    bank = DemoBank(bank_dir)
    for name in TASKS:
        arrays = bank.arrays(name)
        episodes = Episodes(get_task(name), "native")
        keys = gen.demo_keys(3, name, arrays["index"], arrays["attempt"])
        env = episodes.reset(keys, arrays["variation"])
        for k in range(int(arrays["n_keys"].max())):
            valid = k < arrays["n_keys"]
            action = KeyActions(arrays["key_pos"][:, k], arrays["key_quat"][:, k],
                                arrays["key_open"][:, k], valid)
            env, _ = episodes.step(env, action)
        assert (env.outcome == Outcome.SUCCESS).all(), (name, env.outcome)


def _same_bank(a: Path, b: Path) -> None:
    for name in TASKS:
        x, y = DemoBank(a).arrays(name), DemoBank(b).arrays(name)
        assert sorted(x) == sorted(y)
        for key in x:
            np.testing.assert_array_equal(x[key], y[key], err_msg=f"{name}:{key}")


def _interrupt_at(monkeypatch, name: str, call: int) -> None:
    """Make the `call`-th call of generate.<name> raise KeyboardInterrupt."""
    real = getattr(gen, name)
    calls = {"n": 0}

    def wrapper(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == call:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(gen, name, wrapper)


@pytest.mark.parametrize("where, call", [
    pytest.param("_demo_arrays", 2, marks=pytest.mark.slow),  # killed simulating the 2nd task
    ("write_manifest", 1),  # killed between an archive write and its manifest write
])
def test_interrupted_run_resumes_to_the_same_bank(bank_dir, tmp_path, monkeypatch, where, call):
    cfg = config(tmp_path)
    with monkeypatch.context() as patch:
        _interrupt_at(patch, where, call)
        with pytest.raises(KeyboardInterrupt):
            gen.generate(cfg)
    gen.generate(cfg)
    _same_bank(bank_dir, tmp_path)


@pytest.mark.slow  # resuming a bank (test_interrupted_run_resumes_to_the_same_bank) stays in the default suite
def test_extending_a_bank_keeps_its_demos(bank_dir, tmp_path):
    import shutil

    shutil.copytree(bank_dir, tmp_path / "bank")
    gen.generate(replace(config(tmp_path / "bank", demos=3), tasks=("push_buttons",)))
    old, new = DemoBank(bank_dir), DemoBank(tmp_path / "bank")
    arrays = new.arrays("push_buttons")
    assert arrays["index"].tolist() == [0, 1, 2]
    for key, value in old.arrays("push_buttons").items():
        if key not in ("traj", "traj_offsets", "meta", "object_names"):
            np.testing.assert_array_equal(arrays[key][:2], value, err_msg=key)
    assert len(new) == 5


def test_corrupt_and_mismatched_banks_give_clear_errors(bank_dir, tmp_path):
    import shutil

    copy = tmp_path / "bank"
    shutil.copytree(bank_dir, copy)
    path = copy / "open_drawer.npz"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(BankError, match="open_drawer.npz.*checksum"):
        DemoBank(copy).arrays("open_drawer")
    DemoBank(copy).arrays("push_buttons")  # the other task is unaffected
    with pytest.raises(BankError, match="other settings.*seed"):
        gen.generate(replace(config(copy), seed=4))
    with pytest.raises(BankError, match="no manifest.json"):
        DemoBank(tmp_path / "nowhere")
    with pytest.raises(BankError, match="no demos of task 'lamp_on'"):
        DemoBank(bank_dir).arrays("lamp_on")


def test_cli_show_prints_text(bank_dir, capsys):
    from agnostos_mjx.data.show import main

    assert main([str(bank_dir), "--task", "open_drawer", "--index", "1"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("['instruction': open the middle drawer, {'drawer': [")
    assert main([str(bank_dir), "--task", "open_drawer", "--index", "7"]) == 2


@pytest.mark.parametrize("damage", ["compressed_bytes", "not_a_zip", "manifest_json",
                                    "manifest_fields"])
def test_cli_show_reports_any_corruption_in_one_line(bank_dir, tmp_path, capsys, damage):
    import hashlib
    import json
    import shutil

    from agnostos_mjx.data.show import main

    copy = tmp_path / "bank"
    shutil.copytree(bank_dir, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    archive = copy / "open_drawer.npz"
    if damage == "compressed_bytes":  # the checksum matches, the deflate stream does not
        import zipfile

        with zipfile.ZipFile(archive) as z:
            member = max(z.infolist(), key=lambda i: i.compress_size)
        data = bytearray(archive.read_bytes())
        start = member.header_offset + 30 + len(member.filename.encode())
        start += int.from_bytes(data[member.header_offset + 28:member.header_offset + 30],
                                "little")  # the local header's extra field
        data[start] = 0xFF  # an invalid deflate block type: zlib.error when read
        archive.write_bytes(bytes(data))
    elif damage == "not_a_zip":  # np.load would take it for pickled data
        archive.write_bytes(b"\x80\x04 not an archive" * 8)
    elif damage == "manifest_fields":
        del manifest["tasks"]["open_drawer"]["file"]
    manifest["tasks"]["open_drawer"]["sha256"] = hashlib.sha256(archive.read_bytes()).hexdigest()
    text = "{" if damage == "manifest_json" else json.dumps(manifest)
    (copy / "manifest.json").write_text(text)
    assert main([str(copy), "--task", "open_drawer"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and "pickle" not in err
    assert ("open_drawer.npz" if "manifest" not in damage else "manifest.json") in err


def test_cli_generate_unwritable_out_is_one_line(capsys):
    assert gen.main(["--out", "/proc/forbidden", "--tasks", "open_drawer", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot write to /proc" in err


@pytest.mark.slow
def test_worker_processes_make_the_same_bank(bank_dir, tmp_path):
    """Two spawned processes, one chunk each: the bank equals the in-process one."""
    report = gen.generate(replace(config(tmp_path), workers=2))
    assert report["workers"] == 2
    _same_bank(bank_dir, tmp_path)


def test_chunk_planning_covers_gaps_and_replaces_given_up_demos(tmp_path):
    cfg = replace(config(tmp_path, demos=10), batch=4)
    fresh = gen.plan_chunks(cfg, "t", {}, have=0)
    assert [(c.start, c.stop) for c in fresh] == [(0, 4), (4, 8), (8, 10)]
    # a run interrupted after two out-of-order chunks finished
    partial = gen.plan_chunks(cfg, "t", {"done": [[0, 4], [8, 10]]}, have=6)
    assert [(c.start, c.stop) for c in partial] == [(4, 8)]
    # everything ran but two demos were given up: fresh indices after the last one
    top_up = gen.plan_chunks(cfg, "t", {"done": [[0, 10]]}, have=8)
    assert [(c.start, c.stop) for c in top_up] == [(10, 12)]
    assert gen.plan_chunks(cfg, "t", {"done": [[0, 10]]}, have=10) == []
    # banks of the first format recorded a next index instead of intervals
    assert [(c.start, c.stop) for c in gen.plan_chunks(cfg, "t", {"next_index": 8}, 8)] == [(8, 10)]
    assert gen._add_interval([[0, 4], [8, 10]], 4, 8) == [[0, 10]]


def test_workers_need_the_native_backend(tmp_path):
    with pytest.raises(ValueError, match="needs --backend native"):
        gen.resolve_workers(replace(config(tmp_path), backend="warp", workers=2))
