"""docs/architecture.md's layer table against the package's imports: every module has a row,
and no import points to a higher row (type-only imports aside)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "agnostos_mjx"


def layer_table() -> list[tuple[int, list[str]]]:
    """(row, the path column's entries) of each row of the table."""
    rows = []
    for line in (ROOT / "docs" / "architecture.md").read_text().splitlines():
        found = re.match(r"\| (\d+) \| ([^|]*) \|", line)
        if found:
            column = re.sub(r"\([^)]*\)", "", found.group(2))  # asides name no row's files
            paths = re.findall(r"`([^`]+)`", column)
            rows.append((int(found.group(1)), [p for p in paths if p.endswith((".py", "/"))]))
    return rows


def row_of(module: str, table: list[tuple[int, list[str]]]) -> int | None:
    """The row naming `module` (a path under agnostos_mjx/): its file, else the longest
    folder that holds it."""
    best: tuple[int, int] | None = None  # (specificity, row)
    for row, paths in table:
        for path in paths:
            if path == module:
                return row
            if path.endswith("/") and module.startswith(path):
                if best is None or len(path) > best[0]:
                    best = (len(path), row)
    return None if best is None else best[1]


def type_only(tree: ast.Module) -> set[int]:
    """Line numbers of the imports under `if TYPE_CHECKING:`."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for inner in node.body:
                for sub in ast.walk(inner):
                    if isinstance(sub, ast.Import | ast.ImportFrom):
                        lines.add(sub.lineno)
    return lines


def targets(node: ast.AST) -> list[str]:
    """The package's modules an import statement loads, as paths under agnostos_mjx/."""
    names: list[str] = []
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
    out = []
    for name in names:
        if not name.startswith("agnostos_mjx."):
            continue
        rel = name.removeprefix("agnostos_mjx.").replace(".", "/")
        for candidate in (f"{rel}.py", f"{rel}/__init__.py"):
            if (PACKAGE / candidate).is_file():
                out.append(candidate)
    return out


def test_every_module_has_a_row_and_imports_point_down() -> None:
    table = layer_table()
    assert len(table) >= 10, "the layer table of docs/architecture.md was not found"
    modules = sorted(str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py"))
    unnamed = [m for m in modules if m != "__init__.py" and row_of(m, table) is None]
    assert not unnamed, f"modules that no row of docs/architecture.md names: {unnamed}"
    upward = []
    for module in modules:
        source = row_of(module, table)
        if source is None:
            continue
        tree = ast.parse((PACKAGE / module).read_text())
        skip = type_only(tree)
        for node in ast.walk(tree):
            if not isinstance(node, ast.Import | ast.ImportFrom) or node.lineno in skip:
                continue
            for target in targets(node):
                row = row_of(target, table)
                if target != "__init__.py" and row is not None and row > source:
                    upward.append(f"{module} (row {source}) -> {target} (row {row})")
    assert not upward, "imports that point up the layers:\n" + "\n".join(sorted(set(upward)))
