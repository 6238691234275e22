"""The notebooks' code runs as written (in-process, top to bottom, Agg backend) and their
results are what the notebooks' text claims.  demo_bank and dynamics_selection run with
AGNOSTOS_NOTEBOOK_SMALL=1, their own small-settings switch (the code is the same)."""

from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path

import matplotlib
import numpy as np
import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOK = NOTEBOOKS / "evaluate.ipynb"


def run_notebook(path: Path, monkeypatch, **env: str) -> dict:
    """Execute every code cell of `path` in one namespace, from the notebook's directory
    with `env` set; returns the namespace."""
    matplotlib.use("Agg")
    monkeypatch.chdir(path.parent)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    namespace: dict = {}
    for cell in json.loads(path.read_text())["cells"]:
        if cell["cell_type"] == "code":
            source = "".join(cell["source"]) if isinstance(cell["source"], list) else cell["source"]
            exec(compile(source, f"{path.name} cell", "exec"), namespace)
    import matplotlib.pyplot as plt

    plt.close("all")
    return namespace


@pytest.mark.slow
def test_evaluate_notebook_runs(monkeypatch):
    namespace = run_notebook(NOTEBOOK, monkeypatch)
    assert len(namespace["tasks"]) == 23
    assert namespace["results"]["complete"]
    summary = namespace["mine"]["summary"]["tasks"]
    assert summary["lamp_on"]["success_mean"] == summary["lamp_off"]["success_mean"] == 100.0
    plan = namespace["plan"]
    assert plan["response"].startswith("Sure!") and len(plan["parsed"]["actions"]) == 2
    assert namespace["xicm"]["policy"]["name"].startswith("xicm")


# One demo in X-ICM's text: instruction and object voxels, then 7 integers per keyframe.
DEMO_TEXT = re.compile(r"^\['instruction': [^,]+.*\]>\[(\[\d+(, \d+){6}\](, )?)+\], $")


@pytest.mark.slow
def test_demo_bank_notebook_runs(monkeypatch, tmp_path, capsys):
    """Generates 2 seen tasks x 1 demo; first/last frames, X-ICM text and keyframes."""
    from agnostos_mjx.tasks import list_tasks

    ns = run_notebook(NOTEBOOKS / "demo_bank.ipynb", monkeypatch,
                      AGNOSTOS_NOTEBOOK_SMALL="1", AGNOSTOS_NOTEBOOK_BANK=str(tmp_path / "bank"))
    bank = ns["bank"]
    assert ns["BANK"] == tmp_path / "bank"
    assert list(bank.tasks) == list_tasks("seen")[:2] and len(bank) == 2
    out = capsys.readouterr().out
    assert out.startswith(f"2 demos of {', '.join(bank.tasks)}")
    for task in bank.tasks:
        demo = bank.demo(task, 0)
        # "the scene at reset and at the end of the expert's demonstration (128 x 128)"
        first, last = demo.frames["front"]
        assert first.shape == last.shape == (128, 128, 3) and first.dtype == np.uint8
        assert np.abs(first.astype(int) - last).max() > 50  # the expert changed the scene
        # "instruction and object voxels at the first frame, then the keyframes as 7 integers"
        text = demo.text()
        assert DEMO_TEXT.match(text), text
        assert demo.instruction in text and text in out
        assert text.count("], [") + 1 == len(demo.key_ints) >= 2
    # "The recorded tip height over a demo (20 Hz) with its keyframes marked"
    demo, z = ns["demo"], ns["z"]
    assert demo.task == bank.tasks[0] and len(z) == len(demo.trajectory) > 20
    assert np.all(np.diff(demo.keyframes) > 0) and demo.keyframes[-1] <= len(z) - 1
    assert np.isfinite(z).all() and np.ptp(z) > 0.05  # the tip moves


@pytest.mark.slow
def test_dynamics_selection_notebook_runs(monkeypatch, capsys):
    """The shipped model and memory: the held-out report's numbers, the query features of 3
    unseen tasks and where their top-18 come from."""
    ns = run_notebook(NOTEBOOKS / "dynamics_selection.ipynb", monkeypatch,
                      AGNOSTOS_NOTEBOOK_SMALL="1")
    out = capsys.readouterr().out
    memory = ns["memory"]
    # "the seen memory (3,600 demos with their features)"
    assert len(memory) == 3600 and len(set(memory.task.tolist())) == 18
    assert {k: v.shape for k, v in memory.features.items()} == {
        p: (3600, 1024) for p in ("lang", "vis.in", "vis.out")}
    assert "| DDIM steps 10 |" in out  # the small setting: the policies' query steps
    # "the predicted last-frame latent is 56.4% closer to the true one"
    assert "'demos': 360" in out and "'reduction': 0.564" in out
    unseen = ns["unseen"]
    assert unseen == ["open_grill", "close_laptop_lid", "turn_oven_on"]
    features = ns["features"]
    assert {p: v.shape for p, v in features.items()} == {p: (3, 1024) for p in features}
    # "where they differ is where the model expects the scene to change"
    change = np.linalg.norm(features["vis.out"] - features["vis.in"], axis=1)
    assert np.all(change > 0.05 * np.linalg.norm(features["vis.in"], axis=1))
    # "the K = 18 seen demonstrations": each row of the table counts 18 seen demos.
    counts, seen = ns["counts"], ns["seen"]
    assert counts.shape == (3, 18) and np.all(counts.sum(1) == 18)
    for q, task in enumerate(unseen):
        line = next(line for line in out.splitlines() if line.startswith(task + " "))
        chosen = Counter(memory.task[ns["top"][q]].tolist())
        assert line.split(None, 1)[1] == ", ".join(f"{t} x{n}" for t, n in chosen.most_common())
    # As in the committed full run: opening the grill draws on meat_off_grill demos.
    assert counts[0, seen.index("meat_off_grill")] >= 12
