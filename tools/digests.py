"""Digests of a few tiny epochs of every world x algorithm x policy, and of a fine-tuning run.

A refactoring that must not change any number is checked by running this at the commit before
and the commit after and comparing the two outputs line by line::

    python -m tools.digests > before.txt    # at the old commit (git worktree)
    python -m tools.digests > after.txt
    diff before.txt after.txt

Each line is ``<case> <sha256 of the numbers>``: every column of epochs.csv and batches.csv but
the wall-clock ones, and the final policy weights, at full precision. Digests are equal only on
the same machine and torch build (the same seed and config give the same numbers there).
``extra`` overrides apply to every case (e.g. ``env.edge=mirror``); ``--only gym`` runs the
cases whose label holds "gym". ``--blas torch,openblas`` runs every case through each library
of the float32 products in turn, a baseline per library (its lines end in ``[torch]``,
``[openblas]``): the two libraries round differently, so only a library's own lines compare.
Run it from the repository root (the Gymnasium cases import tests/gym_toy.py).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import sys
import tempfile
from pathlib import Path

import pandas as pd
import torch

TIME_COLUMNS = ("seconds", "collect_seconds", "neighbours_seconds", "update_seconds", "wall_time")
TINY = [
    "algo.trajectories=10",
    "algo.horizon=40",
    "algo.batch_size=5",
    "algo.max_off_iters=5",
    "algo.lr=1e-3",
    "algo.kl_threshold=0.5",
    "estimator.k=5",
    "policy.hidden=[16,16]",
    "policy.encoder_hidden=[16,16]",
    "policy.history_size=6",
    "eval.trajectories=4",
    "eval.horizon=20",
    "progress=false",
    "epochs=3",
]
WORLDS = ("slope", "corridor", "multigrid")
ALGOS = ("mepol", "alphamepol", "hmepol")
POLICIES = ("markov", "recursive", "twohead", "gru", "lstm")
# A large step and a tight region: first steps and later steps are rejected (backtracking).
STRESS = ["algo.lr=1e-2", "algo.kl_threshold=0.05"]


def _compose(overrides: list[str]):
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from hmepol_cli.cli import setup

    setup()  # schema and resolvers

    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    GlobalHydra.instance().clear()
    return cfg


DROPPED: list[str] = []  # --drop: columns left out (to compare with a commit that lacked them)


def _numbers(frame: pd.DataFrame) -> bytes:
    gone = [*TIME_COLUMNS, *DROPPED]
    kept = frame.drop(columns=[c for c in gone if c in frame.columns])
    buffer = io.StringIO()
    kept.to_csv(buffer, index=False, float_format="%.17g")
    return buffer.getvalue().encode()


def train_digest(overrides: list[str], workdir: Path, seeds: tuple[int, ...] = (0,)) -> str:
    """One run, or a population of ``seeds`` (its members' files in seed order)."""
    from hmepol_cli.trainer import Trainer

    cfgs = [_compose([*TINY, *overrides, f"seed={s}"]) for s in seeds]
    run_dirs = [workdir / f"seed{s}" for s in seeds]
    trainer = Trainer(cfgs, run_dirs)
    trainer.train()
    digest = hashlib.sha256()
    for run_dir in run_dirs:
        for name in ("epochs.csv", "batches.csv"):
            digest.update(_numbers(pd.read_csv(run_dir / name)))
    for name, value in sorted(trainer.population.params.items()):
        digest.update(name.encode())
        digest.update(value.detach().double().cpu().numpy().tobytes())
    return digest.hexdigest()[:16]


def finetune_digest(init: Path | None, workdir: Path, extra: list[str]) -> str:
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from hmepol_cli.finetune import finetune

    overrides = [
        f"init={init if init is not None else 'none'}",
        "epochs=3",
        "episodes=4",
        "horizon=40",
        "targets=1",
        "config=0",
        "fisher_fraction=0.5",
        "progress=false",
        f"output_dir={workdir / 'finetune'}",
        *(
            [o for o in extra if o.startswith("blas=")]  # a pre-trained policy keeps its own
            if init is not None
            else ["policy.hidden=[16,16]", *extra]
        ),
    ]
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(config_name="finetune", overrides=overrides)
    GlobalHydra.instance().clear()
    out = finetune(cfg)
    rows = pd.read_csv(out / "finetune.csv")
    return hashlib.sha256(_numbers(rows.drop(columns=["init"]))).hexdigest()[:16]


# Gymnasium worlds (tests/gym_toy.py's walker): episodes that end early (|x| >= wall), whose
# particles after the end take no part in the estimate, and episodes that never end.
GYM = ["env=gym", "env.id=tests.gym_toy:hmepol-test/Walk-v0", "env.features=[0]"]
GYM_CASES = {
    "ends": "env.configs=[{wall:0.3},{wall:0.6,drift:0.05}]",
    "never-ends": "env.configs=[{drift:0.0},{drift:0.05}]",
}


def cases(quick: bool, extra: list[str]) -> list[tuple[str, list[str], tuple[int, ...]]]:
    """Every case: (label, overrides, seeds)."""
    out = []
    for world in WORLDS:
        for algo in ALGOS:
            for policy in POLICIES if not quick else ("markov", "recursive"):
                overrides = [f"env={world}", f"algo={algo}", f"policy={policy}", *extra]
                out.append((f"train {world} {algo} {policy}", overrides, (0,)))
    for world in WORLDS:
        for algo in ALGOS:
            for policy in ("markov", "recursive"):
                overrides = [f"env={world}", f"algo={algo}", f"policy={policy}", *STRESS, *extra]
                out.append((f"stress {world} {algo} {policy}", overrides, (0,)))
    for name, configs in GYM_CASES.items():
        for algo in ("mepol", "hmepol"):
            overrides = [*GYM, configs, f"algo={algo}", "estimator.k=3", *extra]
            out.append((f"gym {name} {algo}", overrides, (0,)))
    overrides = ["env=slope", "algo=hmepol", *STRESS, *extra]
    out.append(("population slope hmepol recursive", overrides, (0, 1, 2)))
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("extra", nargs="*", help="overrides applied to every training case")
    parser.add_argument("--quick", action="store_true", help="one policy per algorithm")
    parser.add_argument("--drop", default="", help="columns to leave out, comma-separated")
    parser.add_argument("--only", default="", help="only the cases whose label holds this text")
    parser.add_argument(
        "--blas",
        default="torch",
        help="libraries of the float32 products, comma-separated (torch, openblas): each case "
        "once per library, its lines labelled with it when there are several",
    )
    ns = parser.parse_args(argv)
    libraries = [b for b in ns.blas.split(",") if b]
    if not libraries or any(b not in ("torch", "openblas") for b in libraries):
        parser.error(f"--blas {ns.blas!r}: give torch, openblas or torch,openblas")
    DROPPED.extend(c for c in ns.drop.split(",") if c)
    torch.set_num_threads(1)
    for library in libraries:
        tag = f" [{library}]" if len(libraries) > 1 else ""
        _digests(ns, [*ns.extra, f"blas={library}"], tag)


def _digests(ns: argparse.Namespace, extra: list[str], tag: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for i, (label, overrides, seeds) in enumerate(cases(ns.quick, extra)):
            if ns.only in label:
                digest = train_digest(overrides, root / f"case{i}", seeds)
                print(f"{label}{tag} {digest}", flush=True)
        init = root / "case0" / "seed0"  # slope, mepol, markov
        if ns.only in "finetune pretrained":
            if not init.exists():
                train_digest(cases(True, extra)[0][1], root / "case0")
            digest = finetune_digest(init, root / "ft0", extra)
            print(f"finetune pretrained{tag} {digest}", flush=True)
        if ns.only in "finetune scratch":
            digest = finetune_digest(None, root / "ft1", extra[-1:])
            print(f"finetune scratch{tag} {digest}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
