"""The reference VLA (issue 28): virtual views, the training CLI's smoke mode, the
checkpoint, the ``reference-vla`` policy in the evaluator, and its usage errors."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from agnostos_mjx.vla.views import (
    VIEWS,
    decode_position,
    normalise,
    render_views,
    target_heatmaps,
)


@pytest.mark.slow
def test_heatmaps_decode_to_their_target():
    """Log target heatmaps decode back to the target within a fraction of a view pixel,
    and a point in the scene shows up in every view at the target's pixel."""
    pos = jnp.array([[0.25, 0.1, 0.9], [-0.2, -0.4, 1.5], [0.61, 0.33, 0.75]], jnp.float32)
    size = 32
    maps = target_heatmaps(pos, size)
    out = decode_position(jnp.log(maps + 1e-9))
    assert np.abs(np.asarray(out) - np.asarray(pos)).max() < 1e-3  # metres
    # One coloured point at pos[0], nothing else; the gripper at the same place.
    views = np.asarray(render_views(pos[:1, None], jnp.full((1, 1, 3), 255, jnp.uint8),
                                    pos[:1], size))
    assert views.shape == (1, len(VIEWS), size, size, 9)
    occupancy, blob = views[0, ..., 4], views[0, ..., 8]
    assert (occupancy.sum((1, 2)) == 1).all()
    for v in range(len(VIEWS)):
        hit = np.unravel_index(occupancy[v].argmax(), occupancy[v].shape)
        assert hit == np.unravel_index(blob[v].argmax(), blob[v].shape)
        np.testing.assert_allclose(views[0, v][hit][5:8], normalise(np.asarray(pos[0])),
                                   atol=1e-6)
    # Points outside the cube are not drawn.
    far = render_views(jnp.array([[[5.0, 0.0, 1.0]]]), jnp.zeros((1, 1, 3), jnp.uint8),
                       pos[:1], size)
    assert float(far[..., 4].sum()) == 0.0


@pytest.mark.slow
def test_quick_train_reload_evaluate(tmp_path, capsys, monkeypatch):
    """The smoke path: a tiny model trained for a few steps on 2 tasks (data generated on
    the fly), saved, reloaded as the policy (from the run and from its float16 export) and
    evaluated on 2 episodes; rerunning the training command resumes instead of starting
    over."""
    from agnostos_mjx.dynamics.text import tokenize
    from agnostos_mjx.eval import main as eval_main
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.train import vla

    run = tmp_path / "run"
    argv = ["--quick", "--tasks", "turn_tap,push_buttons", "--demos", "2", "--out", str(run),
            "--no-progress", "--steps", "20"]
    assert vla.main(argv) == 0
    losses = [json.loads(line)["loss"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert len(losses) == 4 and losses[-1] < losses[0]
    held = json.loads((run / "heldout.jsonl").read_text().splitlines()[-1])
    assert held["step"] == 20 and held["samples"] > 0 and 0 <= held["gripper"] <= 1
    assert vla.main(["--out", str(run), "--curve"]) == 0
    assert "| 20 |" in capsys.readouterr().out
    assert vla.main(argv) == 0  # resumes at step 20: nothing more to do
    assert len((run / "log.jsonl").read_text().splitlines()) == 4

    # The float16 export loads as the run does and predicts the same actions.
    exported = tmp_path / "export"
    assert vla.main(["--out", str(run), "--export", str(exported)]) == 0
    policies = [make_policy("reference-vla", checkpoint=str(p)) for p in (run, exported)]
    for policy in policies:
        assert policy.observation_spec.cameras == ("front", "overhead")
        assert policy.observation_spec.height == 32
        assert policy.max_steps == policy.meta["max_key_actions"] <= 6  # the longest demo
    rng = np.random.default_rng(0)
    args = (rng.uniform([-0.3, -0.5, 0.7], [0.7, 0.5, 1.2], (2, 64, 3)).astype(np.float32),
            rng.integers(0, 255, (2, 64, 3)).astype(np.uint8),
            np.array([[0.2, 0.0, 1.1], [0.3, 0.1, 1.0]], np.float32),
            *tokenize(["push the button", "turn tap"], policies[0].cfg.text_len),
            np.ones(2, np.float32), np.zeros(2, np.int32))
    (pos_a, rot_a, grip_a), (pos_b, rot_b, grip_b) = (
        p._forward(p._params, *args) for p in policies)
    np.testing.assert_allclose(pos_a, pos_b, atol=0.01)
    assert (np.asarray(grip_a) == np.asarray(grip_b)).all()
    # Chunks (3 worlds in chunks of 2: the last one padded) predict what one pass does.
    three = [np.concatenate([a, a[:1]]) for a in args]
    whole = policies[0]._predict(*three)
    chunked = make_policy("reference-vla", checkpoint=str(run), chunk=2)._predict(*three)
    assert [len(x) for x in chunked] == [3, 3, 3]
    np.testing.assert_allclose(chunked[0], whole[0], atol=1e-5)
    np.testing.assert_array_equal(chunked[1], whole[1])
    np.testing.assert_array_equal(chunked[2], whole[2])

    # The warm-up (agnostos_mjx.warmup) runs the network on what `act` gives it: the same
    # shapes and dtypes, so the program it leaves in JAX's cache is the run's.
    from agnostos_mjx.policies.base import warm_up_policy
    from agnostos_mjx.policies.reference_vla import ReferenceVLAPolicy

    inputs = []
    predict = ReferenceVLAPolicy._predict
    monkeypatch.setattr(ReferenceVLAPolicy, "_predict", lambda self, *xs: (
        inputs.append([(x.shape, x.dtype) for x in xs]), predict(self, *xs))[1])
    assert warm_up_policy("reference-vla", 2, checkpoint=str(run))
    out = tmp_path / "eval"
    rc = eval_main(["--policy", "reference-vla", "--policy-arg", f"checkpoint={run}",
                    "--tasks", "turn_tap", "--episodes", "2", "--seeds", "0",
                    "--backend", "native", "--out", str(out), "--quiet"])
    assert rc == 0
    rows = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and {r["policy"] for r in rows} == {"reference-vla"}
    assert all(r["key_actions"] <= policies[0].max_steps for r in rows)
    assert len(inputs) > 1 and all(step == inputs[0] for step in inputs[1:])


def test_usage_errors(tmp_path, capsys):
    """Bad input gives a message, not a traceback."""
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.train import vla, vla_data

    with pytest.raises(ValueError, match="checkpoint=RUN"):
        make_policy("reference-vla")
    with pytest.raises(SystemExit):
        vla.parser().parse_args(["--out", "r", "--matmul-precision", "float8"])
    with pytest.raises(ValueError, match="no checkpoint"):
        make_policy("reference-vla", checkpoint=str(tmp_path / "missing"))
    assert vla.main(["--out", str(tmp_path / "missing"), "--export", str(tmp_path / "x")]) == 2
    with pytest.raises(SystemExit) as e:
        vla.main(["--out", str(tmp_path / "r")])  # neither --data nor --quick
    assert e.value.code == 2
    with pytest.raises(SystemExit):
        vla.main(["--out", str(tmp_path / "r"), "--data", str(tmp_path / "none")])
    with pytest.raises(SystemExit):
        vla_data.main(["--out", str(tmp_path / "d"), "--cameras", "front,nose"])
    other = tmp_path / "other"  # data made with other settings is not mixed in
    other.mkdir()
    (other / "manifest.json").write_text(json.dumps({"settings": {"size": 128}}))
    assert vla_data.main(["--out", str(other), "--tasks", "turn_tap", "--demos", "1"]) == 2
    assert "holds data made with" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert vla.main(["--out", str(tmp_path / "r"), "--data", str(empty)]) == 2
    assert "no keyframe chunks" in capsys.readouterr().err


def test_data_worker_holds_one_runner_at_a_time():
    """A data worker that moves to another task closes the old runner first (one GL context
    per process: NVIDIA's EGL refused a second one on a GPU host)."""
    from agnostos_mjx.train import vla_data

    vla_data._RUNNER.clear()
    first = vla_data._episodes("turn_tap", 1)
    assert vla_data._episodes("turn_tap", 1) is first
    closed = []
    first.close = lambda: closed.append(True)
    second = vla_data._episodes("push_buttons", 1)
    assert closed == [True] and second is not first
    assert list(vla_data._RUNNER) == [("push_buttons", 1)]
    vla_data._RUNNER.clear()
    second.close()
