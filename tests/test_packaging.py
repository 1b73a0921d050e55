"""The package as a new user gets it (issue 35): what `make demo` installs, the licence and the
citation, `hmepol --version`."""

from __future__ import annotations

import importlib.metadata
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parent.parent
HEAVY = {"mlflow", "wandb", "tensorboard", "mujoco"}  # what the demo needs none of


def make_dry_run(target: str) -> list[str]:
    """The commands `make TARGET` would run, prerequisites first (make -n runs none of them)."""
    if shutil.which("make") is None:
        pytest.skip("no make on this machine")
    out = subprocess.run(
        ["make", "-n", "-C", str(ROOT), "--no-print-directory", target, "PYTHON=python"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    return out.splitlines()


def pip_requirements(lines: list[str]) -> list[tuple[str, set[str]]]:
    """(distribution, extras) of everything the `pip install` lines name; the checkout itself
    (``-e .``, ``.[a,b]``) is hmepol."""
    wanted = []
    for line in lines:
        words = shlex.split(line)
        if "pip" not in words or "install" not in words:
            continue
        for word in words[words.index("install") + 1 :]:
            if word.startswith("-"):
                continue
            path = re.fullmatch(r"\.(?:\[(.*)\])?", word)
            if path:
                extras = {e.strip() for e in (path.group(1) or "").split(",") if e.strip()}
                wanted.append(("hmepol", extras))
            else:
                req = Requirement(word)
                wanted.append((req.name, set(req.extras)))
    return wanted


def installed_closure(wanted: list[tuple[str, set[str]]]) -> set[str]:
    """Every distribution those requirements pull in, followed through the metadata of what
    this environment has installed (each one's Requires-Dist, markers and extras evaluated)."""
    seen: set[str] = set()
    todo = [(canonicalize_name(name), extras) for name, extras in wanted]
    done: set[tuple[str, frozenset[str]]] = set()
    while todo:
        name, extras = todo.pop()
        if (name, frozenset(extras)) in done:
            continue
        done.add((name, frozenset(extras)))
        seen.add(name)
        try:
            requires = importlib.metadata.requires(name) or []
        except importlib.metadata.PackageNotFoundError:
            continue  # not installed here: its name is checked, its own needs cannot be
        for text in requires:
            req = Requirement(text)
            if req.marker is None or any(
                req.marker.evaluate({"extra": extra}) for extra in {"", *extras}
            ):
                todo.append((canonicalize_name(req.name), set(req.extras)))
    return seen


def test_the_demo_install_pulls_no_tracking_mujoco_or_test_packages():
    lines = make_dry_run("demo")
    wanted = pip_requirements(lines)
    assert ("hmepol", set()) in wanted and any(name == "torch" for name, _ in wanted), lines
    pulled = installed_closure(wanted)
    assert {"torch", "hydra-core", "gymnasium", "matplotlib"} <= pulled  # the walk follows needs
    assert not pulled & HEAVY, sorted(pulled & HEAVY)
    assert not pulled & {"pytest", "hypothesis", "ruff"}, lines
    # the demo itself runs before nothing is installed: its first command is an install
    assert "pip install" in lines[0] and "hmepol" in "\n".join(lines[2:])


def test_make_install_and_make_test_do_install_the_extras_the_tests_use():
    # The same walk on what CI runs finds the heavy packages: the check above can fail.
    for target in ("install", "test"):
        wanted = pip_requirements(make_dry_run(target))
        assert ("hmepol", {"dev", "mujoco", "tracking"}) in wanted, target
    pulled = installed_closure([("hmepol", {"dev", "tracking"})])
    assert {"mlflow", "wandb", "tensorboard", "pytest", "hypothesis"} <= pulled


def test_the_licence_is_mit_and_the_package_says_so():
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "Copyright (c) 2026 the hmepol authors" in text
    assert "WITHOUT WARRANTY OF ANY KIND" in text
    meta = importlib.metadata.metadata("hmepol")
    assert meta["License-Expression"] == "MIT"
    assert "LICENSE" in (meta.get_all("License-File") or [])


def test_the_citation_file_cites_this_software_the_thesis_mepol_and_alpha_mepol():
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0"
    assert cff["type"] == "software" and cff["title"] and cff["message"] and cff["authors"]
    assert cff["version"] == importlib.metadata.version("hmepol")
    assert cff["license"] == "MIT"
    works = {ref["title"]: ref for ref in cff["references"]}
    thesis = works[
        "Unsupervised Pre-Training for Reinforcement Learning via Recursive History Encoders"
    ]
    assert thesis["type"] == "thesis"
    assert [a["family-names"] for a in thesis["authors"]] == ["Maldini"]
    mepol = works[
        "Task-Agnostic Exploration via Policy Gradient of a Non-Parametric State Entropy Estimate"
    ]
    alpha = works["Unsupervised Reinforcement Learning in Multiple Environments"]
    assert [a["family-names"] for a in mepol["authors"]] == ["Mutti", "Pratissoli", "Restelli"]
    assert [a["family-names"] for a in alpha["authors"]] == ["Mutti", "Mancassola", "Restelli"]
    assert (mepol["year"], alpha["year"]) == (2021, 2022)
    for paper in (mepol, alpha):
        assert paper["type"] == "conference-paper" and "AAAI" in paper["collection-title"]
        assert all(a["given-names"] for a in paper["authors"])


@pytest.mark.parametrize("flag", ["--version", "-V"])
def test_version_prints_the_installed_version(flag, capsys):
    from hmepol_cli.cli import main

    main([flag])  # the console script's own run is in the wheel test below
    assert capsys.readouterr().out == f"hmepol {importlib.metadata.version('hmepol')}\n"
