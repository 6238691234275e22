"""No import cycles among the modules of agnostos_mjx.

Every module is parsed with `ast` (nothing is imported), and each import that runs when
its code runs becomes an edge between two of the package's modules:

* module-level imports and function-local (or class-level, or try/except) ones alike:
  a local import only defers the cycle to the first call, it does not remove it;
* `import a.b.c` -> the longest prefix of a.b.c that is one of our modules;
* `from a.b import c` -> the submodule a.b.c when there is one, else the module a.b
  (a name defined there); relative imports (`from . import x`, `from ..y import z`)
  are resolved against the importing module's package first;
* imports under `if TYPE_CHECKING:` (or `typing.TYPE_CHECKING`) are left out: they never
  execute, so they cannot form a runtime cycle (an `else:` branch of that `if` does run
  and is kept);
* the implicit initialisation of a module's parent packages is not an edge (Python runs
  a package's __init__ before any of its submodules, whatever the imports say), but an
  explicit `from agnostos_mjx.pkg import name` of something __init__ defines is.

Not seen: imports by computed name (`importlib.import_module(f"...{name}")`, as the
task registry does) - they are not in the source as module names.

A cycle is a strongly connected component of that graph of more than one module.

Compared with the shared `tools/import_cycles.py` (the project's ad-hoc tool): with
`import_graph(..., type_checking=True)` both find the same cycles on today's tree (this
graph has a few more edges, from packages to their own submodules, which the tool skips;
none closes a cycle).  The rule here leaves TYPE_CHECKING imports out, so a cycle the
tool lists only through such an import is not reported.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "agnostos_mjx"


def package_modules(root: Path) -> dict[str, Path]:
    """Dotted module name -> source file, for every .py file under package directory `root`."""
    modules = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


class _Imports(ast.NodeVisitor):
    """Collects (absolute module, imported names or None) of every executed import."""

    def __init__(self, package: list[str], type_checking: bool = False):
        self.package = package  # the package relative imports start from
        self.type_checking = type_checking  # also collect `if TYPE_CHECKING:` imports
        self.found: list[tuple[str, list[str] | None, int]] = []

    def visit_If(self, node: ast.If) -> None:
        if _is_type_checking(node.test) and not self.type_checking:
            for child in node.orelse:  # the body never runs; an else does
                self.visit(child)
        else:
            self.generic_visit(node)

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self.found.append((alias.name, None, node.lineno))

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.level:
            keep = len(self.package) - (node.level - 1)
            if keep <= 0:
                return  # beyond the top-level package: not ours
            base = ".".join(self.package[:keep] + ([node.module] if node.module else []))
        else:
            base = node.module or ""
        self.found.append((base, [a.name for a in node.names], node.lineno))


def import_graph(root: Path, type_checking: bool = False) -> dict[str, dict[str, str]]:
    """module -> {imported module of the package -> where ("file:line")}; `type_checking`
    also counts the imports under `if TYPE_CHECKING:` (for comparison, not the rule)."""
    modules = package_modules(root)

    def resolve(name: str) -> str | None:
        parts = name.split(".")
        for i in range(len(parts), 0, -1):
            if ".".join(parts[:i]) in modules:
                return ".".join(parts[:i])
        return None

    graph: dict[str, dict[str, str]] = {m: {} for m in modules}
    for module, path in modules.items():
        is_package = path.name == "__init__.py"
        package = module.split(".") if is_package else module.split(".")[:-1]
        visitor = _Imports(package, type_checking)
        visitor.visit(ast.parse(path.read_text(), str(path)))
        for base, names, line in visitor.found:
            if names is None:  # `import a.b.c`: its parents' initialisation is implicit
                targets = [(resolve(base), False)]
            else:  # `from a.b import c`: a submodule, or a name read from a.b (explicit)
                targets = [(f"{base}.{n}", True) if f"{base}.{n}" in modules
                           else (resolve(base), True) for n in names]
            for target, explicit in targets:
                if target is None or target == module:
                    continue
                if module.startswith(target + ".") and not explicit:
                    continue
                graph[module].setdefault(target, f"{path.relative_to(root.parent)}:{line}")
    return graph


def cycles(graph: dict[str, dict[str, str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted,
    in a stable order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(graph) + 100))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return sorted(found)


def describe(graph: dict[str, dict[str, str]], component: list[str]) -> str:
    """A cycle and the import lines that make it."""
    members = set(component)
    lines = [" <-> ".join(component)]
    for m in component:
        for target, where in sorted(graph[m].items()):
            if target in members:
                lines.append(f"    {m} -> {target}  ({where})")
    return "\n".join(lines)


def test_no_import_cycles():
    graph = import_graph(PACKAGE)
    found = cycles(graph)
    assert not found, (
        f"{len(found)} import cycle(s) among the modules of agnostos_mjx (module-level and "
        "function-local imports; TYPE_CHECKING blocks excluded):\n"
        + "\n".join(describe(graph, c) for c in found)
        + "\nBreak each by moving what both sides need into a module that imports neither "
        "(e.g. dynamics/export_format.py, xicm/query.py), or by passing it in as an argument."
    )


def _write(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / "pkg"


def test_finder_on_a_synthetic_package(tmp_path):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        # a <-> b through a function-local import: found
        "pkg/a.py": "from pkg.b import g\n\ndef f():\n    return g()\n",
        "pkg/b.py": "def g():\n    from pkg import a\n    return a\n",
        # c -> d at module level, d -> c only under TYPE_CHECKING: not a cycle
        "pkg/c.py": "from pkg.d import D\n",
        "pkg/d.py": ("from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n"
                     "    from pkg.c import C\nelse:\n    import os\n\nclass D: ...\n"),
        # relative imports: sub.x -> sub.y -> (..) e -> sub.x
        "pkg/sub/__init__.py": "",
        "pkg/sub/x.py": "from .y import Y\n",
        "pkg/sub/y.py": "import typing\n\nif typing.TYPE_CHECKING:\n    import pkg.c\n"
                        "from .. import e\nY = 1\n",
        "pkg/e.py": "class E:\n    def m(self):\n        import pkg.sub.x\n",
    })
    graph = import_graph(pkg)
    assert graph["pkg.b"] == {"pkg.a": "pkg/b.py:2"}
    assert "pkg.c" not in graph["pkg.d"] and "pkg.c" not in graph["pkg.sub.y"]
    assert cycles(graph) == [["pkg.a", "pkg.b"], ["pkg.e", "pkg.sub.x", "pkg.sub.y"]]
    message = describe(graph, ["pkg.a", "pkg.b"])
    assert "pkg.b -> pkg.a  (pkg/b.py:2)" in message and "pkg.a -> pkg.b  (pkg/a.py:1)" in message
