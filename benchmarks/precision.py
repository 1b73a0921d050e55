"""What a lower precision changes in one off-policy update, against float64 on identical particles.

For each thesis preset (tables A.1-A.2) and each precision: one float64 rollout of the initial
policy (or of a *saturated* one, the kind training ends with: the mean's output layer x 300 and
log-std -2.5) is shared by every precision, with its float64 neighbour sets, so that only the
arithmetic differs. Each precision starts from the same weights (cast) and reports, against
float64: the per-step log-likelihoods (largest error), the KL at theta' = theta (must be 0), the
IW entropy there (eq. 2.7), the gradient of the objective (cosine, relative norm of the
difference), and, after one Adam step of the preset's learning rate taken in that precision, the
KL (eq. 2.8) and the IW entropy (relative error)::

    python -m benchmarks.precision                       # slope and corridor, Mepol and HMepol
    python -m benchmarks.precision --trajectories 20     # a quick look

Writes ``precision.json`` and ``precision.md`` to ``--out``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from benchmarks.measure import cpu_name  # noqa: E402
from benchmarks.run import thesis_config  # noqa: E402
from hmepol_cli import estimators, mepol  # noqa: E402
from hmepol_cli.rollout import Rollout, collect, draw_configurations  # noqa: E402
from hmepol_cli.run import load_checkpoint, resolve_checkpoint  # noqa: E402
from hmepol_cli.surrogate import Surrogate  # noqa: E402
from hmepol_cli.trainer import Trainer  # noqa: E402

PRESETS = ("slope_mepol", "slope_hmepol", "corridor_mepol", "corridor_hmepol")
# precision name -> the overrides that select it
PRECISIONS: dict[str, list[str]] = {
    "float64": ["precision=float64"],
    "float32": ["precision=float32"],
    "bf16": ["precision=bf16"],
}


def saturate(trainer: Trainer) -> None:
    """Make member 0 look like a late policy: the mean's output layer x 300, log-std -2.5."""
    params = trainer.population.params
    mean_layer = [
        k
        for k, v in params.items()
        if k.endswith("weight") and v.shape[1] == params["log_std"].shape[1]
    ][-1]
    with torch.no_grad():
        params[mean_layer].mul_(300.0)
        params[mean_layer.replace("weight", "bias")].mul_(300.0)
        params["log_std"].fill_(-2.5)


def cast(rollout: Rollout, dtype: torch.dtype) -> Rollout:
    return dataclasses.replace(
        rollout,
        states=rollout.states.to(dtype),
        actions=rollout.actions.to(dtype),
        histories=rollout.histories.to(dtype),
        log_probs=rollout.log_probs.to(dtype),
        means=rollout.means.to(dtype),
        log_std=rollout.log_std.to(dtype),
    )


def one_update(trainer: Trainer, rollout: Rollout, neighbours) -> dict:
    """theta' = theta, then one Adam step, on given particles. -> the numbers compared."""
    members = torch.tensor([0])
    s = trainer.settings
    surrogate = Surrogate(trainer.population, rollout, neighbours, members, s)
    rows = torch.arange(1)
    start = surrogate(rows)
    entropies, kl, target = start.entropies, start.kl, start.likelihoods
    grads = mepol._gradients(start.objective, trainer.population.params)
    flat = torch.cat([g[0].flatten().double() for g in grads.values()])
    lr = torch.full((1,), s.lr, dtype=torch.float64)
    trainer.optimizer.step(grads, lr, torch.ones(1, dtype=torch.bool))
    with torch.no_grad():
        after = surrogate(rows)
        stepped, kl_step = after.entropies, after.kl
    return {
        "log_probs": target[0].double(),
        "kl_start": float(kl[0].detach()),
        "iw_entropy_start": float(entropies.mean()),
        "gradient": flat,
        "kl_step": float(kl_step[0]),
        "iw_entropy_step": float(stepped.mean()),
    }


def validate_preset(preset: str, state: str, args: argparse.Namespace, work: Path) -> list[dict]:
    """``state``: initial, saturated, or a trained policy: ``<run dir>@<epochs>`` (a kept
    checkpoint of a run of this preset) or a run directory."""
    env, algo = preset.split("_")
    base = [f"algo.trajectories={args.trajectories}", *args.override]
    trained = None
    if state not in ("initial", "saturated"):
        trained = load_checkpoint(resolve_checkpoint(state)[1])["policy"]

    def trainer(name: str) -> Trainer:  # the same seed: the same initial weights, cast
        cfg = thesis_config(env, algo, [*base, *PRECISIONS[name]], iters=1)
        made = Trainer(cfg, work / f"{preset}-{len(state)}-{name}")
        if state == "saturated":
            saturate(made)
        if trained is not None:
            made.population.load_member_state_dict(0, trained)
        return made

    t64 = trainer("float64")
    a, k = t64.cfg.algo, t64.cfg.estimator.k
    generator = t64.members[0].generator
    configurations = draw_configurations(t64.world, a.trajectories, a.batch_size, generator)[None]
    r64 = collect(t64.world, t64.population, None, configurations, a.horizon, [generator])
    particles = estimators.particles_by_batch(r64.particles[0], a.batch_size)
    n64 = estimators.nearest_neighbours(particles, k, "kdtree")
    h64 = estimators.knn_entropy(n64)
    reference = one_update(t64, r64, n64)
    rows = []
    for name in PRECISIONS:
        t = trainer(name)
        dtype = t.population.dtype
        shared = dataclasses.replace(n64, radius=n64.radius.to(dtype))
        # The on-policy entropy (eq. 2.6) with the neighbours searched in this precision.
        own = estimators.nearest_neighbours(particles.to(dtype), k, "kdtree")
        entropy_error = float((estimators.knn_entropy(own).double() - h64).abs().max())
        got = one_update(t, cast(r64, dtype), shared)
        g, g64 = got["gradient"], reference["gradient"]
        error = {key: abs(got[key] - reference[key]) for key in ("iw_entropy_start", "kl_step")}
        error["iw_entropy_step"] = abs(got["iw_entropy_step"] - reference["iw_entropy_step"])
        rows.append(
            {
                "preset": preset,
                "policy": state if trained is None else f"trained ({Path(state).name[-24:]})",
                "precision": name,
                "log_prob_max_abs_error": float(
                    (got["log_probs"] - reference["log_probs"]).abs().max()
                ),
                "entropy_abs_error": entropy_error,
                "kl_at_start": got["kl_start"],
                "iw_entropy_start_abs_error": error["iw_entropy_start"],
                "gradient_one_minus_cosine": 1.0 - float(torch.cosine_similarity(g, g64, dim=0)),
                "gradient_relative_error": float((g - g64).norm() / g64.norm()),
                "kl_step": got["kl_step"],
                "kl_step_relative_error": error["kl_step"] / reference["kl_step"],
                "iw_entropy_step_abs_error": error["iw_entropy_step"],
            }
        )
    return rows


def markdown(rows: list[dict], args: argparse.Namespace) -> str:
    lines = [
        f"Machine: {cpu_name()}, torch {torch.__version__}.",
        "",
        f"Identical particles: one float64 rollout per preset and policy state, "
        f"{args.trajectories} trajectories x 400 steps; float64 neighbour sets shared.",
        "",
        "| preset | policy | precision | abs error kNN entropy (own neighbours) "
        "| max abs error log pi | KL at theta' = theta | "
        "abs error IW entropy | 1 - gradient cosine | gradient rel. error | KL after one step "
        "(rel. error) | abs error IW entropy after one step |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['preset']} | {r['policy']} | {r['precision']} | {r['entropy_abs_error']:.2g} "
            f"| {r['log_prob_max_abs_error']:.2g} | {r['kl_at_start']:.2g} "
            f"| {r['iw_entropy_start_abs_error']:.2g} | {r['gradient_one_minus_cosine']:.2g} "
            f"| {r['gradient_relative_error']:.2g} "
            f"| {r['kl_step']:.4g} ({r['kl_step_relative_error']:.2g}) "
            f"| {r['iw_entropy_step_abs_error']:.2g} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=PRESETS)
    parser.add_argument(
        "--states",
        nargs="+",
        default=["initial", "saturated"],
        help="initial | saturated | a trained policy of the preset: <run dir>[@<epochs>]",
    )
    parser.add_argument("--trajectories", type=int, default=100)
    parser.add_argument("--out", type=Path, default=Path("outputs/bench"))
    parser.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides")
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for preset in args.presets:
            for state in args.states:
                rows.extend(validate_preset(preset, state, args, Path(tmp)))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "precision.json").write_text(json.dumps(rows, indent=2) + "\n")
    text = markdown(rows, args)
    (args.out / "precision.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
