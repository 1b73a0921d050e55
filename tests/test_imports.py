"""The package's modules import one another without a circle: every import of a project module,
at any depth of a file (a function's, or one under ``TYPE_CHECKING``, too), read from the source
with ``ast``, makes an edge; the graph of those edges has no cycle. The report imports nothing
that trains (it reads what runs wrote), neither in its source nor when it runs."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

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


# The report reads what runs wrote (run.json, the tables) and draws it: it needs the run
# directory's contract (hmepol_cli.run), the drawing (hmepol_cli.plots) and the algorithms'
# names and colours (hmepol_cli.algorithms, plain data), never the code that trains. A study's
# folder brings in hmepol_cli.study, which reads its decisions with the report's statistics.
REPORT_MAY_IMPORT = (
    "hmepol_cli",
    "hmepol_cli.algorithms",
    "hmepol_cli.errors",
    "hmepol_cli.plots",
    "hmepol_cli.run",
    "hmepol_cli.study",
)
TRAINING_CODE = (
    "torch",
    "hmepol_cli.envs",
    "hmepol_cli.config",
    "hmepol_cli.trainer",
    "hmepol_cli.finetune",
    "hmepol_cli.checks",
)


def test_the_report_imports_only_what_reads_and_draws_runs():
    graph = import_graph()

    def outside(name: str) -> set[str]:
        return {
            m
            for m in graph[name]
            if m not in REPORT_MAY_IMPORT
            and not m.startswith(("hmepol_cli.report", "hmepol_cli.run"))
        }

    report = [n for n in graph if n == "hmepol_cli.report" or n.startswith("hmepol_cli.report.")]
    for name in [*report, "hmepol_cli.plots", "hmepol_cli.algorithms", "hmepol_cli.study"]:
        assert not outside(name), f"{name} imports {sorted(outside(name))}"


@pytest.mark.slow  # a fresh interpreter (or several): make test runs it, make test-fast does not
def test_a_report_loads_no_training_code(tmp_path):
    """In a fresh interpreter, importing the report and making one (runs, a fine-tuning) loads
    neither torch nor the modules that train."""
    from tests.test_report import write_finetune_run, write_run

    for seed in (0, 1):
        write_run(tmp_path / "runs", seed=seed)
        write_finetune_run(tmp_path / "runs", algo_init="mepol", seed=seed)
    script = f"""
import sys
from pathlib import Path
import hmepol_cli.report
imported = set(sys.modules)
hmepol_cli.report.run_report(Path({str(tmp_path / "runs")!r}), Path({str(tmp_path / "out")!r}))
for when, names in (("import", imported), ("report", set(sys.modules))):
    for name in {TRAINING_CODE!r}:
        if any(m == name or m.startswith(name + ".") for m in names):
            print(when, name)
"""
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, check=False
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "runs used" in done.stdout
    loaded = [line for line in done.stdout.splitlines() if line.startswith(("import ", "report "))]
    assert loaded == []


def test_the_config_defaults_the_report_reads_are_todays():
    from hmepol_cli.report.defaults import DEFAULTS_FILE
    from tools.config_defaults import config_defaults

    assert json.loads(DEFAULTS_FILE.read_text()) == config_defaults(), (
        f"{DEFAULTS_FILE.name} is not what the schema and conf/ give: write it again with "
        "python -m tools.config_defaults"
    )
