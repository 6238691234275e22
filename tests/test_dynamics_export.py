"""The compact shipping format of the dynamics model (quick preset, CPU): an export
gives the features of the run it came from, is small, holds no decoder, fails
clearly when damaged; the default preset's export fits the package's budget."""

from __future__ import annotations

import json
import shutil
import types

import jax
import numpy as np
import pytest
from flax import nnx

from agnostos_mjx.dynamics import export_format
from agnostos_mjx.dynamics.autoencoder import Autoencoder
from agnostos_mjx.dynamics.checkpoint import CheckpointError, Checkpoints
from agnostos_mjx.dynamics.config import (
    AE_QUICK,
    DIFFUSION_QUICK,
    PRESETS,
    TEXT_QUICK,
    UNET_QUICK,
)
from agnostos_mjx.dynamics.data import FramePairs, synthetic
from agnostos_mjx.dynamics.diffusion import DynamicsModel
from agnostos_mjx.dynamics.export_format import (
    META_FILE,
    PARAMS_FILE,
    feature_modules,
    parameter_count,
    size_bound,
)
from agnostos_mjx.dynamics.features import extract
from agnostos_mjx.dynamics.layers import create
from agnostos_mjx.dynamics.pipeline import Pipeline, autoencoder_meta, dynamics_meta
from agnostos_mjx.train import autoencoder as ae_cli
from agnostos_mjx.train import dynamics as dyn_cli
from agnostos_mjx.train import evaluate as eval_cli
from agnostos_mjx.train import export as export_cli
from agnostos_mjx.train.common import preset
from agnostos_mjx.xicm.dynamics_selector import bank_features

SHIP_BUDGET = 30e6  # bytes of params.npz the package may ship for the model


@pytest.fixture(scope="module")
def pairs() -> FramePairs:
    return synthetic(8, seed=1)


def _randomised(model: nnx.Module, seed: int) -> nnx.State:
    """Its parameters plus noise: every weight matters, the zero-initialised ones too
    (cheaper than training, which would move them only a little)."""
    rng = np.random.default_rng(seed)
    return jax.tree.map(lambda x: x + 0.02 * rng.normal(size=x.shape), nnx.state(model))


@pytest.fixture(scope="module")
def dyn_run(tmp_path_factory):
    """An autoencoder run and a dynamics run as training writes them (checkpoint at step 2)."""
    ae_dir, out = tmp_path_factory.mktemp("ae"), tmp_path_factory.mktemp("dyn")
    ae = create(lambda: Autoencoder(AE_QUICK, rngs=nnx.Rngs(0)))
    Checkpoints(ae_dir / "checkpoints").save(
        2, {"params": _randomised(ae, 0)}, autoencoder_meta(AE_QUICK)
    )
    model = create(lambda: DynamicsModel(TEXT_QUICK, UNET_QUICK, rngs=nnx.Rngs(0)))
    meta = dynamics_meta(TEXT_QUICK, UNET_QUICK, DIFFUSION_QUICK, AE_QUICK)
    meta.update(latent_scale=0.7, autoencoder_dir=str(ae_dir))
    Checkpoints(out / "checkpoints").save(2, {"params": _randomised(model, 1)}, meta)
    return out


@pytest.fixture(scope="module")
def exported(tmp_path_factory, dyn_run):
    out = tmp_path_factory.mktemp("export") / "dynamics"
    export_cli.main(["--run", str(dyn_run), "--out", str(out)])
    return out


def test_the_model_structure_is_traced_once_then_read_from_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("AGNOSTOS_CACHE", str(tmp_path))
    traced = feature_modules(AE_QUICK, TEXT_QUICK, UNET_QUICK)
    (kept,) = (tmp_path / "model_structure").glob("*.pkl")

    def no_trace(build):
        raise AssertionError("traced the constructor again")

    with monkeypatch.context() as m:
        m.setattr(export_format, "abstract", no_trace)
        read = feature_modules(AE_QUICK, TEXT_QUICK, UNET_QUICK)
    for name in ("ae", "dynamics"):
        (g1, s1), (g2, s2) = nnx.split(traced[name]), nnx.split(read[name])
        assert g1 == g2
        assert jax.tree.map(lambda x: (x.shape, x.dtype), s1) == jax.tree.map(
            lambda x: (x.shape, x.dtype), s2)
    kept.write_bytes(b"half a file")  # damaged: traced again and rewritten
    again = feature_modules(AE_QUICK, TEXT_QUICK, UNET_QUICK)
    assert nnx.split(again["dynamics"])[0] == nnx.split(traced["dynamics"])[0]
    assert kept.read_bytes() != b"half a file"


@pytest.mark.slow
def test_round_trip_gives_the_runs_features(dyn_run, exported, pairs):
    run, exp = Pipeline.load(dyn_run), Pipeline.load(exported)
    assert exp.diffusion == run.diffusion and exp.text == run.text
    assert exp.latent_scale == run.latent_scale and exp.identity != run.identity
    first, instr = pairs.first[:3], pairs.instructions[:3]
    a, b = extract(run, first, instr), extract(exp, first, instr)
    for part in a:
        assert b[part].dtype == np.float32 and b[part].shape == (3, 1024)
        # float16 weights: ~3 significant digits, relative to the feature's scale.
        scale = np.abs(a[part]).max()
        np.testing.assert_allclose(b[part], a[part], rtol=0, atol=2e-3 * scale, err_msg=part)
        cos = np.sum(a[part] * b[part], 1) / np.linalg.norm(a[part], axis=1)
        assert np.all(cos / np.linalg.norm(b[part], axis=1) > 0.9999), part
    # What build_memory --checkpoint and DynamicsSelector call, given the export directory.
    bank = types.SimpleNamespace(frame_pairs=lambda camera: (first, None, instr, None))
    for part, value in bank_features(bank, exported).items():
        np.testing.assert_array_equal(value, b[part])


@pytest.mark.slow
def test_export_is_small_float16_and_has_no_decoder(dyn_run, exported):
    assert sorted(p.name for p in exported.iterdir()) == [META_FILE, PARAMS_FILE]  # no temp files
    meta = json.loads((exported / META_FILE).read_text())
    assert meta["version"] == 1 and meta["source"]["step"] == 2
    assert meta["diffusion"]["sample_steps"] == DIFFUSION_QUICK.sample_steps
    with np.load(exported / PARAMS_FILE) as z:
        arrays = {k: z[k] for k in z.files}
    assert not [k for k in arrays if "decoder" in k]
    assert {k.split(".")[0] + "." + k.split(".")[1] for k in arrays} == {
        "ae.encoder",
        "dynamics.text",
        "dynamics.unet",
    }
    assert {v.dtype for v in arrays.values()} == {np.dtype(np.float16)}
    n = sum(v.size for v in arrays.values())
    assert n == meta["parameters"] == parameter_count(AE_QUICK, TEXT_QUICK, UNET_QUICK)
    size = (exported / PARAMS_FILE).stat().st_size
    assert size <= size_bound(AE_QUICK, TEXT_QUICK, UNET_QUICK)
    run = Pipeline.load(dyn_run)
    float32_bytes = 4 * sum(
        np.size(x) for m in (run.ae, run.model) for x in jax.tree.leaves(nnx.state(m))
    )
    assert size < 0.5 * float32_bytes  # half the bytes per weight, and no decoder


@pytest.mark.slow
def test_damaged_export_is_a_clear_error(exported, tmp_path):
    def copy(name: str):
        d = tmp_path / name
        shutil.copytree(exported, d)
        return d

    d = copy("truncated")
    data = (d / PARAMS_FILE).read_bytes()
    (d / PARAMS_FILE).write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=f"{d / PARAMS_FILE} is corrupt"):
        Pipeline.load(d)

    d = copy("no_json")
    (d / META_FILE).unlink()
    with pytest.raises(CheckpointError, match=f"export {d} is incomplete: no {META_FILE}"):
        Pipeline.load(d)

    d = copy("bad_json")
    (d / META_FILE).write_text('{"format": ')
    with pytest.raises(CheckpointError, match=f"export {d / META_FILE} is corrupt"):
        Pipeline.load(d)

    d = copy("new_version")
    meta = json.loads((d / META_FILE).read_text())
    (d / META_FILE).write_text(json.dumps({**meta, "version": 99}))
    with pytest.raises(CheckpointError, match=f"export {d} has format version 99"):
        Pipeline.load(d)

    d = copy("other_config")  # configs that do not fit the arrays: the parameter is named
    meta["model"]["unet"]["channels"] = [16, 48]
    (d / META_FILE).write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match=r"(?s)params\.npz does not fit.*unet.*shape"):
        Pipeline.load(d)

    with pytest.raises(CheckpointError, match=f"no dynamics model at {tmp_path / 'nowhere'}"):
        Pipeline.load(tmp_path / "nowhere")
    with pytest.raises(CheckpointError, match="is an export"):
        Pipeline.load(exported, ae_run=tmp_path)
    with pytest.raises(SystemExit, match="give --json"):
        eval_cli.main(["--run", str(exported), "--synthetic", "4"])


@pytest.mark.slow  # tracing the large preset's shapes
def test_default_preset_export_fits_the_budget():
    """From shapes only (the large preset, 48.6 M parameters, would be ~97 MB)."""
    ship = PRESETS["default"]
    assert ship.unet.channels == (64, 128, 128) and ship.text.width == 192
    assert ship.ae == PRESETS["large"].ae  # only its encoder is shipped
    large = PRESETS["large"]
    assert parameter_count(large.ae, large.text, large.unet) > 40e6
    n = parameter_count(ship.ae, ship.text, ship.unet)
    assert 14e6 < n < 15e6  # float16: 2 bytes each
    assert 2 * n < size_bound(ship.ae, ship.text, ship.unet) <= SHIP_BUDGET


def test_preset_flag_on_the_training_entry_points():
    args = ["--out", "x", "--synthetic", "4", "--preset", "large"]
    assert preset(ae_cli.parser().parse_args(args)).ae == PRESETS["large"].ae
    dyn = dyn_cli.parser().parse_args([*args, "--ae", "a"])
    assert preset(dyn) == PRESETS["large"] and preset(dyn).unet.channels == (128, 256, 256)
    plain = dyn_cli.parser().parse_args(["--out", "x", "--ae", "a"])
    assert preset(plain) == PRESETS["default"] and preset(plain).dyn_train.steps == 7_000
    quick = dyn_cli.parser().parse_args(["--out", "x", "--ae", "a", "--quick"])
    assert preset(quick) == PRESETS["quick"]
    with pytest.raises(SystemExit, match="contradict"):
        preset(dyn_cli.parser().parse_args([*args, "--ae", "a", "--quick"]))
