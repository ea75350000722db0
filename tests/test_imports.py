"""The package's import graph (ast over every module of ari_sfm, factors/ and pipelines/, function-level and
``if TYPE_CHECKING:`` imports included: an import that only hides a cycle is still one) has no cycle at all."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ROOTS = {"ari_sfm": ROOT / "ari_sfm", "ari_sfm.factors": ROOT / "factors", "ari_sfm.pipelines": ROOT / "pipelines"}


def modules() -> dict[str, Path]:
    """Dotted name -> file of every module (factors/ and pipelines/ as ari_sfm.factors and ari_sfm.pipelines: the
    links ari_sfm/factors and ari_sfm/pipelines point there, and rglob does not follow them)."""
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
    assert "ari_sfm.models.polynomial" in graph["ari_sfm.calibration.record"]  # inside Calibration.projection_model
    assert "ari_sfm.records" in graph["ari_sfm.models.ari"]  # under `if TYPE_CHECKING:`
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]


def test_the_factors_solver_sits_below_the_graph():
    """rig_graph -> backend -> packed_problem -> extra_factors, marginals -> variables: never upwards."""
    graph = import_graph()
    assert "ari_sfm.factors.backend" in graph["ari_sfm.factors.rig_graph"]
    for lower in ("backend", "packed_problem", "extra_factors", "marginals", "variables"):
        assert "ari_sfm.factors.rig_graph" not in graph[f"ari_sfm.factors.{lower}"], lower
    for lower in ("extra_factors", "marginals", "variables"):
        assert "ari_sfm.factors.packed_problem" not in graph[f"ari_sfm.factors.{lower}"], lower


def test_no_import_cycle_anywhere_in_the_package():
    """Every module of ari_sfm, ari_sfm.factors and ari_sfm.pipelines: no strongly connected component."""
    graph = import_graph()
    assert any(m.startswith("ari_sfm.factors.") for m in graph)
    assert any(m.startswith("ari_sfm.pipelines.") for m in graph)
    found = cycles(graph)
    assert not found, "import cycles: " + "; ".join(" <-> ".join(sorted(c)) for c in found)
