"""The code's layering, read from the source: the apps are leaves (nothing imports them), the
packages import each other without a cycle, and the experiment code keeps its functions short."""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: the top-level packages whose imports are checked
TOP = ("dss", "pix2pix", "data_prep", "experiments", "conf")
MAX_LINES = 80


def _modules():
    """(path relative to the repository, dotted module name, parsed tree) of every package file."""
    for top in TOP:
        for path in sorted((REPO / top).rglob("*.py")):
            rel = path.relative_to(REPO)
            parts = list(rel.with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            yield rel.as_posix(), ".".join(parts), ast.parse(path.read_text(), filename=str(rel))


def _imports(tree: ast.AST, module: str) -> set[str]:
    """Every module an import statement anywhere in ``tree`` names (function-level ones too;
    relative imports resolved against ``module``)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[:len(base) - node.level + (1 if _is_package(module) else 0)]
                name = ".".join([*base, *([node.module] if node.module else [])])
            else:
                name = node.module or ""
            found.add(name)
            found.update(f"{name}.{a.name}" for a in node.names)
    return found


def _is_package(module: str) -> bool:
    return (REPO / Path(*module.split(".")) / "__init__.py").is_file()


def package_of(module: str) -> str | None:
    """The layer a module belongs to: ``dss``, ``pix2pix``, ``data_prep``, ``conf``, one of
    ``experiments``' sub-packages (``experiments.apps``, ``experiments.denoising``, ...), or
    ``experiments`` for its shared top-level modules (common, outputs, ...)."""
    parts = module.split(".")
    if parts[0] not in TOP:
        return None
    if parts[0] == "experiments" and len(parts) > 1 and (REPO / "experiments" / parts[1]).is_dir():
        return f"experiments.{parts[1]}"
    return parts[0]


def package_graph() -> dict[str, dict[str, set[str]]]:
    """{package: {imported package: {files that import it}}}, imports inside a package left out."""
    graph: dict[str, dict[str, set[str]]] = {}
    for rel, module, tree in _modules():
        src = package_of(module)
        graph.setdefault(src, {})
        for name in _imports(tree, module):
            dst = package_of(name)
            if dst and dst != src:
                graph[src].setdefault(dst, set()).add(rel)
    return graph


def _cycle(graph: dict[str, dict[str, set[str]]]) -> list[str] | None:
    """One import cycle between packages, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, {})):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_no_import_cycle_between_packages():
    graph = package_graph()
    cycle = _cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle) + "; " + "; ".join(
        f"{a} -> {b} in {sorted(graph[a][b])[:3]}" for a, b in zip(cycle, cycle[1:]))
    # the library at the bottom imports none of the layers above it
    assert set(graph["dss"]) <= {"conf"}, graph["dss"]
    assert not set(graph["pix2pix"]) & {"dss", "data_prep"} and not any(
        p.startswith("experiments") for p in graph["pix2pix"]), graph["pix2pix"]
    assert not any(p.startswith("experiments") for p in graph["data_prep"]), graph["data_prep"]


def test_the_check_finds_a_cycle():
    graph = {"a": {"b": {"a.py"}}, "b": {"c": {"b.py"}}, "c": {"a": {"c.py"}}, "d": {"a": {"d.py"}}}
    assert _cycle(graph) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b": {"a.py"}}, "b": {}}) is None
    assert package_of("experiments.evaluation.table.cases") == "experiments.evaluation"
    assert package_of("experiments.common") == "experiments" and package_of("numpy") is None


def test_nothing_imports_the_apps():
    """experiments.apps holds the command-line apps; the packages (and evaluation) never import
    them, and no config instantiates a class from them."""
    offenders = []
    for rel, module, tree in _modules():
        if package_of(module) == "experiments.apps":
            continue
        offenders += [f"{rel}: {name}" for name in _imports(tree, module)
                      if name == "experiments.apps" or name.startswith("experiments.apps.")]
    for path in sorted((REPO / "conf").rglob("*.yaml")):
        offenders += [f"{path.relative_to(REPO)}: {m}" for m in
                      re.findall(r"_target_:\s*(experiments\.apps\.\S+)", path.read_text())]
    assert not offenders, offenders


def test_experiment_functions_are_short():
    """No function in experiments/ is longer than MAX_LINES lines (long jobs are split into
    named stages)."""
    long = []
    for path in sorted((REPO / "experiments").rglob("*.py")):
        rel = path.relative_to(REPO).as_posix()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_LINES:
                    long.append(f"{rel}:{node.lineno} {node.name} ({n} lines)")
    assert not long, long
