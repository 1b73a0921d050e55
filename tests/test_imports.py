"""The package's modules import one another without a circle: every import of a project module,
at any depth of a file (a function's, or one under ``TYPE_CHECKING``, too), read from the source
with ``ast``, makes an edge; the graph of those edges has no cycle."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hmepol_cli", "hydra_plugins")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def imports(path: Path, name: str, known: set[str]) -> set[str]:
    """The project modules ``path`` (module ``name``) imports."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, up level - 1
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            # ``from pkg import mod`` imports the module pkg.mod; ``from mod import name`` mod
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base
                       for a in node.names]  # fmt: skip
        else:
            continue
        for target in targets:
            while target and target not in known:  # a name inside a module: the module
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as the modules along it (first == last), or None."""
    state: dict[str, int] = {}  # 1 on the current path, 2 done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def import_graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imports(path, name, set(known)) for name, path in known.items()}


def test_the_package_imports_without_a_circle():
    found = cycle(import_graph())
    assert found is None, "import circle: " + " -> ".join(found)


def test_the_walk_sees_the_imports_that_make_the_algorithm():
    graph = import_graph()
    assert {"hmepol_cli.settings", "hmepol_cli.records", "hmepol_cli.surrogate"} <= graph[
        "hmepol_cli.mepol"
    ]
    assert "hmepol_cli.settings" in graph["hmepol_cli.surrogate"]
    assert "hmepol_cli.estimators" in graph["hmepol_cli.settings"]  # from pkg import module


def test_cycle_finds_a_circle_and_only_a_circle():
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None  # a diamond is no circle
    assert cycle({"a": {"b"}, "b": {"b2"}, "b2": {"b"}}) == ["b", "b2", "b"]


def test_a_type_checking_import_back_is_a_circle(tmp_path):
    """The circle the settings split removed: surrogate imported the settings from mepol under
    TYPE_CHECKING while mepol imported surrogate."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "loop.py").write_text("from pkg.surrogate import Surrogate\n")
    (pkg / "surrogate.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.loop import Settings\n"
    )
    known = {"pkg", "pkg.loop", "pkg.surrogate"}
    graph = {
        n: imports(pkg / f"{n.split('.')[-1] if '.' in n else '__init__'}.py", n, known)
        for n in known
    }
    assert cycle(graph) in (
        ["pkg.loop", "pkg.surrogate", "pkg.loop"],
        ["pkg.surrogate", "pkg.loop", "pkg.surrogate"],
    )
