"""Sizes a reader can hold: no function over 80 lines in evaluation/ and runtime/ (the run
and the episode loop read as named steps, not one long body), no module over 600 lines."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "agnostos_mjx"
MAX_FUNCTION_LINES = 80
MAX_MODULE_LINES = 600


def long_functions(folder: Path, limit: int) -> list[str]:
    """'path:line name (lines)' of every function under `folder` longer than `limit`."""
    found = []
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > limit:
                    found.append(f"{path.name}:{node.lineno} {node.name} "
                                 f"({lines} lines)")
    return found


def test_no_long_function_in_evaluation_or_runtime():
    found = [f for name in ("evaluation", "runtime")
             for f in long_functions(PACKAGE / name, MAX_FUNCTION_LINES)]
    assert not found, f"functions over {MAX_FUNCTION_LINES} lines: {found}"


def test_no_long_module():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        name = path.relative_to(PACKAGE).as_posix()
        with path.open() as f:
            lines = sum(1 for _ in f)
        if lines > MAX_MODULE_LINES:
            found.append(f"{name} ({lines} lines)")
    assert not found, f"modules over {MAX_MODULE_LINES} lines: {found}"


def test_the_check_sees_a_long_function(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    (tmp_path / "m.py").write_text(f"def f():\n{body}\n")
    assert len(long_functions(tmp_path, MAX_FUNCTION_LINES)) == 1
