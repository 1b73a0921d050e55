"""`make bench`: thesis-scale speed of hmepol on this machine, each figure beside a baseline.

Settings are the shipped thesis presets (tables A.1-A.2): slope, 200 trajectories x 400 steps,
B = 5, k = 30; corridor, 100 x 400, B = 1, k = 30; Mepol (Markovian policy) and HMepol (recursive
policy, bptt = 1). For each: environment steps per second of the batched collection against a
plain per-step Python loop over single environments; neighbour search per epoch (kdtree and
torch) against a brute-force search; one whole epoch with 30 off-policy iterations, and from it
the seconds per off-policy iteration against the machine's measured matmul throughput. Then a
float32 against float64 check. Writes ``bench.json`` and ``bench.md`` to ``--out``.

Other processes may share the machine: each ratio compares figures taken in the same run, short
timings keep the fastest of their repetitions, and the report gives the load average.
"""

from __future__ import annotations

import os

# OpenMP threads that spin while they wait hold on to a core that another process's thread, or
# their own partner, needs: on a shared machine sleeping waits degrade gracefully. Set before
# torch loads OpenMP; an explicit setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402
from hydra import compose, initialize_config_module  # noqa: E402
from hydra.core.global_hydra import GlobalHydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from benchmarks import baseline  # noqa: E402
from benchmarks.measure import (  # noqa: E402
    best_rates,
    best_time,
    brute_force_seconds,
    cpu_name,
    forward_flops,
    layer_matmul_flops,
)
from benchmarks.results import OFF_ITERS, Row, markdown, targets  # noqa: E402
from hmepol_cli import blas, estimators, mepol  # noqa: E402
from hmepol_cli.cli import setup  # noqa: E402
from hmepol_cli.config import validate  # noqa: E402
from hmepol_cli.envs import make_world  # noqa: E402
from hmepol_cli.precision import bf16_runs_fast_here  # noqa: E402
from hmepol_cli.rollout import collect, draw_configurations  # noqa: E402
from hmepol_cli.seeding import keep_freed_memory  # noqa: E402
from hmepol_cli.surrogate import Surrogate  # noqa: E402
from hmepol_cli.trainer import Trainer  # noqa: E402

setup()  # the config schema and resolvers, for composing

ENVS = ("slope", "corridor")
ALGOS = ("mepol", "hmepol")


def thesis_config(env: str, algo: str, overrides: list[str], iters: int = OFF_ITERS) -> DictConfig:
    """The shipped preset ``{env}_{algo}``, with ``iters`` off-policy iterations forced to run."""
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                f"experiment={env}_{algo}",
                "progress=false",
                "algo.kl_threshold=1e9",  # a trust region no step leaves
                f"algo.max_off_iters={iters}",
                *overrides,
            ],
        )
    GlobalHydra.instance().clear()
    validate(cfg)
    return cfg


def bench_setting(env: str, algo: str, args: argparse.Namespace, work: Path) -> Row:
    overrides = [f"blas={args.blas}", *args.override]
    trainer = Trainer(thesis_config(env, algo, overrides), work / f"{env}-{algo}")
    print(f"{env} {algo}: {trainer.blas_reason}", flush=True)
    a, k = trainer.cfg.algo, trainer.cfg.estimator.k
    policy, generator = trainer.population.member(0), trainer.members[0].generator
    row = Row(env, algo, a.trajectories * a.horizon, forward_flops(policy))

    configurations = draw_configurations(trainer.world, a.trajectories, a.batch_size, generator)[
        None
    ]
    rollouts = []

    def collection() -> None:
        rollouts.append(
            collect(trainer.world, trainer.population, None, configurations, a.horizon, [generator])
        )

    # The plain loop and the batched collection take turns, so that both see the same load.
    for _ in range(args.repeats):
        plain, row.plain_steps_timed = baseline.steps_per_second(
            trainer.world, policy, a.horizon, args.plain_trajectories
        )
        row.plain_steps_per_s = max(row.plain_steps_per_s, plain)
        row.steps_per_s = max(row.steps_per_s, row.particles / best_time(collection, 1))

    particles = estimators.particles_by_batch(rollouts[-1].particles[0], a.batch_size)
    search = estimators.nearest_neighbours
    row.kdtree_s = best_time(lambda: search(particles, k, "kdtree"), args.repeats)
    row.torch_s = best_time(lambda: search(particles, k, "torch"), args.repeats)
    row.brute_force_s, row.brute_force_batches_timed = brute_force_seconds(
        particles, k, args.brute_force_batches
    )

    before = best_rates(row.particles)
    (stats,) = trainer.epoch()
    row.layer_rates, row.square_rates = best_rates(row.particles, before)
    row.blas = trainer.blas
    row.layer_matmul_flops = row.layer_rates[row.blas]
    row.square_matmul_flops = row.square_rates[row.blas]
    row.collect_s, row.neighbours_s = stats.seconds["collect"], stats.seconds["neighbours"]
    row.update_s, row.epoch_s = stats.seconds["update"], stats.seconds["epoch"]
    row.off_iters = stats.update.off_iters
    if "bf16" in args.precisions:
        cfg = thesis_config(env, algo, [*overrides, "precision=bf16"])
        (lowered,) = Trainer(cfg, work / f"{env}-{algo}-bf16").epoch()
        row.bf16_epoch_s, row.bf16_update_s = lowered.seconds["epoch"], lowered.seconds["update"]
        row.bf16_off_iters = lowered.update.off_iters
        row.bf16_layer_matmul_flops = layer_matmul_flops(row.particles, dtype=torch.bfloat16)
    return row


def off_policy_update(trainer: Trainer, rollout, neighbours) -> list:
    """The off-policy loop of a one-member trainer on given particles and neighbours."""
    first = torch.tensor([0])
    surrogate = Surrogate(trainer.population, rollout, neighbours, first, trainer.settings)
    return mepol.off_policy_loop(
        trainer.population, trainer.optimizer, surrogate, first, trainer.settings
    )


def dtype_check(args: argparse.Namespace, work: Path) -> dict:
    """float32 against float64 on the same particles and the same initial weights.

    Reduced scale (slope HMepol, 50 trajectories, 10 off-policy iterations). One float64 rollout
    is shared (sampling draws different random numbers in each dtype). Its particles' kNN
    entropies in both dtypes; then the trust-region update in both dtypes, first each with the
    neighbours searched on its own particles, then both with the float64 neighbour sets (which
    isolates arithmetic precision from tie-breaking between coincident particles).
    """
    small = ["algo.trajectories=50", "algo.max_off_iters=10", *args.override]

    def trainer(dtype: str) -> Trainer:  # same seed: same initial weights in either dtype
        return Trainer(
            thesis_config("slope", "hmepol", [*small, f"precision={dtype}"]), work / dtype
        )

    t64 = trainer("float64")
    a, k = t64.cfg.algo, t64.cfg.estimator.k
    generator = t64.members[0].generator
    configurations = draw_configurations(t64.world, a.trajectories, a.batch_size, generator)[None]
    r64 = collect(t64.world, t64.population, None, configurations, a.horizon, [generator])
    r32 = dataclasses.replace(
        r64,
        states=r64.states.float(),
        actions=r64.actions.float(),
        histories=r64.histories.float(),
        log_probs=r64.log_probs.float(),
    )
    n64, n32 = (
        estimators.nearest_neighbours(
            estimators.particles_by_batch(r.particles[0], a.batch_size), k, "kdtree"
        )
        for r in (r64, r32)
    )
    shared = dataclasses.replace(n64, radius=n64.radius.float())
    h64, h32 = estimators.knn_entropy(n64), estimators.knn_entropy(n32)
    (u64,) = off_policy_update(t64, r64, n64)
    (u32,) = off_policy_update(trainer("float32"), r32, n32)
    (u32_shared,) = off_policy_update(trainer("float32"), r32, shared)
    o64, o32, o32_shared = (float(u.entropies.mean()) for u in (u64, u32, u32_shared))
    return {
        "setting": f"slope HMepol, {a.trajectories} trajectories x {a.horizon} steps, "
        f"B={a.batch_size}, k={k}, {u64.off_iters} off-policy iterations",
        "entropy_max_abs_diff": float((h64 - h32.double()).abs().max()),
        "neighbour_index_mismatch": float((n64.indices != n32.indices).double().mean()),
        "objective_start": float(h64.mean()),
        "objective_float64": o64,
        "objective_float32": o32,
        "objective_abs_diff": abs(o64 - o32),
        "objective_float32_shared_neighbours": o32_shared,
        "objective_abs_diff_shared_neighbours": abs(o64 - o32_shared),
        "kl_float64": u64.kl,
        "kl_float32": u32.kl,
        "kl_float32_shared_neighbours": u32_shared.kl,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.run", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/bench"))
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--envs", nargs="+", default=list(ENVS), choices=ENVS)
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), choices=ALGOS)
    parser.add_argument("--repeats", type=int, default=3, help="repetitions of short timings")
    parser.add_argument(
        "--plain-trajectories", type=int, default=4, help="trajectories the plain loop runs"
    )
    parser.add_argument(
        "--brute-force-batches", type=int, default=10, help="mini-batches brute force searches"
    )
    parser.add_argument(
        "--override", nargs="*", default=[], help="extra Hydra overrides (smoke runs)"
    )
    parser.add_argument(
        "--blas",
        default="auto",
        choices=("auto", "torch", "openblas"),
        help="the library of the float32 layer products (default: auto, as a run chooses)",
    )
    parser.add_argument(
        "--precisions",
        nargs="+",
        default=None,
        choices=("float32", "bf16"),
        help="default: float32, and bf16 where the CPU has bfloat16 units (asked for by name, "
        "bf16 is measured anyway: the slow path's cost)",
    )
    args = parser.parse_args(argv)
    if args.precisions is None:
        args.precisions = ["float32", "bf16"] if bf16_runs_fast_here("cpu") else ["float32"]
        if "bf16" not in args.precisions:
            print(f"bf16 not measured: {cpu_name()} (--precisions float32 bf16 measures it)")
    if args.threads:
        torch.set_num_threads(args.threads)
    blas.limit_openblas_threads(torch.get_num_threads())  # both libraries at torch's threads
    start, load_before = time.perf_counter(), os.getloadavg()
    for env in args.envs:  # the plain loop must simulate the same walls as the batched world
        world = make_world(thesis_config(env, "mepol", args.override).env)
        if baseline.check_same_physics(world) > 1e-12:  # the slide rounds in its own order
            raise SystemExit(f"the plain loop's {env} physics differ from the batched world's")

    keep_freed_memory()  # the trainer's allocator settings, for the matmul references too
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for env in args.envs:
            for algo in args.algos:
                rows.append(bench_setting(env, algo, args, Path(tmp)))
                print(f"{rows[-1].label}: epoch {rows[-1].epoch_s:.1f} s", flush=True)
        check = dtype_check(args, Path(tmp))
    meta = {
        "machine": cpu_name(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "blas": ", ".join(sorted({r.blas for r in rows})) or args.blas,
        "openblas": " ".join(str(v) for v in blas.openblas_info().values()),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "load_before": " ".join(f"{x:.1f}" for x in load_before),
        "load_after": " ".join(f"{x:.1f}" for x in os.getloadavg()),
        "seconds": time.perf_counter() - start,
        "repeats": args.repeats,
        "targets": targets(rows),
    }
    text = markdown(rows, check, meta)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench.md").write_text(text)
    rows_out = [{**dataclasses.asdict(r), **r.derived()} for r in rows]
    (args.out / "bench.json").write_text(
        json.dumps({"meta": meta, "rows": rows_out, "dtype_check": check}, indent=2)
    )
    print(text)
    print(f"written: {args.out / 'bench.md'}, {args.out / 'bench.json'}")


if __name__ == "__main__":
    main()
