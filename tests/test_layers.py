"""The import structure: the service path stays off the simulation, and no package has a cycle.

Every import counts, at module level or inside a function (a function-level import hides a
dependency, it does not remove it); only imports under `if TYPE_CHECKING:` are left out.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# Modules allowed to import companion.sim: the simulation itself and the command that runs it.
SIM_USERS = ("companion.sim", "companion.cli")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules(package: str) -> dict[str, Path]:
    return {_module_name(p): p for p in sorted((ROOT / package).rglob("*.py"))}


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imported(tree: ast.AST, known: dict[str, Path], this: str) -> set[str]:
    """The project modules `tree` imports (a `from package import name` of a submodule counts
    as that submodule)."""
    found: set[str] = set()
    package = this if known[this].name == "__init__.py" else this.rpartition(".")[0]

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node):
            for statement in node.orelse:
                visit(statement)
            return
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.add(sub if sub in known else base)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return {name for name in found if name in known and name != this}


def _graph(package: str) -> dict[str, set[str]]:
    known = {**_modules("companion"), **_modules("sitl")}
    return {name: _imported(ast.parse(path.read_text()), known, name)
            for name, path in known.items() if name.split(".")[0] == package}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle among the graph's own modules, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in graph:
                continue
            if state.get(nxt) == 1:
                return [*path[path.index(nxt):], nxt]
            if nxt not in state and (found := visit(nxt)) is not None:
                return found
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (found := visit(start)) is not None:
            return found
    return None


def test_only_the_simulation_and_the_command_import_the_simulation() -> None:
    graph = _graph("companion")
    users = {name: sorted(m for m in deps if m.startswith("companion.sim"))
             for name, deps in graph.items() if not name.startswith(SIM_USERS)}
    assert {name: sims for name, sims in users.items() if sims} == {}


def test_no_import_cycle_in_companion_or_sitl() -> None:
    for package in ("companion", "sitl"):
        assert _cycle(_graph(package)) is None, package


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None
