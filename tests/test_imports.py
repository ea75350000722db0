"""The package's import graph (ast over every module, function-level imports included: an import inside a
function that only hides a cycle is still one) has no cycle through calibrate, calibration, evaluate, the
baselines, reconstruct, metrics or reference, and none between factors/ and the rest."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ROOTS = {"ari_sfm": ROOT / "ari_sfm", "ari_sfm.factors": ROOT / "factors", "ari_sfm.pipelines": ROOT / "pipelines"}
ACYCLIC = {"ari_sfm.calibrate", "ari_sfm.calibration", "ari_sfm.evaluate", "ari_sfm.reconstruct", "ari_sfm.metrics",
           "ari_sfm.reference", "ari_sfm.points"}


def modules() -> dict[str, Path]:
    """Dotted name -> file of every module (factors/ and pipelines/ mapped into ari_sfm, as pyproject.toml does)."""
    out = {}
    for package, folder in ROOTS.items():
        for path in folder.rglob("*.py"):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([package, *parts])] = path
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports anywhere in its body (a package's parents' __init__ not counted)."""
    mods = modules()
    graph = {m: set() for m in mods}
    for name, path in mods.items():
        here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = ".".join(here[:len(here) - node.level + 1] + ([node.module] if node.module else [])) \
                    if node.level else (node.module or "")
                subs = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in mods]
                # `from pkg import sub` imports the submodule; pkg itself only for names that are not submodules
                targets = subs + ([base] if len(subs) < len(node.names) else [])
            else:
                continue
            graph[name] |= {t for t in targets if t in mods and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in graph:
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
                component = set()
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.add(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(component)
    return found


def test_the_graph_sees_function_level_imports():
    graph = import_graph()
    assert "ari_sfm.detection" in graph["ari_sfm.factors.rig_graph"]  # inside RigGraph.from_dataset
    assert "ari_sfm.models.polynomial" in graph["ari_sfm.calibration"]  # inside the pf parsing
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]


def test_no_import_cycle_through_the_calibration_and_reconstruction_modules():
    for component in cycles(import_graph()):
        named = {m for m in component if m in ACYCLIC or m.startswith("ari_sfm.baselines")}
        assert not named, f"import cycle through {sorted(named)}: {sorted(component)}"
        in_factors = {m.startswith("ari_sfm.factors") for m in component}
        assert in_factors == {True}, f"import cycle between factors/ and the rest: {sorted(component)}"
