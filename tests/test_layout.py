"""The shape of the code base: no class over 300 lines, no function over 100, and no import circle between its
modules (imports inside functions count; those under ``if TYPE_CHECKING`` do not run and do not)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_CLASS, MAX_FUNCTION = 300, 100


def _modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the packages wpot and render."""
    out = {}
    for path in sorted([*ROOT.glob("wpot/**/*.py"), *ROOT.glob("render/**/*.py")]):
        parts = path.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


MODULES = _modules()


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for n in ast.walk(node))
    return skip


def imports_of(name: str) -> set[str]:
    """The modules of wpot and render that module ``name`` imports, wherever the import statement stands."""
    path = MODULES[name]
    tree = ast.parse(path.read_text())
    skip = _type_checking_nodes(tree)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
        else:
            continue
        out.update(t for t in targets if t in MODULES and t != name)
    return out


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return cycles


def test_the_cycle_finder_finds_a_planted_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert import_cycles(graph) == [["a", "b", "c"]]
    assert import_cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circle():
    graph = {name: imports_of(name) for name in MODULES}
    assert sum(map(len, graph.values())) > 50  # the graph was read (a parse that found nothing would pass)
    assert import_cycles(graph) == []


def _sizes() -> list[tuple[str, str, int]]:
    out = []
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                kind = "class" if isinstance(node, ast.ClassDef) else "function"
                out.append((kind, f"{name}.{node.name}", node.end_lineno - node.lineno + 1))
    return out


@pytest.mark.parametrize("kind,limit", [("class", MAX_CLASS), ("function", MAX_FUNCTION)])
def test_no_class_or_function_too_long(kind, limit):
    sizes = [(what, n) for k, what, n in _sizes() if k == kind]
    assert len(sizes) > 20
    assert [(what, n) for what, n in sizes if n > limit] == []


def test_the_packages_follow_the_pipeline():
    """Each stage of the data flow is a package or module of its own (the docs' front page draws them)."""
    for module in ("wpot.mesh", "wpot.io", "wpot.spectral", "wpot.signatures", "wpot.sampling", "wpot.cost",
                   "wpot.ot", "wpot.ot.exact", "wpot.ot.anneal", "wpot.comparison", "wpot.maps", "wpot.runs",
                   "wpot.evaluate", "wpot.plot", "wpot.paper", "wpot.cli", "render"):
        assert module in MODULES, module
    top = {n for n in MODULES if n.count(".") == 1 and n.startswith("wpot.")}
    assert len(top) <= 25  # flat modules stay few: a stage with several modules is a package
