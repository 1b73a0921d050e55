"""The README and the docs/ pages: every relative link resolves (a file, and a heading for a
#fragment), every repository path and `python -m` module named in backticks exists, every
`make` target named is the Makefile's, every table row has its header's cells, the README
stays a front page, and its first lines give the two commands and the decisive result's
picture."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", ROOT / "RESULTS.md", *sorted((ROOT / "docs").glob("*.md")),
         ROOT / "docs" / "results" / "decisive" / "PREREGISTRATION.md",
         ROOT / "investigations" / "README.md"]  # fmt: skip
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def unfenced(text: str) -> list[str]:
    """The text's lines, those of a code fence (its ``` lines too) blanked, so that line k of
    the list is still line k + 1 of the page."""
    out, fence = [], False
    for line in text.splitlines():
        marker = line.startswith("```")
        fence = fence != marker
        out.append("" if fence or marker else line)
    return out


def anchors(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings (lower case, punctuation dropped, spaces to -)."""
    out = set()
    for line in unfenced(page.read_text()):
        if line.startswith("#"):
            title = line.lstrip("#").strip().lower()
            out.add(re.sub(r"[^\w\- ]", "", title).replace(" ", "-"))
    return out


def links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return [t for t in LINK.findall(text) if not re.match(r"[a-z]+://|mailto:", t)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    for target in links(page):
        path, _, fragment = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        assert resolved.exists(), f"{page.name}: {target} does not exist"
        if fragment:
            assert fragment in anchors(resolved), f"{page.name}: {target}: no such heading"


# A backticked path is checked when it starts at one of the repository's folders and holds no
# placeholder (<run>, *, {a,b}, $VAR): `hmepol_cli/envs/base.py`, `docs/results/full`.
FOLDERS = ("hmepol_cli", "tests", "docs", "benchmarks", "investigations", "tools", "conf",
           "hydra_plugins")  # fmt: skip
ALTERNATIVES = "|".join(FOLDERS)
CODE = re.compile(r"```.*?```|`[^`\n]+`", re.S)
PATH = re.compile(rf"(?<![\w./-])((?:{ALTERNATIVES})/[\w./-]*)")
MODULE = re.compile(rf"python -m ((?:{ALTERNATIVES})(?:\.\w+)+)")
MAKE = re.compile(r"(?<![\w-])make ([a-z][\w-]*)")


def code_spans(text: str) -> list[str]:
    """The text of a page's code: its backticked spans and fenced blocks."""
    return CODE.findall(text)


def named_paths(text: str) -> set[str]:
    """Repository paths named in a page's code, without placeholders."""
    out = set()
    for span in code_spans(text):
        for m in PATH.finditer(span):
            end = span[m.end() : m.end() + 1]
            if end not in ("<", "*", "{", "$"):
                out.add(m.group(1).rstrip("./"))
    return out


def named_modules(text: str) -> set[str]:
    return {m for span in code_spans(text) for m in MODULE.findall(span)}


def named_targets(text: str) -> set[str]:
    return {t for span in code_spans(text) for t in MAKE.findall(span)}


def makefile_targets() -> set[str]:
    text = (ROOT / "Makefile").read_text()
    return set(re.findall(r"^([a-z][\w-]*)\s*:(?!=)", text, flags=re.M))


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_backticked_path_and_module_exists(page):
    text = page.read_text()
    missing = sorted(p for p in named_paths(text) if not (ROOT / p).exists())
    assert not missing, f"{page.name}: no such path: {missing}"
    modules = sorted(
        m for m in named_modules(text)
        if not ROOT.joinpath(*m.split(".")).with_suffix(".py").exists()
    )  # fmt: skip
    assert not modules, f"{page.name}: `python -m` of no such module: {modules}"


@pytest.mark.parametrize("page", [*PAGES, ROOT / "Makefile"], ids=lambda p: p.name)
def test_every_make_target_named_is_the_makefiles(page):
    text = page.read_text()
    named = named_targets(text) if page.suffix == ".md" else set()
    if page.name == "Makefile":  # its comments name targets in backticks too
        comments = "\n".join(line for line in text.splitlines() if line.startswith("#"))
        named = named_targets(comments)
    missing = named - makefile_targets()
    assert not missing, f"{page.name}: no such make target: {sorted(missing)}"


def table_rows_off_their_header(text: str) -> list[tuple[int, int, int]]:
    """(line, header cells, row cells) for every table row whose cell count is not its
    header's. GitHub splits a cell at every unescaped |, in code spans too, and drops the
    cells past the header's count, so a row like that loses its last words unseen."""
    out, header = [], None
    for number, line in enumerate(unfenced(text), start=1):
        if not line.startswith("|"):
            header = None
            continue
        cells = len(re.split(r"(?<!\\)\|", line.strip().strip("|")))
        if header is None:
            header = cells
        elif cells != header:
            out.append((number, header, cells))
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_table_row_has_its_headers_cells(page):
    off = table_rows_off_their_header(page.read_text())
    assert not off, f"{page.name}: (line, header cells, row cells); write a cell's | as \\|: {off}"


def test_the_checks_find_what_they_look_for():
    """Hand-written cases: what counts as a path, a module and a target, and what does not."""
    text = (
        "Run `make test-fast`, then `python -m investigations.worlds`; see\n"
        "`hmepol_cli/envs/base.py` and `docs/results/full/`, not `outputs/runs/<run>`,\n"
        "`conf/env/<name>.yaml` or `docs/*.md`; make sure (prose, not code).\n"
        "```bash\nmake demo DEMO_DIR=x\n```\n"
    )
    assert named_paths(text) == {"hmepol_cli/envs/base.py", "docs/results/full"}
    assert named_modules(text) == {"investigations.worlds"}
    assert named_targets(text) == {"test-fast", "demo"}
    assert {"test", "test-fast", "demo", "bench", "results"} <= makefile_targets()
    assert "PYTHON" not in makefile_targets() and "TEST_WORKERS" not in makefile_targets()
    table = "| a | b |\n|---|---|\n| max \\|h'\\| 2 | ok |\n| max |h'| 2 | lost |\n\nprose | x\n"
    assert table_rows_off_their_header(table) == [(4, 2, 4)]


def test_the_anchor_rule_follows_github():
    page = ROOT / "docs" / "worlds.md"
    assert "your-own-gymnasium-environment" in anchors(page)


def test_the_readme_is_a_front_page_with_the_two_commands_first():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250
    head = "\n".join(lines[:12])
    assert "make demo" in head and "make test" in head
    screen = "\n".join(lines[:25])  # one picture on the first screen: the decisive result
    assert re.findall(r"!\[[^\]]*\]\(([^)]+)\)", screen) == [
        "docs/results/decisive/figures/corridor.png"
    ]
    documented = {Path(t).name for t in links(ROOT / "README.md") if t.startswith("docs/")}
    assert {p.name for p in (ROOT / "docs").glob("*.md")} <= documented
