"""What one benchmark run measured, the ratios derived from it, and its Markdown report."""

from __future__ import annotations

from dataclasses import dataclass, field

OFF_ITERS = 30  # off-policy iterations of a measured epoch (the thesis' max_off_iters)
# What the speed benchmark asks of this machine.
TARGETS = {
    "collection_ratio": 50.0,  # steps/s against the plain per-step loop, at least
    "neighbour_seconds": 0.5,  # kdtree search per epoch, at most
    "matmul_fraction": 0.5,  # of measured matmul throughput in an off-policy iteration, at least
    "hmepol_corridor_epoch_seconds": 40.0,  # at most
    # The corridor Mepol epoch, of its layer products at the machine's best float32 rate
    "mepol_corridor_epoch_over_products": 1.6,  # at most
}
ALGO_NAMES = {"mepol": "Mepol", "hmepol": "HMepol"}


@dataclass
class Row:
    """One setting (world x algorithm) at thesis scale."""

    env: str
    algo: str
    particles: int  # N x T
    forward_flops: int  # of the policy, per particle
    plain_steps_per_s: float = 0.0  # the plain per-step loop
    plain_steps_timed: int = 0
    steps_per_s: float = 0.0  # batched collection
    kdtree_s: float = 0.0
    torch_s: float = 0.0
    brute_force_s: float = 0.0
    brute_force_batches_timed: int = 0
    collect_s: float = 0.0  # of the whole epoch
    neighbours_s: float = 0.0
    update_s: float = 0.0
    epoch_s: float = 0.0
    off_iters: int = 0
    # Matmul throughput measured just before and just after the epoch (the faster of the two),
    # through the library the epoch used (blas):
    layer_matmul_flops: float = 0.0  # at the hidden layer's shapes over all particles
    square_matmul_flops: float = 0.0  # 2048 x 2048 by 2048 x 2048
    blas: str = "torch"  # the library of the epoch's float32 layer products
    # The same per library (torch, openblas): the machine's best float32 rate is their maximum
    layer_rates: dict = field(default_factory=dict)
    square_rates: dict = field(default_factory=dict)
    # The same epoch with precision=bf16 (its own trainer, same seed), measured right after:
    bf16_epoch_s: float = 0.0
    bf16_update_s: float = 0.0
    bf16_off_iters: int = 0
    bf16_layer_matmul_flops: float = 0.0  # the layer's matmuls in bfloat16

    @property
    def label(self) -> str:
        return f"{self.env} {ALGO_NAMES[self.algo]}"

    @property
    def collection_ratio(self) -> float:
        return self.steps_per_s / self.plain_steps_per_s

    @property
    def iteration_s(self) -> float:
        return self.update_s / max(self.off_iters, 1)

    @property
    def iteration_flops(self) -> float:
        """Forward + backward of the policy over all particles, counted as 3 x forward."""
        return 3.0 * self.forward_flops * self.particles

    @property
    def iteration_flops_per_s(self) -> float:
        return self.iteration_flops / self.iteration_s

    @property
    def matmul_fraction(self) -> float:
        """Of the matmul throughput at the policy's own layer shapes (the target's reference)."""
        return self.iteration_flops_per_s / self.layer_matmul_flops

    @property
    def square_fraction(self) -> float:
        return self.iteration_flops_per_s / self.square_matmul_flops

    @property
    def best_matmul_flops(self) -> float:
        """The machine's best float32 product rate: over the libraries, at the layer's shapes
        and at 2048²."""
        rates = [*self.layer_rates.values(), *self.square_rates.values()]
        return max([*rates, self.layer_matmul_flops, self.square_matmul_flops])

    @property
    def products_s(self) -> float:
        """Seconds the epoch's layer products (every off-policy iteration's forward and
        backward over all particles) take at the best rate: the floor of an epoch."""
        return self.iteration_flops * self.off_iters / self.best_matmul_flops

    @property
    def epoch_over_products(self) -> float:
        return self.epoch_s / self.products_s

    @property
    def bf16_ratio(self) -> float:
        """How many times faster the bf16 epoch is than the float32 one."""
        return self.epoch_s / self.bf16_epoch_s if self.bf16_epoch_s else float("nan")

    @property
    def bf16_matmul_fraction(self) -> float:
        """The bf16 iteration's FLOP rate, of the bf16 layer-matmul rate."""
        if not self.bf16_update_s:
            return float("nan")
        rate = self.iteration_flops / (self.bf16_update_s / max(self.bf16_off_iters, 1))
        return rate / self.bf16_layer_matmul_flops

    @property
    def plain_epoch_s(self) -> float:
        """The same epoch with the plain loop's collection and the brute-force search."""
        return self.particles / self.plain_steps_per_s + self.brute_force_s + self.update_s

    def derived(self) -> dict[str, float]:
        names = (
            "collection_ratio",
            "iteration_s",
            "iteration_flops",
            "matmul_fraction",
            "square_fraction",
            "best_matmul_flops",
            "products_s",
            "epoch_over_products",
            "plain_epoch_s",
            "bf16_ratio",
            "bf16_matmul_fraction",
        )
        return {name: getattr(self, name) for name in names}


def targets(rows: list[Row]) -> list[tuple[str, str, bool]]:
    """(target, measured, met) for each target the rows cover."""
    t, out = TARGETS, []
    if rows:
        lowest = min(r.collection_ratio for r in rows)
        out.append(
            (
                f"collection >= {t['collection_ratio']:.0f}x the plain loop",
                f"{lowest:.1f}x (lowest)",
                lowest >= t["collection_ratio"],
            )
        )
        highest = max(r.kdtree_s for r in rows)
        out.append(
            (
                f"neighbour search < {t['neighbour_seconds']} s per epoch",
                f"{highest:.3f} s (highest)",
                highest < t["neighbour_seconds"],
            )
        )
        lowest = min(r.matmul_fraction for r in rows)
        out.append(
            (
                f"off-policy iteration >= {t['matmul_fraction']:.0%} of matmul throughput",
                f"{lowest:.0%} (lowest)",
                lowest >= t["matmul_fraction"],
            )
        )
    for r in rows:
        if (r.env, r.algo) == ("corridor", "mepol") and r.off_iters:
            limit = t["mepol_corridor_epoch_over_products"]
            out.append(
                (
                    f"Mepol corridor epoch <= {limit}x its layer products at the best rate",
                    f"{r.epoch_over_products:.2f}x ({r.epoch_s:.1f} s / {r.products_s:.1f} s)",
                    r.epoch_over_products <= limit,
                )
            )
        if (r.env, r.algo) == ("corridor", "hmepol"):
            limit = t["hmepol_corridor_epoch_seconds"]
            out.append(
                (f"HMepol corridor epoch < {limit:.0f} s", f"{r.epoch_s:.1f} s", r.epoch_s < limit)
            )
    return out


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join([*lines, *("| " + " | ".join(r) + " |" for r in rows)])


def markdown(rows: list[Row], check: dict, meta: dict) -> str:
    """The report: one table per measurement, then the dtype check and the targets."""
    first = rows[0]
    collection = _table(
        ["setting", "steps/s", "plain loop steps/s", "ratio"],
        [
            [
                r.label,
                f"{r.steps_per_s:,.0f}",
                f"{r.plain_steps_per_s:,.0f}",
                f"{r.collection_ratio:.1f}x",
            ]
            for r in rows
        ],
    )
    neighbours = _table(
        ["setting", "kdtree s", "torch s", "brute force s", "brute force / kdtree"],
        [
            [
                r.label,
                f"{r.kdtree_s:.3f}",
                f"{r.torch_s:.3f}",
                f"{r.brute_force_s:.2f}",
                f"{r.brute_force_s / r.kdtree_s:.0f}x",
            ]
            for r in rows
        ],
    )
    libraries = sorted({b for r in rows for b in r.layer_rates})
    rates = _table(
        ["setting", *(f"{b}: layer, 2048² GFLOP/s" for b in libraries), "best", "epoch's library"],
        [
            [
                r.label,
                *(
                    f"{r.layer_rates.get(b, 0) / 1e9:.1f}, {r.square_rates.get(b, 0) / 1e9:.1f}"
                    for b in libraries
                ),
                f"{r.best_matmul_flops / 1e9:.1f}",
                r.blas,
            ]
            for r in rows
        ],
    )
    iteration = _table(
        [
            "setting",
            "s / iteration",
            "GFLOP / iteration",
            "GFLOP/s",
            "layer matmul GFLOP/s",
            "fraction",
            "2048² matmul GFLOP/s",
            "fraction",
        ],
        [
            [
                r.label,
                f"{r.iteration_s:.3f}",
                f"{r.iteration_flops / 1e9:.1f}",
                f"{r.iteration_flops_per_s / 1e9:.1f}",
                f"{r.layer_matmul_flops / 1e9:.1f}",
                f"{r.matmul_fraction:.0%}",
                f"{r.square_matmul_flops / 1e9:.1f}",
                f"{r.square_fraction:.0%}",
            ]
            for r in rows
        ],
    )
    epoch = _table(
        [
            "setting",
            "collect s",
            "neighbours s",
            f"{first.off_iters} iterations s",
            "epoch s",
            "plain epoch s",
            "ratio",
            "products at the best rate s",
            "epoch / products",
        ],
        [
            [
                r.label,
                f"{r.collect_s:.2f}",
                f"{r.neighbours_s:.2f}",
                f"{r.update_s:.1f}",
                f"{r.epoch_s:.1f}",
                f"{r.plain_epoch_s:.1f}",
                f"{r.plain_epoch_s / r.epoch_s:.2f}x",
                f"{r.products_s:.1f}",
                f"{r.epoch_over_products:.2f}x",
            ]
            for r in rows
        ],
    )
    precision = _table(
        [
            "setting",
            "float32 epoch s",
            "bf16 epoch s",
            "bf16 / float32 speed",
            "float32: of its layer matmul rate",
            "bf16: of its layer matmul rate",
            "layer matmul GFLOP/s float32, bf16",
        ],
        [
            [
                r.label,
                f"{r.epoch_s:.1f}",
                f"{r.bf16_epoch_s:.1f}",
                f"{r.bf16_ratio:.2f}x",
                f"{r.matmul_fraction:.0%}",
                f"{r.bf16_matmul_fraction:.0%}",
                f"{r.layer_matmul_flops / 1e9:.0f}, {r.bf16_layer_matmul_flops / 1e9:.0f}",
            ]
            for r in rows
            if r.bf16_epoch_s
        ],
    )
    goals = _table(
        ["target", "measured", "met"],
        [[t, m, "yes" if ok else "no"] for t, m, ok in meta["targets"]],
    )
    return f"""\
Machine: {meta["machine"]}; torch {meta["torch"]}, {meta["threads"]} threads, \
OMP_WAIT_POLICY={meta["omp_wait_policy"]}, float32, blas={meta["blas"]} (OpenBLAS \
{meta["openblas"]}). Load average (1, 5, 15 min) \
{meta["load_before"]} at the start, {meta["load_after"]} at the end; {meta["seconds"]:.0f} s in all.

**Collection** (N x T steps, policy included) against a plain per-step Python loop over single \
environments (NumPy float64, one policy forward per environment per step; \
{first.plain_steps_timed} steps timed, extrapolated). The two take turns, the faster of \
{meta["repeats"]} turns each; kNN searches too keep the fastest of {meta["repeats"]}:

{collection}

**Neighbour search per epoch** (every mini-batch, k = 30) against a brute-force search (all \
pairwise distances of a mini-batch, NumPy float64, one thread; {first.brute_force_batches_timed} \
mini-batches timed, extrapolated):

{neighbours}

**float32 product rates per library** (torch's own, and NumPy's OpenBLAS on the same memory; \
measured just before and after each epoch, the faster kept): at the hidden layer's shapes over \
all particles and at 2048². The best of them is the machine's float32 rate the epoch is held \
against:

{rates}

**Off-policy iteration** (forward + backward of the IW objective, KL, Adam step, trust-region \
bookkeeping; the mean over the {first.off_iters} iterations of the epoch below) against float32 \
products through the epoch's library, measured just before and after that epoch: at the \
shapes of a hidden 300 x 300 layer over all particles (forward x W^T, backward g W and g^T x: \
the representative size) and at 2048². FLOPs counted analytically: 2 x in x out per Linear \
per particle forward, x3 for forward + backward:

{iteration}

**Whole epoch** (collection + neighbours + {first.off_iters} off-policy iterations, forced by \
kl_threshold=1e9). Plain epoch: the plain loop's collection and the brute-force search, with \
the same off-policy iterations. Products at the best rate: the epoch's layer products \
(3 x forward FLOPs x particles x iterations) at the best rate of the table above, the floor an \
epoch could reach:

{epoch}

**Precision** (the same epoch, {first.off_iters} iterations, with `precision=bf16`: the hidden \
layers' products in bfloat16, the action mean and the likelihoods in float32; measured right \
after the float32 one, on the same machine; `python -m benchmarks.precision` validates it):

{precision}

**float32 vs float64** ({check["setting"]}; one float64 rollout shared by both): the kNN \
entropies of the same particles differ by at most {check["entropy_max_abs_diff"]:.1e} nats. The \
update moves the objective from {check["objective_start"]:.5f} to {check["objective_float64"]:.5f} \
in float64 and to {check["objective_float32_shared_neighbours"]:.5f} in float32 with the same \
neighbour sets (difference {check["objective_abs_diff_shared_neighbours"]:.1e} nats; KL \
{check["kl_float64"]:.4g} and {check["kl_float32_shared_neighbours"]:.4g}). With each dtype's own \
search it reaches {check["objective_float32"]:.5f} (difference {check["objective_abs_diff"]:.1e}; \
KL {check["kl_float32"]:.4g}): rounding the particles to float32 changes \
{check["neighbour_index_mismatch"]:.0%} of the neighbour-list entries, among particles at \
(almost) the same distance (agents the slope holds against a wall or the arena's edge), and \
which of those tied particles belong to N_i^k changes the gradient, not the entropy.

**Targets**

{goals}
"""
