"""The package as a new user gets it: what `make demo` installs, the licence and the
citation, `hmepol --version`, and a built wheel that works with no checkout in sight."""

from __future__ import annotations

import importlib.metadata
import os
import re
import shlex
import shutil
import site
import subprocess
import sys
import textwrap
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
    # and every command after the installs runs through the Python that holds the package, so
    # PYTHON=<a venv's python> works without that venv's bin/ on PATH
    commands = [line for line in lines if "pip install" not in line]
    assert commands and all(line.startswith("python -m hmepol_cli ") for line in commands), lines


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


def test_the_checkout_check_sees_what_a_test_leaves_but_not_the_caches(tmp_path):
    from tests.conftest import checkout_paths

    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "a.py").write_text("")
    for cache in (".pytest_cache", "src/__pycache__", "hmepol.egg-info", "venv/lib"):
        (tmp_path / cache).mkdir(parents=True)
        (tmp_path / cache / "x").write_text("")
    (tmp_path / "venv" / "pyvenv.cfg").write_text("")
    before = checkout_paths(tmp_path)
    assert before == {"src", "src/a.py"}
    (tmp_path / "mlruns" / "0").mkdir(parents=True)
    (tmp_path / "outputs").mkdir()
    assert checkout_paths(tmp_path) - before == {"mlruns", "mlruns/0", "outputs"}


# --------------------------------------------------------------------------- the wheel
# Two epochs of a few short trajectories: the whole command, from config to report, in seconds.
WHEEL_RUN = [
    "epochs=1",
    "algo.trajectories=4",
    "algo.horizon=20",
    "algo.batch_size=2",
    "algo.max_off_iters=2",
    "estimator.k=3",
    "policy.hidden=[8]",
    "eval.trajectories=2",
    "eval.horizon=10",
    "progress=false",
]


def not_built(folder: str, names: list[str]) -> set[str]:
    """What the wheel test's copy of the checkout leaves out (shutil.copytree's ignore)."""
    left = {n for n in names if n == "__pycache__" or n.endswith(".egg-info")}
    if Path(folder).resolve() == ROOT:
        left |= {n for n in names if n.startswith(".") or n in ("docs", "outputs", "build", "dist")}
    return left


@pytest.mark.slow
def test_the_built_wheel_works_from_an_empty_folder_without_the_checkout(tmp_path):
    assert not tmp_path.resolve().is_relative_to(ROOT), "run the suite with its temp dir elsewhere"
    # A copy, so that the build's egg-info and build/ stay out of the checkout; without the
    # results, the runs and the caches, which no build reads.
    source, dist = tmp_path / "source", tmp_path / "dist"
    shutil.copytree(ROOT, source, ignore=not_built)
    # --no-isolation: the build backend installed here, so it builds offline; build makes the
    # sdist, then the wheel from the unpacked sdist, so a file missing from the sdist fails too.
    built = subprocess.run(
        [sys.executable, "-m", "build", "--no-isolation", "--outdir", str(dist), str(source)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-2000:]
    (wheel,) = dist.glob("hmepol-*.whl")
    (sdist,) = dist.glob("hmepol-*.tar.gz")
    version = importlib.metadata.version("hmepol")
    assert wheel.name.startswith(f"hmepol-{version}-") and sdist.name == f"hmepol-{version}.tar.gz"

    venv, empty = tmp_path / "venv", tmp_path / "empty"
    empty.mkdir()
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    site_dir = Path(
        subprocess.run(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()
    )  # fmt: skip
    # The dependencies are this environment's (offline, seconds): its site folders go on the
    # new venv's path after the venv's own, as plain path entries, so their .pth files (the
    # editable install's hook into the checkout among them) are not run. hmepol comes only from
    # the wheel.
    (site_dir / "outer-dependencies.pth").write_text("\n".join(sorted(set(site.getsitepackages()))))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PYTHONNOUSERSITE"] = "1"
    installed = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
         "--no-index", "--quiet", str(wheel)],
        capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert installed.returncode == 0, installed.stderr[-2000:]

    def run(*args: str, tool: Path = venv / "bin" / "hmepol") -> subprocess.CompletedProcess:
        proc = subprocess.run(
            [str(tool), *args], cwd=empty, capture_output=True, text=True, timeout=300, env=env
        )
        assert proc.returncode == 0, f"{args}:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
        return proc

    where = run(
        "-c",
        textwrap.dedent(
            """
            import importlib.metadata, importlib.resources, sys
            import hmepol_cli, hydra_plugins.hmepol_population_launcher as launcher
            from hmepol_cli.cli import main
            main(["--version"])
            print(hmepol_cli.__file__)
            print(launcher.__file__)
            print(importlib.resources.files("hmepol_cli.conf").joinpath("config.yaml"))
            print(importlib.metadata.distribution("hmepol").read_text("direct_url.json"))
            print("\\n".join(sys.path))
            """
        ),
        tool=python,
    ).stdout.splitlines()
    printed, package, launcher, conf, direct_url, *path = where
    assert printed == f"hmepol {version}"  # --version of the wheel's hmepol_cli
    for inside in (package, launcher, conf):
        assert Path(inside).resolve().is_relative_to(site_dir.resolve()), inside
    assert Path(conf).is_file(), conf
    assert '"editable": true' not in direct_url, direct_url
    # Nothing else on the path holds a hmepol_cli: the checkout is not seen, however it got in.
    sources = [p for p in path if (Path(p or empty) / "hmepol_cli").exists()]
    assert [Path(p).resolve() for p in sources] == [site_dir.resolve()], path

    helped = run("train", "--help").stdout
    assert "== Config groups" in helped and "env: " in helped and "slope" in helped

    run("train", *WHEEL_RUN, "hydra.run.dir=runs/one")
    assert len((empty / "runs" / "one" / "epochs.csv").read_text().splitlines()) == 2
    run("report", "runs", "--out", "report")
    assert any((empty / "report" / "figures").glob("*.png")), os.listdir(empty / "report")
    assert "| slope |" in (empty / "report" / "summary.md").read_text()


@pytest.mark.slow  # a fresh interpreter (or several): make test runs it, make test-fast does not
def test_importing_the_cli_changes_no_environment_variable():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = "import os, hmepol_cli.cli; print(os.environ.get('OMP_WAIT_POLICY'))"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["None"]


@pytest.mark.slow  # a fresh interpreter (or several): make test runs it, make test-fast does not
def test_the_command_sets_the_openmp_wait_policy_before_torch_loads():
    """The OpenMP runtime reads OMP_WAIT_POLICY once, as torch loads it: the entry point sets it
    first (unless the user did), and `hmepol` is that entry point."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = textwrap.dedent(
        """
        import builtins, os, sys
        seen, real = [], builtins.__import__
        def spy(name, *args, **kwargs):
            if name == "torch" and "torch" not in sys.modules and not seen:
                seen.append(os.environ.get("OMP_WAIT_POLICY"))
            return real(name, *args, **kwargs)
        builtins.__import__ = spy
        sys.argv = ["hmepol", "--version"]
        from hmepol_cli.__main__ import main
        main()
        print(seen)
        """
    )
    for preset, expected in ((None, "PASSIVE"), ("ACTIVE", "ACTIVE")):
        run_env = env if preset is None else {**env, "OMP_WAIT_POLICY": preset}
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, env=run_env, timeout=120
        )
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.splitlines()[-1] == f"[{expected!r}]"
    (script,) = [e for e in importlib.metadata.entry_points(group="console_scripts", name="hmepol")]
    assert script.value == "hmepol_cli.__main__:main"
