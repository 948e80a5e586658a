"""Imports run one way: no two modules of v2vsim, agents and models import each other, directly or through others,
counting imports inside functions and under TYPE_CHECKING (read from the source, nothing is imported)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("v2vsim", "agents", "models")


def _modules() -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is a package's __init__)."""
    out = {}
    for pkg in PACKAGES:
        for f in sorted((REPO / pkg).rglob("*.py")):
            parts = list(f.relative_to(REPO).with_suffix("").parts)
            init = parts[-1] == "__init__"
            out[".".join(parts[:-1] if init else parts)] = (f, init)
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules of PACKAGES it imports (`from a import b` counts as a.b where b is a module)."""
    mods = _modules()

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, (f, init) in mods.items():
        here = m if init else m.rpartition(".")[0]
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = here.split(".")[: len(here.split(".")) - (node.level - 1)]
                    base = ".".join(parts + ([node.module] if node.module else []))
                targets = [base, *(f"{base}.{a.name}" for a in node.names)]
            else:
                continue
            graph[m].update(r for t in targets if (r := resolve(t)) not in (None, m))
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_the_graph_sees_function_level_imports() -> None:
    graph = import_graph()
    assert "models.fusion.contract" in graph["models.registry"]  # imported inside a function (it imports torch)
    assert "agents.ego" in graph["agents.evaluate"]


def test_no_import_circle() -> None:
    graph = import_graph()
    found = circles(graph)
    assert not found, "import circles: " + "; ".join(
        ", ".join(f"{a} -> {b}" for a in c for b in sorted(graph[a]) if b in c) for c in found)


def test_a_circle_is_found() -> None:
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def upward_imports(package: str, above: tuple[str, ...]) -> list[str]:
    """`file:line imported` for every import, at any depth of the code, of a package in `above` by a Python file
    anywhere under `package`/ (candidates' folders and scripts included, not only the import package's modules)."""
    found = []
    for f in sorted((REPO / package).rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module or ""]
            else:
                continue
            found += [f"{f.relative_to(REPO)}:{node.lineno} {n}" for n in names if n.split(".")[0] in above]
    return found


def test_models_import_nothing_of_the_harness() -> None:
    """issue 52: models/ holds models; the data flow runs v2vsim/agents -> models, never back (experiment scripts
    that drive the trainer live under scripts/)."""
    found = upward_imports("models", ("v2vsim", "agents"))
    assert not found, "models/ imports the harness: " + "; ".join(found)
