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


def test_quick_train_reload_evaluate(tmp_path):
    """The smoke path: a tiny model trained for a few steps on 2 tasks (data generated on
    the fly), saved, reloaded as the policy and evaluated on 2 episodes; rerunning the
    training command resumes instead of starting over."""
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
    assert vla.main(argv) == 0  # resumes at step 20: nothing more to do
    assert len((run / "log.jsonl").read_text().splitlines()) == 4

    policy = make_policy("reference-vla", checkpoint=str(run))
    assert policy.observation_spec.cameras == ("front", "overhead")
    assert policy.observation_spec.height == 32

    out = tmp_path / "eval"
    rc = eval_main(["--policy", "reference-vla", "--policy-arg", f"checkpoint={run}",
                    "--tasks", "turn_tap", "--episodes", "2", "--seeds", "0",
                    "--backend", "native", "--out", str(out), "--quiet"])
    assert rc == 0
    rows = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and {r["policy"] for r in rows} == {"reference-vla"}


def test_usage_errors(tmp_path, capsys):
    """Bad input gives a message, not a traceback."""
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.train import vla, vla_data

    with pytest.raises(ValueError, match="checkpoint=RUN"):
        make_policy("reference-vla")
    with pytest.raises(ValueError, match="no checkpoint"):
        make_policy("reference-vla", checkpoint=str(tmp_path / "missing"))
    with pytest.raises(SystemExit) as e:
        vla.main(["--out", str(tmp_path / "r")])  # neither --data nor --quick
    assert e.value.code == 2
    with pytest.raises(SystemExit):
        vla.main(["--out", str(tmp_path / "r"), "--data", str(tmp_path / "none")])
    with pytest.raises(SystemExit):
        vla_data.main(["--out", str(tmp_path / "d"), "--cameras", "front,nose"])
    empty = tmp_path / "empty"
    empty.mkdir()
    assert vla.main(["--out", str(tmp_path / "r"), "--data", str(empty)]) == 2
    assert "no keyframe chunks" in capsys.readouterr().err
