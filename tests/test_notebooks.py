"""The evaluation notebook's code runs as written (in-process, Agg backend) and its
results are what the notebook's text claims."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "evaluate.ipynb"


def test_evaluate_notebook_runs(monkeypatch):
    matplotlib.use("Agg")
    monkeypatch.chdir(NOTEBOOK.parent)
    cells = json.loads(NOTEBOOK.read_text())["cells"]
    namespace: dict = {}
    for cell in cells:
        if cell["cell_type"] == "code":
            source = "".join(cell["source"]) if isinstance(cell["source"], list) else cell["source"]
            exec(compile(source, f"{NOTEBOOK.name} cell", "exec"), namespace)
    assert len(namespace["tasks"]) == 23
    assert namespace["results"]["complete"]
    summary = namespace["mine"]["summary"]["tasks"]
    assert summary["lamp_on"]["success_mean"] == summary["lamp_off"]["success_mean"] == 100.0
    plan = namespace["plan"]
    assert plan["response"].startswith("Sure!") and len(plan["parsed"]["actions"]) == 2
    assert namespace["xicm"]["policy"]["name"].startswith("xicm")
