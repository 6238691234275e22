"""The seen-demo memory, demo selection and the retrieval baseline's transfer."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from agnostos_mjx.policies.retrieval import transfer
from agnostos_mjx.xicm.memory import DemoMemory, MemoryFileError, default_memory_path
from agnostos_mjx.xicm.query import Query
from agnostos_mjx.xicm.selection import (
    RandomSelector,
    TextSelector,
    make_selector,
    resolve_selection,
)


@pytest.fixture(scope="module")
def memory() -> DemoMemory:
    return DemoMemory.load(default_memory_path())


def test_shipped_memory_holds_seen_demos_in_xicm_text(memory):
    from agnostos_mjx.tasks import SEEN

    assert len(memory) >= 3000
    assert set(memory.task.tolist()) <= set(SEEN) and len(set(memory.task.tolist())) >= 16
    pattern = re.compile(r"^\['instruction': [^,]+.*\]>\[(\[\d+(, \d+){6}\](, )?)+\], $")
    for i in range(0, len(memory), 97):
        assert pattern.match(str(memory.text[i])), memory.text[i]
        n = int(memory.n_keys[i])
        assert n >= 1 and np.isfinite(memory.key_pos[i, :n]).all()


def test_random_selection_is_seeded_and_distinct(memory):
    sel = RandomSelector(memory)
    a, b, c = sel.select([Query("x", 1), Query("x", 1), Query("x", 2)], 18)
    assert len(set(a.tolist())) == 18 and a.tolist() == b.tolist() and a.tolist() != c.tolist()


def test_text_selection_ranks_matching_instructions_first(memory):
    [top] = TextSelector(memory).select([Query("open the bottom drawer", 0)], 5)
    assert str(memory.task[top[0]]) == "open_drawer"
    assert str(memory.instruction[top[0]]) == "open the bottom drawer"


def test_selection_modes_resolve_or_fail_clearly(memory):
    assert resolve_selection("auto", memory) == ("lang+vis.out" if memory.features else "text")
    assert resolve_selection("random", memory) == "random"
    bare = replace(memory, features={})
    with pytest.raises(ValueError, match="needs dynamics features"):
        make_selector("lang+vis.out", bare)
    with pytest.raises(ValueError, match="unknown selection"):
        make_selector("colour", bare)


def test_memory_round_trip_concat_and_errors(memory, tmp_path):
    part = DemoMemory(**{k: getattr(memory, k)[:3] for k in memory.__dataclass_fields__
                         if k != "features"}, features={"lang": np.ones((3, 4), np.float32)})
    both = DemoMemory.concat(part, part)
    assert len(both) == 6 and both.features["lang"].shape == (6, 4)
    both.save(tmp_path / "m.npz")
    back = DemoMemory.load(tmp_path / "m.npz")
    assert back.text.tolist() == both.text.tolist() and "lang" in back.features
    with pytest.raises(MemoryFileError, match="no demo memory"):
        DemoMemory.load(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(MemoryFileError, match="unreadable"):
        DemoMemory.load(tmp_path / "bad.npz")


def test_transfer_moves_actions_with_the_matched_object():
    demo_objects = np.array([[0.3, 0.0, 0.8], [0.5, 0.2, 0.8], [np.nan] * 3])
    query_objects = np.array([[0.2, -0.1, 0.8], [0.4, 0.3, 0.9]])
    keys = np.array([[0.3, 0.0, 0.9], [0.52, 0.2, 0.85]])
    moved = transfer(keys, demo_objects, query_objects)
    np.testing.assert_allclose(moved[0], [0.2, -0.1, 0.9], atol=1e-6)  # with object 0
    np.testing.assert_allclose(moved[1], [0.42, 0.3, 0.95], atol=1e-6)  # with object 1
    far = transfer(np.array([[5.0, 5.0, 5.0]]), demo_objects, query_objects)
    assert (far <= np.array([0.7, 0.5, 1.752]) + 1e-6).all()  # clipped to the action bounds


def test_packed_features_keep_similarities_and_rankings():
    from agnostos_mjx.dynamics.features import similarity
    from agnostos_mjx.xicm.memory import _pack_feature, _unpack_feature

    rng = np.random.default_rng(0)
    lang_rows = rng.normal(size=(5, 64)).astype(np.float32)
    features = {"lang": lang_rows[rng.integers(0, 5, 300)],  # few distinct rows, as lang
                "vis.out": rng.normal(size=(300, 64)).astype(np.float32)}
    packed = {k: _pack_feature(v) for k, v in features.items()}
    assert packed["lang"]["codes"].shape == (5, 64) and packed["lang"]["codes"].dtype == np.int8
    back = {k: _unpack_feature(p) for k, p in packed.items()}
    queries = {k: v[:20] for k, v in features.items()}
    exact = similarity(queries, features, "lang+vis.out", "cosine")
    approx = similarity(queries, back, "lang+vis.out", "cosine")
    assert np.abs(exact - approx).max() < 5e-3
    top = lambda s: np.argsort(-s, axis=1, kind="stable")[:, :18]  # noqa: E731
    overlap = np.mean([len(set(a) & set(b)) / 18 for a, b in zip(top(exact), top(approx))])
    assert overlap > 0.95


def test_a_bank_normalised_once_gives_the_same_similarities_bit_for_bit():
    """The selector normalises the memory once per run; the similarities must be exactly
    those of normalising both sides on every call (records stay identical)."""
    from agnostos_mjx.dynamics.features import normalised, normalised_similarity, similarity

    rng = np.random.default_rng(1)
    bank = {p: rng.normal(size=(200, 32)).astype(np.float32) for p in ("lang", "vis.out")}
    query = {p: rng.normal(size=(7, 32)).astype(np.float32) for p in ("lang", "vis.out")}
    for metric in ("cosine", "dot"):
        prepared = normalised(bank, "lang+vis.out", metric)
        once = normalised_similarity(normalised(query, "lang+vis.out", metric), prepared, metric)
        assert np.array_equal(once, similarity(query, bank, "lang+vis.out", metric))
    with pytest.raises(ValueError, match="unknown metric"):
        normalised(bank, "lang", "euclid")
    with pytest.raises(ValueError, match="no similarity"):
        normalised(bank, "random")


def test_shipped_model_selects_demos_of_the_querys_task(memory, bank_dir):
    """The shipped export and memory, end to end on CPU: a push_buttons first frame and
    instruction (from the tiny test bank, other seeds) retrieves push_buttons demos."""
    from agnostos_mjx.data import DemoBank
    from agnostos_mjx.xicm.dynamics_selector import DynamicsSelector

    assert set(memory.features) == {"lang", "vis.in", "vis.out"}
    demo = next(d for d in DemoBank(bank_dir).demos() if d.task == "push_buttons")
    frame = DemoBank(bank_dir).arrays("push_buttons")["rgb_front_first"][0]
    frame = np.kron(frame, np.ones((4, 4, 1), np.uint8))  # the tiny bank is 32 x 32
    selector = DynamicsSelector(memory, "lang+vis.out")
    assert selector.pipeline.diffusion.sample_steps == 10  # the measured default
    # Rows of several tasks' rounds share the sampler's calls: a query's demos do not depend
    # on its place in a call or on the rows beside it.
    alone = selector.submit([Query(demo.instruction, 0, frame)], 18)
    shared = selector.submit([Query("open the drawer", 1, np.roll(frame, 9, axis=1)),
                              Query("press it", 2, frame), Query(demo.instruction, 3, frame)], 18)
    (chosen,) = alone.result()
    tasks = memory.task[chosen].tolist()
    assert tasks.count("push_buttons") >= 15, tasks
    np.testing.assert_array_equal(chosen, shared.result()[2])


@pytest.mark.slow  # five times the sampling of the test above
def test_the_originals_50_ddim_steps_pick_nearly_the_same_demos(memory, bank_dir):
    from agnostos_mjx.data import DemoBank
    from agnostos_mjx.xicm.dynamics_selector import DynamicsSelector

    demo = next(d for d in DemoBank(bank_dir).demos() if d.task == "push_buttons")
    frame = DemoBank(bank_dir).arrays("push_buttons")["rgb_front_first"][0]
    frame = np.kron(frame, np.ones((4, 4, 1), np.uint8))
    query = [Query(demo.instruction, 0, frame)]
    (chosen,) = DynamicsSelector(memory, "lang+vis.out").select(query, 18)
    (chosen50,) = DynamicsSelector(memory, "lang+vis.out", sample_steps=50).select(query, 18)
    assert len(set(chosen50.tolist()) & set(chosen.tolist())) >= 15


def test_ddim_steps_flag_reaches_the_selection_policies():
    from agnostos_mjx.evaluation.config import parse_config, resolve_policy

    for policy in ("retrieval", "xicm"):
        argv = ["--policy", policy, "--ddim-steps", "20", "--llm-url", "http://x/v1",
                "--llm-model", "m"]
        _, kwargs, _ = resolve_policy(parse_config(argv))
        assert kwargs["sample_steps"] == 20
    _, kwargs, _ = resolve_policy(parse_config(["--policy", "retrieval"]))
    assert kwargs["sample_steps"] is None  # the selector's measured default


def test_instruction_features_are_encoded_once_per_text(memory, monkeypatch):
    """lang features depend on the text alone: a run encodes each instruction once."""
    import agnostos_mjx.xicm.dynamics_selector as ds

    class FakePipeline:
        calls: list[list[str]] = []
        chunk_size = 4

        def lang(self, texts):
            self.calls.append(list(texts))
            return np.stack([np.full(1024, len(t), np.float32) for t in texts])

    monkeypatch.setattr(ds, "load_pipeline", lambda *a, **k: FakePipeline())
    selector = ds.DynamicsSelector(memory, "lang")
    frame = np.zeros((128, 128, 3), np.uint8)
    first = selector.select([Query("open the drawer", 0, frame), Query("close it", 1, frame)], 3)
    again = selector.select([Query("close it", 2, frame), Query("open the drawer", 3, frame)], 3)
    assert FakePipeline.calls == [["close it", "open the drawer"]]
    np.testing.assert_array_equal(first[0], again[1])
    np.testing.assert_array_equal(selector.lang_features(["close it"])[0], np.full(1024, 8.0))


def test_selection_report_counts_every_selected_demo(tmp_path):
    import json

    from agnostos_mjx.bench.selection import main

    assert main(["--tasks", "lamp_on", "--scenes", "2", "--k", "3", "--selection", "text",
                 "--out", str(tmp_path)]) == 0
    (row,) = json.loads((tmp_path / "selection.json").read_text())["rows"]
    assert sum(row["histogram"].values()) == 2 * 3
    assert row["majority_share"] == row["histogram"][row["majority"]] / 6
    assert 1 <= row["scenes_with_that_majority"] <= 2
    assert "| lamp_on |" in (tmp_path / "selection.md").read_text()
    assert main(["--tasks", "no_such_task"]) == 2


def test_build_memory_extend_replaces_rerecorded_tasks(memory, bank_dir, tmp_path):
    """--extend keeps the other tasks' demos and swaps in the bank's demos of its tasks."""
    from agnostos_mjx.xicm.build_memory import main

    base = tmp_path / "base.npz"
    memory.save(base)
    out = tmp_path / "new.npz"
    assert main(["--bank", str(bank_dir), "--extend", str(base), "--out", str(out)]) == 0
    new = DemoMemory.load(out)
    bank_tasks = {"open_drawer", "push_buttons"}
    for t in sorted(set(memory.task.tolist())):
        expected = 2 if t in bank_tasks else int((memory.task == t).sum())
        assert int((new.task == t).sum()) == expected, t
    others = ~np.isin(memory.task, sorted(bank_tasks))
    np.testing.assert_array_equal(new.text[: others.sum()], memory.text[others])


@pytest.mark.slow  # two retrieval runs of 3 tasks with the selection's network
def test_tasks_gathering_their_selection_rows_record_what_sharing_records(tmp_path, monkeypatch):
    """The GPU's way (agnostos_mjx/infra/gather.py) through the whole evaluation, forced on the
    CPU: the rows of the tasks waiting at once go out together once all wait, and since a
    CPU row's result does not depend on its place, the records are those of rows shared as
    they come (the CPU's way)."""
    import json

    from agnostos_mjx import eval as ev
    from agnostos_mjx.infra.gather import RowBatcher
    from agnostos_mjx.xicm import dynamics_selector

    calls: list[int] = []
    work = RowBatcher._work

    def counted(self):
        fn = self.fn
        self.fn = lambda items: (calls.append(len(items)), fn(items))[1]
        return work(self)

    monkeypatch.setattr(RowBatcher, "_work", counted)
    args = ["--tasks", "lamp_on,close_microwave,take_usb_out_of_computer", "--seeds", "0",
            "--episodes", "2", "--batch", "2", "--quiet"]
    assert ev.main([*args, "--out", str(tmp_path / "shared")]) == 0
    monkeypatch.setattr(dynamics_selector, "rows_share_calls", lambda: False)
    calls.clear()
    assert ev.main([*args, "--out", str(tmp_path / "gathered")]) == 0
    assert calls and max(calls) > 2  # some call held more than one task's 2 rows

    def load(folder):
        rows = [json.loads(line) for line in (folder / "episodes.jsonl").read_text().splitlines()]
        return {(r["task"], r["episode"]): {k: v for k, v in r.items() if k != "wall_s"}
                for r in rows}

    assert len(load(tmp_path / "gathered")) == 6
    assert load(tmp_path / "gathered") == load(tmp_path / "shared")
