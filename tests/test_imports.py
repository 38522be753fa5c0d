"""Import structure of the package: no module imports itself back through others, the evaluator
stands below the SLAM back end, the file helpers (results folder included) below both and the
odometry, and the command line starts without torch.

The graph is read from the source with ``ast``: every ``import`` and ``from ... import`` of a
``radarslam`` module, at module level and inside functions (a lazy import is still a dependency),
resolved to the file it loads (``from radarslam.io import loops`` is an edge to
``radarslam/io/loops.py``; ``from radarslam.io.loops import NodeKey`` too). Importing a submodule
also runs its package's ``__init__.py``; those implicit edges are left out, they are not a choice
a module makes.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "radarslam"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE_DIR.rglob("*.py"))}


def _imported(name: str, path: Path, modules: dict[str, Path]) -> dict[str, int]:
    """The package modules ``name`` imports, each with the first line that does."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for alias in node.names:
                submodule = f"{source}.{alias.name}"
                targets.append((submodule if submodule in modules else source, node.lineno))
    found: dict[str, int] = {}
    for target, line in targets:
        while target and target not in modules:  # an attribute path: its module
            target = target.rpartition(".")[0]
        if target and target != name:
            found.setdefault(target, line)
    return found


def import_graph() -> dict[str, dict[str, int]]:
    """module -> {imported package module: line}."""
    modules = _modules()
    return {name: _imported(name, path, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(graph[root]))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(graph[child])))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def _describe(component: list[str], graph: dict[str, dict[str, int]]) -> str:
    edges = [
        f"{a}:{line} -> {b}"
        for a in component
        for b, line in sorted(graph[a].items())
        if b in component
    ]
    return "; ".join(edges)


def test_the_graph_sees_top_level_and_function_level_imports():
    graph = import_graph()
    assert "radarslam.io.loops" in graph["radarslam.eval.loops"]  # module level
    # inside a function: the evaluator's command loads the evaluator on call
    assert "radarslam.eval.evaluate" in graph["radarslam.eval.commands"]
    assert "radarslam.place_recognition.commands" in graph["radarslam.cli"]


def test_cycle_detection_finds_a_cycle():
    graph = {"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}
    assert _cycles(graph) == [["a", "b", "c"]]


def test_no_import_cycle_between_modules():
    graph = import_graph()
    cycles = _cycles(graph)
    assert not cycles, "import cycles: " + " | ".join(_describe(c, graph) for c in cycles)


def test_eval_does_not_import_slam():
    graph = import_graph()
    bad = [
        f"{module}:{line} imports {target}"
        for module, targets in graph.items()
        if module == "radarslam.eval" or module.startswith("radarslam.eval.")
        for target, line in targets.items()
        if target == "radarslam.slam" or target.startswith("radarslam.slam.")
    ]
    assert not bad, "; ".join(bad)


def test_the_results_folder_stands_below_its_writers_and_reader():
    """``radarslam.io`` (the results folder among it) is shared by SLAM, the odometry and the
    evaluator, so it imports none of them."""
    graph = import_graph()
    above = ("radarslam.slam", "radarslam.odometry", "radarslam.eval")
    bad = [
        f"{module}:{line} imports {target}"
        for module, targets in graph.items()
        if module == "radarslam.io" or module.startswith("radarslam.io.")
        for target, line in targets.items()
        if any(target == a or target.startswith(f"{a}.") for a in above)
    ]
    assert not bad, "; ".join(bad)


def test_the_command_line_starts_without_torch():
    code = (
        "import sys\n"
        "import radarslam.cli\n"
        "after_import = 'torch' in sys.modules\n"
        "sys.argv = ['radarslam', '--help']\n"
        "try:\n"
        "    radarslam.cli.main()\n"
        "except SystemExit:\n"
        "    pass\n"
        "print(after_import, 'torch' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.split()[-2:] == ["False", "False"], out.stdout + out.stderr
