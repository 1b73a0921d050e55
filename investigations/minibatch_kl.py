"""The mini-batch KL (eq. 2.8) as this project computes it and as the alpha-Mepol code does, on
identical particles.

Ours (``estimators.kl_divergence``, ``Surrogate``): the importance weights are normalised
within each mini-batch of B trajectories, eq. 2.8 is computed per mini-batch with its own
neighbour sets, clamped at 0, and averaged over the mini-batches.

The public alpha-Mepol code (``compute_kl`` in src/algorithms/alphamepol.py and its call in the
off-policy loop) normalises the weights over all N trajectories and sums them over each
particle's neighbours with the neighbour indices of its mini-batch's own search (0 .. B T - 1),
reshaped to one (N T, k + 1) table as if they were indices into all N T particles: every
mini-batch's neighbourhoods read the weights of the *first* mini-batch's particles. It then
averages log(k / (N T W_i)) over all N T particles (eps = 0) and clamps the mean at 0. We also
show what that code evidently means, the same global normalisation with each mini-batch's
indices shifted to its own particles ("reference, global indices").

The particles are one rollout of the quick preset (40 trajectories, B = 5, T = 400, k = 30;
alpha-Mepol, the multigrid or slope world) from our initial policy. The sampling policy is
compared with the policy after one epoch of our off-policy loop (the preset's learning rate and
30 steps, every one inside the KL threshold of 15), and, for larger KLs, after a few Adam steps
at 10 and 100 times that learning rate, all on that same rollout and neighbour sets::

    python -m investigations.minibatch_kl                   # multigrid and slope, seeds 0 and 1
    python -m investigations.minibatch_kl --worlds multigrid --seeds 0
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import math  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402
from hydra import compose, initialize_config_module  # noqa: E402
from hydra.core.global_hydra import GlobalHydra  # noqa: E402

from benchmarks.measure import cpu_name  # noqa: E402
from hmepol_cli import estimators, mepol  # noqa: E402
from hmepol_cli.cli import setup  # noqa: E402
from hmepol_cli.config import validate  # noqa: E402
from hmepol_cli.rollout import collect, draw_configurations  # noqa: E402
from hmepol_cli.surrogate import Surrogate
from hmepol_cli.trainer import Trainer  # noqa: E402

setup()  # the config schema and resolvers, for composing


# ------------------------------------------------------------------ the three KLs
def kl_ours(log_ratios: torch.Tensor, indices: torch.Tensor, batch_size: int) -> float:
    """Eq. 2.8 per mini-batch (weights normalised in it), clamped at 0, averaged.
    log_ratios (N, T), indices (M, P, k) -> nats"""
    weights = estimators.importance_weights(log_ratios, batch_size)  # (M, P)
    neighbours = estimators.Neighbours(indices, torch.ones(indices.shape[:2]), dim=2)
    return float(estimators.kl_divergence(weights, neighbours).mean())


def kl_reference(
    log_ratios: torch.Tensor, indices: torch.Tensor, global_indices: bool = False
) -> tuple[float, float]:
    """The alpha-Mepol code's KL: weights normalised over all N T particles, neighbourhood sums
    with each mini-batch's local indices read as global ones (``global_indices``: shifted to
    the mini-batch's own particles), the mean of log(k / (N T W_i)) over all particles.
    -> (clamped at 0 as the code does, unclamped)"""
    m, p, k = indices.shape
    weights = torch.softmax(torch.cumsum(log_ratios, dim=1).flatten(), dim=0)  # (N T,)
    rows = indices + (torch.arange(m)[:, None, None] * p if global_indices else 0)
    w_sum = weights[rows.reshape(-1, k)].sum(dim=1)  # (N T,)
    total = weights.numel()
    kl = float(torch.log(k / (total * w_sum)).mean())
    return max(0.0, kl), kl


# ------------------------------------------------------------------ one epoch of ours
def preset(world: str, seed: int) -> object:
    experiment = {"multigrid": "quick_multigrid", "slope": "quick_slope"}[world]
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[f"experiment={experiment}", "algo=alphamepol", "progress=false",
                       f"seed={seed}"],
        )  # fmt: skip
    GlobalHydra.instance().clear()
    validate(cfg)
    return cfg


def log_ratios_of(surrogate: Surrogate) -> tuple[torch.Tensor, float]:
    """log pi'(a|h) - log pi(a|h) of every step at the current parameters, (N, T) float64,
    and the KL our Surrogate itself computes there (its trust region's)."""
    with torch.no_grad():
        estimate = surrogate(torch.arange(1))
    ratios = (estimate.likelihoods - surrogate.behaviour)[0].double()
    return ratios, float(estimate.kl_one_step[0])


def adam_steps(trainer: Trainer, surrogate: Surrogate, lr: float, steps: int) -> None:
    """``steps`` Adam steps of the objective's gradient from the current parameters, as the
    off-policy loop takes them when every step is accepted."""
    params = trainer.population.params
    start = surrogate(torch.arange(1))
    grads = mepol._gradients(start.objective, params)
    rate = torch.full((1,), lr, dtype=torch.float64)
    on = torch.ones(1, dtype=torch.bool)
    for _ in range(steps):
        trainer.optimizer.step(grads, rate, on)
        grads = mepol._gradients(surrogate(torch.arange(1)).objective, params)


def measure(world: str, seed: int, work: Path, big_steps: int) -> list[dict]:
    cfg = preset(world, seed)
    trainer = Trainer(cfg, work / f"{world}-{seed}")
    s, a = trainer.settings, cfg.algo
    generator = trainer.members[0].generator
    configurations = draw_configurations(trainer.world, s.trajectories, s.batch_size, generator)
    rollout = collect(trainer.world, trainer.population, None, configurations[None], s.horizon,
                      [generator])  # fmt: skip
    features = trainer.world.entropy_features(rollout.particles)
    particles = estimators.particles_by_batch(features.flatten(0, 1), s.batch_size)
    neighbours = s.estimator.search(particles)
    members = torch.tensor([0])
    initial_policy = {k: v.clone() for k, v in trainer.population.member_state_dict(0).items()}
    initial_adam = trainer.optimizer.member_state_dict(0)
    rows = []

    def row(label: str, surrogate: Surrogate) -> None:
        ratios, surrogate_kl = log_ratios_of(surrogate)
        ours = kl_ours(ratios, neighbours.indices, s.batch_size)
        # Our formula here is the Surrogate's own: the same weights, neighbours and clamp.
        assert math.isclose(ours, surrogate_kl, rel_tol=1e-4, abs_tol=1e-7), (ours, surrogate_kl)
        ref, ref_raw = kl_reference(ratios, neighbours.indices)
        fixed, fixed_raw = kl_reference(ratios, neighbours.indices, global_indices=True)
        rows.append(
            {
                "world": f"{world}, seed {seed} (configs "
                f"{', '.join(map(str, sorted(set(configurations.tolist()))))})",
                "policy": label,
                "ours": ours,
                "reference": ref,
                "reference_raw": ref_raw,
                "global": fixed,
                "global_raw": fixed_raw,
                "max_log_ratio": float(ratios.cumsum(dim=1).abs().max()),
            }
        )

    # One epoch of our off-policy loop (the trainer's): the preset's lr, up to 30 steps.
    surrogate = Surrogate(trainer.population, rollout, neighbours, members, s)
    result = mepol.off_policy_loop(trainer.population, trainer.optimizer, surrogate, members, s)[0]
    row(f"one epoch: {result.off_iters} steps of lr {a.lr:g}", surrogate)
    # Larger steps from the same initial policy, on the same particles.
    for factor in (10, 100):
        trainer.population.load_member_state_dict(0, initial_policy)
        trainer.optimizer.load_member_state_dict(0, initial_adam)
        surrogate = Surrogate(trainer.population, rollout, neighbours, members, s)
        adam_steps(trainer, surrogate, factor * float(a.lr), big_steps)
        row(f"{big_steps} steps of lr {factor * float(a.lr):g}", surrogate)
    return rows


def markdown(rows: list[dict], seconds: float) -> str:
    lines = [
        "Identical particles: one rollout of the quick preset (alpha-Mepol, N = 40 trajectories, "
        "B = 5, T = 400, k = 30; 8 mini-batches of 2,000 particles) from the initial policy; the "
        "sampling policy against the policy after the steps named, on that rollout. "
        f"Machine: {cpu_name()}, {torch.get_num_threads()} thread(s), {seconds:.0f} s.",
        "",
        "| world | target policy | ours: per mini-batch, clamped, averaged | alpha-Mepol code "
        "(unclamped) | ratio code / ours | code - ours | reference, global indices "
        "(unclamped) | ratio / ours |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ratio = r["reference"] / r["ours"] if r["ours"] > 0 else math.nan
        ratio_g = r["global"] / r["ours"] if r["ours"] > 0 else math.nan
        lines.append(
            f"| {r['world']} | {r['policy']} | {r['ours']:.4g} | {r['reference']:.4g} "
            f"({r['reference_raw']:.4g}) | {ratio:.3f} | {r['reference'] - r['ours']:+.3g} | "
            f"{r['global']:.4g} ({r['global_raw']:.4g}) | {ratio_g:.3f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--worlds", nargs="+", default=["multigrid", "slope"], choices=["multigrid", "slope"]
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--steps", type=int, default=5, help="Adam steps at the larger rates")
    parser.add_argument("--threads", type=int, default=1)
    ns = parser.parse_args(argv)
    torch.set_num_threads(ns.threads)
    start = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for world in ns.worlds:
            for seed in ns.seeds:
                rows += measure(world, seed, Path(work), ns.steps)
    print(markdown(rows, time.perf_counter() - start))


if __name__ == "__main__":
    main()
