"""The dynamics diffusion model on CPU with the quick preset: training, checkpoints,
features and selection.  One autoencoder run and one dynamics run of two steps
each are shared by the module (compiles dominate the run time)."""

from __future__ import annotations

import json
import shutil
import sys
import types
from dataclasses import replace

import jax
import numpy as np
import pytest
from flax import nnx

from agnostos_mjx.dynamics.autoencoder import Autoencoder, autoencoder_loss
from agnostos_mjx.dynamics.checkpoint import CheckpointError, Checkpoints
from agnostos_mjx.dynamics.config import (
    AE_QUICK,
    DIFFUSION_QUICK,
    TEXT_QUICK,
    TRAIN_QUICK,
    UNET_QUICK,
)
from agnostos_mjx.dynamics.data import FramePairs, synthetic
from agnostos_mjx.dynamics.diffusion import DynamicsModel, diffusion_loss
from agnostos_mjx.dynamics.features import (
    DemoSelector,
    FeatureIndex,
    build_index,
    extract,
    leave_one_out_same_task,
    parse_mode,
    select,
    similarity,
)
from agnostos_mjx.dynamics.layers import abstract, create
from agnostos_mjx.dynamics.pipeline import Pipeline, load_autoencoder
from agnostos_mjx.dynamics.text import tokenize
from agnostos_mjx.train import autoencoder as ae_cli
from agnostos_mjx.train import dynamics as dyn_cli
from agnostos_mjx.train import evaluate as eval_cli
from agnostos_mjx.train.autoencoder import train_autoencoder
from agnostos_mjx.train.common import make_step, optimizer
from agnostos_mjx.train.dynamics import train_dynamics

TCFG = replace(TRAIN_QUICK, steps=2, batch_size=4, ckpt_every=1, log_every=1, holdout_every=4)


@pytest.fixture(scope="module")
def pairs() -> FramePairs:
    return synthetic(12, seed=0)


@pytest.fixture(scope="module")
def ae_run(tmp_path_factory, pairs):
    out = tmp_path_factory.mktemp("ae")
    train_autoencoder(pairs, AE_QUICK, TCFG, out, progress=False)
    return out


@pytest.fixture(scope="module")
def dyn_run(tmp_path_factory, pairs, ae_run):
    out = tmp_path_factory.mktemp("dyn")
    train_dynamics(
        pairs, ae_run, TEXT_QUICK, UNET_QUICK, DIFFUSION_QUICK, TCFG, out, progress=False
    )
    return out


@pytest.fixture(scope="module")
def pipe(dyn_run) -> Pipeline:
    return Pipeline.load(dyn_run)


def _losses_before_after(model: nnx.Module, loss_fn, batch) -> tuple[float, float]:
    """The jitted step returns the loss at the params it was given: two calls on
    the same batch and key give the loss before and after one update."""
    graphdef, params = nnx.split(model)
    tx = optimizer(TCFG)  # the fixtures' optimiser: the compiled step can come from the cache
    step = make_step(graphdef, tx, loss_fn)
    key = jax.random.key(1)
    params, opt_state, before = step(params, tx.init(params), batch, key)
    _, _, after = step(params, opt_state, batch, key)
    return float(before), float(after)


def test_one_step_lowers_autoencoder_loss(pairs):
    model = create(lambda: Autoencoder(AE_QUICK, rngs=nnx.Rngs(0)))
    before, after = _losses_before_after(
        model, lambda m, b, k: autoencoder_loss(m, b, k, 1e-4), pairs.first[:4]
    )
    assert after < before


@pytest.mark.slow  # a long compile; the training fixtures run the same loss
def test_one_step_lowers_diffusion_loss():
    model = create(lambda: DynamicsModel(TEXT_QUICK, UNET_QUICK, rngs=nnx.Rngs(0)))
    z = np.random.default_rng(0).normal(size=(2, 4, 16, 16, 4)).astype(np.float32)
    ids, mask = tokenize(["push the red block left"] * 4, TEXT_QUICK.max_len)
    before, after = _losses_before_after(
        model, lambda m, b, k: diffusion_loss(m, DIFFUSION_QUICK, *b, k), (z[0], z[1], ids, mask)
    )
    assert after < before


@pytest.mark.slow
def test_training_writes_log_checkpoints_and_samples(ae_run, dyn_run):
    for run in (ae_run, dyn_run):
        log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
        assert [r["step"] for r in log] == [1, 2] and all(np.isfinite(r["loss"]) for r in log)
        assert Checkpoints(run / "checkpoints").latest_step() == 2
        assert (run / "samples" / "step_0000002.png").exists()
        assert json.loads((run / "config.json").read_text())["train"]["steps"] == 2


def test_checkpoint_round_trip(tmp_path):
    a = create(lambda: Autoencoder(AE_QUICK, rngs=nnx.Rngs(0)))
    b = abstract(lambda: Autoencoder(AE_QUICK, rngs=nnx.Rngs(1)))
    ckpts = Checkpoints(tmp_path / "checkpoints")
    ckpts.save(7, {"params": nnx.state(a)}, {"kind": "x", "model": {"n": 1}})
    trees, meta = ckpts.restore({"params": nnx.state(b)}, {"kind": "x", "model": {"n": 1}})
    assert meta["step"] == 7
    for x, y in zip(jax.tree.leaves(nnx.state(a)), jax.tree.leaves(trees["params"])):
        np.testing.assert_array_equal(x, y)


class _ShardingProbe(nnx.Module):
    """Asks a traced value for its sharding, as flax's Variable.set_value does on every
    RNG draw (JAX answers with an AttributeError, which getattr would swallow)."""

    def __init__(self, rngs: nnx.Rngs):
        self.w = nnx.Param(jax.random.normal(rngs(), (3, 2)))
        with pytest.raises(AttributeError, match="sharding"):
            _ = (self.w[...] * 2.0).sharding


def test_building_modules_skips_the_unseen_error_message_walk(monkeypatch):
    """layers.abstract / create: while a constructor is traced, a tracer's AttributeError
    does not walk back through the whole trace for its message (quadratic: most of
    loading the shipped dynamics model with jax 0.10 / flax 0.12), and JAX's method is back afterwards."""
    from jax._src.interpreters import partial_eval

    frame, tracer = partial_eval.JaxprStackFrame, partial_eval.DynamicJaxprTracer
    if "find_progenitors" not in frame.__dict__ or "_origin_msg" not in tracer.__dict__:
        pytest.skip("this JAX has no error-message walk to skip")
    walks = []
    walk = frame.find_progenitors
    monkeypatch.setattr(frame, "find_progenitors",
                        lambda self, t: walks.append(1) or walk(self, t))
    original = tracer.__dict__["_origin_msg"]
    assert abstract(lambda: _ShardingProbe(nnx.Rngs(0))).w.shape == (3, 2)
    assert create(lambda: _ShardingProbe(nnx.Rngs(0))).w[...].shape == (3, 2)
    assert walks == []
    assert tracer.__dict__["_origin_msg"] is original


@pytest.mark.slow
def test_resume_continues_step_count_and_matches_uninterrupted(tmp_path, pairs, ae_run):
    """Interrupt after step 1 (lose checkpoint 2 and a log line past it), resume:
    the run goes on from step 1 and ends where the uninterrupted one did."""
    run = tmp_path / "run"
    shutil.copytree(ae_run, run)
    shutil.rmtree(run / "checkpoints" / "2")
    train_autoencoder(pairs, AE_QUICK, TCFG, run, progress=False)
    steps = [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert steps == [1, 2]  # step 1 from before, step 2 after resuming (the stale line dropped)
    assert Checkpoints(run / "checkpoints").latest_step() == 2
    (a, _), (b, _) = load_autoencoder(run), load_autoencoder(ae_run)
    for x, y in zip(jax.tree.leaves(nnx.state(a)), jax.tree.leaves(nnx.state(b))):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_missing_checkpoint_is_a_clear_error(tmp_path, dyn_run):
    with pytest.raises(CheckpointError, match=str(tmp_path / "nowhere")):
        Pipeline.load(tmp_path / "nowhere")
    (tmp_path / "empty" / "checkpoints").mkdir(parents=True)
    with pytest.raises(CheckpointError, match="no checkpoint found in .*empty"):
        load_autoencoder(tmp_path / "empty")
    with pytest.raises(CheckpointError, match="'dynamics' checkpoint, expected 'autoencoder'"):
        load_autoencoder(dyn_run)


@pytest.mark.slow
def test_incompatible_checkpoint_names_what_mismatched(tmp_path, pairs, ae_run):
    run = tmp_path / "ae"
    shutil.copytree(ae_run, run)
    wider = replace(AE_QUICK, channels=(8, 16, 16, 32))
    with pytest.raises(
        CheckpointError,
        match=r"(?s)incompatible.*autoencoder\.channels: checkpoint has \[8, 16, 16, 16\]",
    ):
        train_autoencoder(pairs, wider, TCFG, run, progress=False)
    # Same metadata, other shapes: the parameter is named.
    ckpts = Checkpoints(run / "checkpoints")
    meta = ckpts.meta()
    template = {"params": nnx.state(abstract(lambda: Autoencoder(wider, rngs=nnx.Rngs(0))))}
    with pytest.raises(CheckpointError, match=r"params\.decoder\.conv_in\.kernel.*: shape"):
        ckpts.restore(template, {"kind": meta["kind"], "model": meta["model"]})


@pytest.mark.slow
def test_feature_shapes_and_determinism(pipe, pairs):
    first, instr = pairs.first[:3], pairs.instructions[:3]
    a = extract(pipe, first, instr)
    b = extract(pipe, first, instr)
    assert set(a) == {"lang", "vis.in", "vis.out"}
    for part in a:
        assert a[part].shape == (3, 1024) and a[part].dtype == np.float32
        assert np.all(np.isfinite(a[part]))
        np.testing.assert_array_equal(a[part], b[part])
    # A demo's features do not depend on the batch it is computed in.
    one = extract(pipe, first[1:2], instr[1:2])
    for part in a:
        np.testing.assert_allclose(one[part][0], a[part][1], rtol=1e-4, atol=1e-4)


@pytest.mark.slow  # trains the quick model (the pipe fixture)
def test_the_selections_one_program_gives_the_features_scores_bit_for_bit(pipe, pairs):
    """query_similarity (frames to scores in one compiled program) gives exactly the
    scores of extract, normalised and normalised_similarity one after the other."""
    from agnostos_mjx.dynamics.features import normalised, normalised_similarity, query_similarity

    first, instr = pairs.first[:4], pairs.instructions[:4]
    bank = extract(pipe, pairs.first[4:], pairs.instructions[4:])
    query = extract(pipe, first, instr)
    for mode, metric in (("lang+vis.out", "cosine"), ("vis.in+vis.out", "dot")):
        prepared = normalised(bank, mode, metric)
        want = normalised_similarity(normalised(query, mode, metric), prepared, metric)
        got = query_similarity(pipe, first, instr, query["lang"], prepared, metric)
        np.testing.assert_array_equal(got, want)


@pytest.mark.slow
def test_lang_depends_on_the_instruction(pipe):
    lang = pipe.lang(
        [
            "push the red block left",
            "slide the blue block up",
            "öffne die schublade",
            "push the red block left",
        ]
    )
    assert not np.allclose(lang[0], lang[1]) and not np.allclose(lang[0], lang[2])
    np.testing.assert_array_equal(lang[0], lang[3])


def _bank(m: int = 30, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {p: rng.normal(size=(m, 1024)).astype(np.float32) for p in ("lang", "vis.in", "vis.out")}


@pytest.mark.parametrize(
    "mode",
    [
        "lang",
        "vis.in",
        "vis.out",
        "lang+vis.in",
        "lang+vis.out",
        "vis.in+vis.out",
        "lang+vis.in+vis.out",
    ],
)
def test_selection_is_most_similar_first(mode):
    bank = _bank()
    rng = np.random.default_rng(1)
    query = {p: bank[p][5] + 0.1 * rng.normal(size=1024) for p in bank}
    chosen = select(query, bank, mode=mode, k=18)
    assert len(chosen) == 18 and len(set(chosen)) == 18 and chosen[0] == 5
    sims = similarity(query, bank, mode)[0]
    assert np.all(np.diff(sims[chosen]) <= 0)
    assert np.all(sims[chosen].min() >= np.delete(sims, chosen))
    # Only the named parts matter: scrambling another part changes nothing.
    other = [p for p in bank if p not in parse_mode(mode)]
    if other:
        scrambled = {**bank, other[0]: bank[other[0]][::-1]}
        np.testing.assert_array_equal(select(query, scrambled, mode=mode), chosen)


def test_similarity_runs_in_float32_on_the_device():
    """The bank is normalised once and stays on the device; a round's scores are float32
    cosines (the mean over parts), as float64 gives them to 1e-6."""
    from agnostos_mjx.dynamics.features import normalised, normalised_similarity

    bank = _bank()
    prepared = normalised(bank, "lang+vis.out")
    assert all(isinstance(v, jax.Array) and v.dtype == np.float32 for v in prepared.values())
    query = {p: bank[p][:3] + 0.5 for p in bank}
    sims = normalised_similarity(normalised(query, "lang+vis.out"), prepared)

    def unit(x):
        x = np.asarray(x, np.float64)
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    want = sum(unit(query[p]) @ unit(bank[p]).T for p in ("lang", "vis.out")) / 2
    assert sims.dtype == np.float32 and sims.shape == (3, len(bank["lang"]))
    np.testing.assert_allclose(sims, want, atol=1e-6)


def test_selection_modes_random_dot_and_exclude():
    bank = _bank()
    r1, r2 = select({}, bank, mode="random", seed=3), select({}, bank, mode="random", seed=3)
    np.testing.assert_array_equal(r1, r2)
    assert len(set(r1)) == 18 and not np.array_equal(r1, select({}, bank, mode="random", seed=4))
    assert parse_mode("lang_vis.out") == parse_mode("lang+vis.out") == ("lang", "vis.out")
    with pytest.raises(ValueError, match="bad selection mode"):
        parse_mode("vision")
    # The original's dot product lets a large-norm item win; cosine does not.
    query = {"lang": bank["lang"][2], "vis.out": bank["vis.out"][2]}
    loud = {p: v.copy() for p, v in bank.items()}
    loud["lang"][9] = 100 * (0.3 * bank["lang"][2] + bank["lang"][9])  # cosine ~0.3, norm x100
    assert select(query, loud, metric="cosine")[0] == 2
    assert select(query, loud, metric="dot")[0] == 9
    excluded = np.zeros(30, bool)
    excluded[2] = True
    assert 2 not in select(query, bank, exclude=excluded)


@pytest.mark.slow
def test_index_cache_and_leave_one_out(pipe, pairs, tmp_path, monkeypatch):
    bank = pairs.subset(range(6))
    path = tmp_path / "index.npz"
    index = build_index(pipe, bank, path, pipe.identity)
    loaded = FeatureIndex.load(path)
    assert loaded.fingerprint == index.fingerprint and list(loaded.tasks) == bank.tasks
    t0 = bank.tasks[0]
    assert list(index.positions[index.tasks == t0]) == list(range(bank.tasks.count(t0)))
    for part in index.features:
        np.testing.assert_array_equal(loaded.features[part], index.features[part])
    monkeypatch.setattr(
        "agnostos_mjx.dynamics.features.extract", lambda *a, **k: pytest.fail("cache not used")
    )
    assert build_index(pipe, bank, path, pipe.identity).fingerprint == index.fingerprint
    for mode in ("random", "lang+vis.out"):
        assert 0.0 <= leave_one_out_same_task(index, mode, k=3) <= 1.0
    monkeypatch.undo()
    chosen = DemoSelector(pipe, index, k=3)(bank.first[4], bank.instructions[4])
    assert chosen[0] == (bank.tasks[4], int(index.positions[4]))  # a demo is its own best match
    assert len(DemoSelector(None, index, mode="random", k=3)(bank.first[0], "x")) == 3
    np.savez(tmp_path / "old.npz", version=0)
    with pytest.raises(ValueError, match="version 0"):
        FeatureIndex.load(tmp_path / "old.npz")


@pytest.mark.slow
def test_evaluate_script(dyn_run, pairs, tmp_path):
    data = tmp_path / "pairs.npz"
    pairs.save(data)
    assert FramePairs.load(data).instructions == pairs.instructions
    result = eval_cli.main(
        [
            "--run",
            str(dyn_run),
            "--data",
            str(data),
            "--holdout-every",
            "4",
            "--k",
            "3",
            "--batch",
            "3",
            "--json",
            str(tmp_path / "e.json"),
        ]
    )
    assert json.loads((tmp_path / "e.json").read_text())["prediction"]["demos"] == 3
    assert set(result["selection"]["same_task_fraction"]) == set(eval_cli.MODES)


def test_cli_help_explains_every_flag():
    for cli in (ae_cli, dyn_cli, eval_cli):
        text = cli.parser().format_help()
        for action in cli.parser()._actions:
            assert action.help, f"{cli.__name__}: {action.option_strings} has no help"
        assert "--quick" in text or cli is eval_cli
    assert (
        "--unet-channels" in dyn_cli.parser().format_help()
        and "--batch-size" in ae_cli.parser().format_help()
    )


def test_frame_pairs_from_bank_records_and_split(pairs, monkeypatch):
    class Demo:  # the bank's record: frames[camera] = (first, last)
        def __init__(self, i: int):
            self.frames = {"front": (pairs.first[i], pairs.last[i])}
            self.instruction, self.task = pairs.instructions[i], pairs.tasks[i]

    assert FramePairs.from_records(Demo(i) for i in range(3)).instructions == pairs.instructions[:3]

    class DemoBank:
        def __init__(self, root):
            pass

        def frame_pairs(self, camera):
            return pairs.first, pairs.last, pairs.instructions, pairs.tasks

    monkeypatch.setitem(sys.modules, "agnostos_mjx.data", types.SimpleNamespace(DemoBank=DemoBank))
    assert FramePairs.from_bank("bank").tasks == pairs.tasks
    records = [
        {
            "first_frame": pairs.first[i],
            "last_frame": pairs.last[i],
            "instruction": pairs.instructions[i],
            "task": pairs.tasks[i],
            "variation": 0,
        }
        for i in range(5)
    ]
    fp = FramePairs.from_records(records)
    assert len(fp) == 5 and fp.tasks == pairs.tasks[:5]
    train, held = pairs.split(4)
    assert len(train) == 9 and held.instructions == [pairs.instructions[i] for i in (3, 7, 11)]


def test_sample_grid_png(pairs, tmp_path):
    from PIL import Image

    from agnostos_mjx.train.common import save_grid

    path = save_grid(tmp_path / "g.png", [pairs.first[:2], pairs.last[:2]], ["first", "last"])
    grid = np.asarray(Image.open(path).convert("RGB"))
    assert grid.shape == (2 * 130, 2 * 130, 3)
    np.testing.assert_array_equal(grid[:128, 130:258], pairs.last[0])
    (tmp_path / "file").write_text("")  # a file where the folder should be: warn, go on
    assert save_grid(tmp_path / "file" / "g.png", [pairs.first[:1]], []) is None


@pytest.mark.parametrize("prediction", ["v", "epsilon"])
@pytest.mark.parametrize("schedule", ["cosine", "scaled_linear"])
def test_ddim_with_an_oracle_denoiser_recovers_the_target(prediction, schedule):
    """A denoiser that knows x0 makes DDIM land on x0: checks the schedule, the
    v/epsilon conversions and the step rule without any training."""
    import jax.numpy as jnp

    from agnostos_mjx.dynamics.diffusion import alphas_cumprod, ddim_sample

    cfg = replace(DIFFUSION_QUICK, prediction=prediction, schedule=schedule, sample_steps=10)
    ab_all = jnp.asarray(alphas_cumprod(cfg))
    x0 = jnp.asarray(np.random.default_rng(0).normal(size=(2, 16, 16, 4)), jnp.float32)

    def unet(x, cond, t, ctx, mask, pooled):
        target = jnp.concatenate([x0] * 3)  # the three guidance branches agree
        ab = ab_all[t][:, None, None, None]
        eps = (x - jnp.sqrt(ab) * target) / jnp.sqrt(1 - ab)
        return eps if prediction == "epsilon" else jnp.sqrt(ab) * eps - jnp.sqrt(1 - ab) * target

    oracle = types.SimpleNamespace(
        text=lambda ids, mask: (
            jnp.zeros((len(ids), ids.shape[1], 8)),
            jnp.zeros((len(ids), 1024)),
        ),
        unet=unet,
    )
    ids, mask = tokenize(["a", "b"], 8)
    noise = jax.random.normal(jax.random.key(0), x0.shape)
    out = ddim_sample(oracle, cfg, jnp.zeros_like(x0), jnp.asarray(ids), jnp.asarray(mask), noise)
    np.testing.assert_allclose(out, x0, atol=1e-3)


def test_map_chunks_runs_one_shape():
    from agnostos_mjx.dynamics.batching import map_chunks

    shapes: set[int] = set()

    def fn(x):
        shapes.add(x.shape[0])
        return x * 2

    for n in (1, 3, 8, 19):
        out = map_chunks(fn, np.arange(n, dtype=np.float32), size=8)
        np.testing.assert_array_equal(out, 2 * np.arange(n, dtype=np.float32))
    assert shapes == {8}


def test_row_batcher_shares_calls_between_requests_and_returns_each_its_rows():
    import threading

    from agnostos_mjx.infra.gather import RowBatcher, allow_gathering, flush, send_alone, then

    gate, calls = threading.Event(), []

    def fn(items):
        gate.wait(10)  # hold the first call until every request is queued
        calls.append(list(items))
        if "bad" in items:
            raise ValueError("bad row")
        return [f"{x}!" for x in items]

    batcher = RowBatcher(fn, size=4, workers=2)
    first = batcher.submit(["a"])
    rest = [batcher.submit(["b", "c"]), batcher.submit(["d", "e", "f"]), batcher.submit([])]
    gate.set()
    assert first.result(10) == ["a!"]
    assert [f.result(10) for f in rest] == [["b!", "c!"], ["d!", "e!", "f!"], []]
    assert sorted(x for call in calls for x in call) == list("abcdef")
    assert all(len(call) <= 4 for call in calls) and len(calls) < 4  # rounds shared calls
    with pytest.raises(ValueError, match="bad row"):
        batcher.submit(["g", "bad"]).result(10)
    assert batcher.submit(["h"]).result(10) == ["h!"]  # a failed call stops no worker
    # Gathering (a GPU): nothing runs until flush, then the requests go out in key order,
    # whatever order they came in, and share calls.
    calls.clear()
    held = RowBatcher(fn, size=4, gather=True)
    late, early = held.submit(list("xyz"), key=2), held.submit(list("ab"), key=1)
    with pytest.raises(ValueError, match="needs a key"):
        held.submit(["k"])
    assert not late.done() and not early.done() and calls == []
    flush(late)
    assert late.result(10) == ["x!", "y!", "z!"] and early.result(10) == ["a!", "b!"]
    assert calls == [["a", "b", "x", "y"], ["z"]]
    flush(late)  # a finished request: nothing to send
    assert calls == [["a", "b", "x", "y"], ["z"]]
    # A caller that waits on nothing else sends its request alone; the others stay held.
    calls.clear()
    mine, theirs = held.submit(["m", "n"], key=5), held.submit(["t"], key=0)
    send_alone(mine)
    assert mine.result(10) == ["m!", "n!"] and calls == [["m", "n"]] and not theirs.done()
    flush(theirs)
    assert theirs.result(10) == ["t!"] and calls == [["m", "n"], ["t"]]
    # A request cancelled while held (Ctrl-C) is dropped; the worker serves the next ones.
    calls.clear()
    cancelled, kept = held.submit(["p"], key=0), then(held.submit(["q"], key=1), list)
    assert cancelled.cancel()
    flush(kept)
    assert kept.result(10) == ["q!"] and calls == [["p", "q"]]
    waited = then(held.submit(["r"], key=0), list)  # what a task yields, cancelled
    assert waited.cancel()
    flush(waited)  # its rows still run; nobody gets them
    alive = held.submit(["s"], key=0)
    flush(alive)
    assert alive.result(10) == ["s!"]
    # Where gathering is not allowed (processes fed by a task queue), each request goes
    # alone at once, in calls of its own rows from the first place.
    calls.clear()
    allow_gathering(False)
    try:
        futures = [held.submit(list("abcde"), key=1), held.submit(["x"], key=0)]
        assert [f.result(10) for f in futures] == [[f"{c}!" for c in "abcde"], ["x!"]]
    finally:
        allow_gathering(True)
    assert calls == [list("abcd"), ["e"], ["x"]]


def test_tasks_waiting_on_gathered_rows_are_released_together_in_key_order():
    import concurrent.futures
    import time

    from agnostos_mjx.evaluation import scheduler
    from agnostos_mjx.infra.gather import RowBatcher, then
    from agnostos_mjx.policies.base import run_blocking

    calls = []

    def fn(items):
        calls.append(list(items))
        return [f"{x}!" for x in items]

    batcher = RowBatcher(fn, size=8, gather=True)
    physics: concurrent.futures.Future = concurrent.futures.Future()

    def task(name, key, before=None):
        if before is not None:  # another wait first (physics): the rows must wait for it
            yield before
        rows = then(batcher.submit([f"{name}1", f"{name}2"], key=key), list)  # as selectors
        yield rows
        return rows.result()

    jobs = [task("b", 2), task("a", 1, before=physics), task("c", 3)]
    pool = concurrent.futures.ThreadPoolExecutor(1)
    pool.submit(lambda: (time.sleep(0.2), physics.set_result(None)))
    values = scheduler.run_interleaved(jobs, limit=3)
    assert values == [["b1!", "b2!"], ["a1!", "a2!"], ["c1!", "c2!"]]
    # One call, sent after the physics ended, in key order (a, b, c), not arrival order.
    assert calls == [["a1", "a2", "b1", "b2", "c1", "c2"]]
    calls.clear()
    assert run_blocking(task("d", 4)) == ["d1!", "d2!"] and calls == [["d1", "d2"]]


@pytest.mark.slow  # a benchmark's smoke test: its compiles
def test_dynamics_benchmark_quick_mode(tmp_path):
    from agnostos_mjx.bench import dynamics as bench

    assert bench.main(["--quick", "--out", str(tmp_path / "b.json")]) == 0
    result = json.loads((tmp_path / "b.json").read_text())
    assert result["training"]["steps_per_s"] > 0
    assert [r["batch"] for r in result["features"]] == [1, 4]
    assert all(r["queries_per_s"] > 0 for r in result["features"])



# ---- issue 13: the CPU-specialised layers compute what flax's layers computed ----


def _randomized(module: nnx.Module, seed: int) -> nnx.Module:
    """`module` with every float parameter perturbed: the untrained presets zero-initialise
    the last convolutions and projections, so their features would hide a difference."""
    graphdef, state = nnx.split(module)
    leaves, tree = jax.tree.flatten(state)
    keys = jax.random.split(jax.random.key(seed), len(leaves))
    leaves = [x + 0.3 * jax.random.normal(k, x.shape, x.dtype)
              if jax.numpy.issubdtype(x.dtype, jax.numpy.floating) else x
              for k, x in zip(keys, leaves)]
    return nnx.merge(graphdef, jax.tree.unflatten(tree, leaves))


def _assert_stock(module: nnx.Module) -> None:
    """The reference really runs flax's own layers (else the comparison proves nothing)."""
    kinds = {type(m) for _, m in nnx.iter_modules(module)}
    assert nnx.GroupNorm in kinds and not any(k is not nnx.GroupNorm
                                              and issubclass(k, nnx.GroupNorm) for k in kinds)
    for _, m in nnx.iter_modules(module):
        if isinstance(m, nnx.MultiHeadAttention):
            assert m.attention_fn is nnx.dot_product_attention


@pytest.mark.slow
def test_cpu_layers_give_flax_layers_features():
    """GroupNorm and attention specialised for the CPU (layers.py) against flax's own, on a
    quick-preset model with random weights: the same features up to float round-off."""
    from agnostos_mjx.bench.dynamics import quick_pipeline, reference_pipeline

    pipe = quick_pipeline()
    pipe = replace(pipe, ae=_randomized(pipe.ae, 1), model=_randomized(pipe.model, 2), chunk=4)
    ref = reference_pipeline(pipe)
    _assert_stock(ref.model)
    _assert_stock(ref.ae)
    assert not any(type(m) is nnx.GroupNorm for _, m in nnx.iter_modules(pipe.model))
    rng = np.random.default_rng(0)
    first = rng.integers(0, 255, (6, 128, 128, 3), dtype=np.uint8)
    words = ["turn on the lamp", "open the grill", "", "push the red button", "x", "open it"]
    new, old = extract(pipe, first, words), extract(ref, first, words)
    for part in ("vis.in", "vis.out", "lang"):
        norm = np.linalg.norm(old[part], axis=1)
        assert norm.min() > 1.0, part  # features that could show a difference
        rel = np.abs(new[part] - old[part]).max(axis=1) / norm
        assert rel.max() < 1e-5, (part, rel.max())


@pytest.mark.slow
def test_cpu_group_norm_and_attention_match_flax():
    from agnostos_mjx.dynamics.layers import GroupNorm, dot_product_attention

    rng = np.random.default_rng(1)
    for shape, groups in (((3, 8, 8, 64), 32), ((2, 16, 16, 12), 4), ((2, 5, 48), 8)):
        norm = _randomized(GroupNorm(shape[-1], num_groups=groups, rngs=nnx.Rngs(0)), 3)
        stock = nnx.GroupNorm(shape[-1], num_groups=groups, rngs=nnx.Rngs(0))
        nnx.update(stock, nnx.state(norm))
        x = jax.numpy.asarray(rng.normal(2.0, 3.0, shape).astype(np.float32))
        np.testing.assert_allclose(norm(x), stock(x), atol=2e-5, rtol=1e-5)
        mask = jax.numpy.asarray(rng.random(shape) > 0.3)  # the general path: flax's
        np.testing.assert_array_equal(norm(x, mask=mask), stock(x, mask=mask))
    q = jax.numpy.asarray(rng.normal(size=(3, 40, 4, 16)).astype(np.float32))
    k = jax.numpy.asarray(rng.normal(size=(3, 24, 4, 16)).astype(np.float32))
    v = jax.numpy.asarray(rng.normal(size=(3, 24, 4, 16)).astype(np.float32))
    mask = jax.numpy.asarray(np.arange(24)[None, :] < np.array([[1], [7], [24]]))[:, None, None]
    for m in (None, mask):
        np.testing.assert_allclose(dot_product_attention(q, k, v, mask=m),
                                   nnx.dot_product_attention(q, k, v, mask=m),
                                   atol=1e-5, rtol=1e-5)


def _first_frames(tasks: tuple[str, ...], n: int) -> tuple[np.ndarray, list[str]]:
    """The evaluation's first queries: n scenes of each task (seed 0, variation 0) rendered
    by the front camera, with the task's instruction."""
    from agnostos_mjx.evaluation.protocol import episode_keys
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    frames, words = [], []
    for name in tasks:
        runner = Episodes(get_task(name), "native")
        env = runner.reset(episode_keys(np.zeros(n), np.arange(n)), np.zeros(n, np.int32))
        frames.append(runner.render(env, "front", 128, 128))
        words += [runner.task.descriptions(0)[0]] * n
    return np.concatenate(frames), words


@pytest.mark.slow  # the shipped model, old and new, on 32 scenes
def test_shipped_query_features_and_top18_unchanged_by_cpu_work():
    """Issue 13's gate: the query features of the shipped model (the evaluation's 10 DDIM
    steps) of 32 scenes of two unseen tasks, computed as before the CPU work (flax's layers,
    chunks of 64) and as now, agree to 1e-4 of their norm, and select the same top-18."""
    from agnostos_mjx.bench.dynamics import reference_pipeline
    from agnostos_mjx.xicm.dynamics_selector import QUERY_SAMPLE_STEPS, load_pipeline
    from agnostos_mjx.xicm.memory import DemoMemory, default_memory_path

    frames, words = _first_frames(("lamp_on", "open_grill"), 16)
    pipe = load_pipeline(None, QUERY_SAMPLE_STEPS)
    ref = reference_pipeline(pipe)
    _assert_stock(ref.model)
    new, old = extract(pipe, frames, words), extract(ref, frames, words)
    for part in ("vis.in", "vis.out", "lang"):
        rel = np.abs(new[part] - old[part]).max(axis=1) / np.linalg.norm(old[part], axis=1)
        assert rel.max() < 1e-4, (part, rel.max())
    bank = DemoMemory.load(default_memory_path()).features
    sims = [similarity(f, bank, "lang+vis.out") for f in (new, old)]
    top = [np.argsort(-s, axis=1, kind="stable")[:, :18] for s in sims]
    # The same demos in the same order, but for exact near-ties (neighbouring ranks of these
    # queries lie as little as 1e-6 apart, the size of the round-off): where the lists
    # differ, each rank's two demos must be equally similar under the old features.
    rows = np.arange(len(words))[:, None]
    assert np.abs(sims[1][rows, top[0]] - sims[1][rows, top[1]]).max() < 1e-5
    assert (top[0] == top[1]).mean() > 0.99


def test_a_pipeline_serves_several_threads_at_once():
    """The selection's workers call one pipeline from two threads: every call gives what
    it gives alone (nnx.jit, which updates the module on each call, failed here)."""
    from concurrent.futures import ThreadPoolExecutor

    from agnostos_mjx.xicm.dynamics_selector import load_pipeline

    pipe = load_pipeline()  # the shipped model: test_xicm compiles the same text program
    texts = ["press the button", "open the drawer"]
    alone = pipe.lang(texts)
    with ThreadPoolExecutor(4) as pool:
        outs = list(pool.map(lambda _: pipe.lang(texts), range(16)))
    for out in outs:
        np.testing.assert_array_equal(out, alone)


@pytest.mark.slow  # compiles the quick model's UNet and sampler
def test_flops_reports_the_work_per_query_and_the_floor_of_n_queries(tmp_path, capsys):
    import json

    from agnostos_mjx.bench import query_flops as flops

    assert flops.main(["--quick", "--queries", "100", "--repeats", "1",
                       "--out", str(tmp_path / "f.json")]) == 0
    r = json.loads((tmp_path / "f.json").read_text())
    assert r["gflop_per_query"] > 0 and r["ddim_steps"] == 8 and r["queries"] == 100
    assert r["gflops_1_threads"] > 0 and r["matmul_gflops"] > 0
    out = capsys.readouterr().out
    assert "GFLOP per query" in out and "100 queries" in out
