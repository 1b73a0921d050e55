"""Population training against separate runs: seconds per epoch for S members, per device.

    python -m benchmarks.population                      # CPU: S = 1, 4 against one-thread runs
    python -m benchmarks.population --device cuda --sizes 1 4 8 16 --iters 30

For each S, one population of S seeds trains at a thesis preset (``--setting``, e.g.
slope-hmepol: 200 trajectories x 400 steps, B = 5, k = 30) with every off-policy iteration
forced (``--iters``): one epoch to warm up, then the mean of ``--epochs`` timed epochs. Against:

- on a CPU, S separate runs side by side: S processes of one thread each, started together by a
  shared clock, each timing the same epoch of its own seed; their wall time is the time S seeds
  take (what a sweep's joblib jobs do);
- on a GPU, S separate runs one after the other on the device: S times a population of one,
  measured in the same call (separate processes on one GPU take turns).

FLOP rate: the policy's forward FLOPs x particles x 3 (forward and backward) x iterations x S
over the update's seconds, as a fraction of the device's float32 matrix-product rate, measured
in the same call at the shapes of a hidden (300, 300) layer over all particles.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from benchmarks.measure import cpu_name, forward_flops  # noqa: E402
from benchmarks.run import thesis_config  # noqa: E402
from hmepol_cli.seeding import keep_freed_memory  # noqa: E402
from hmepol_cli.trainer import Trainer  # noqa: E402


def member_configs(setting: str, seeds: list[int], args: argparse.Namespace) -> list:
    """The thesis preset of ``setting`` (env-algo) for each seed, every iteration forced."""
    env, algo = setting.split("-")
    device = [f"device={args.device}", f"precision={args.precision}"]
    return [
        thesis_config(env, algo, [*device, f"seed={seed}", *args.override], args.iters)
        for seed in seeds
    ]


def synchronize(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def epoch_seconds(trainer: Trainer, epochs: int, device: str) -> dict[str, float]:
    """Mean seconds of ``epochs`` epochs (after one to warm up), split as the trainer does."""
    trainer.epoch()
    synchronize(device)
    totals: dict[str, float] = {}
    for _ in range(epochs):
        start = time.perf_counter()
        stats = trainer.epoch()
        synchronize(device)
        totals["epoch"] = totals.get("epoch", 0.0) + time.perf_counter() - start
        for key in ("collect", "neighbours", "update"):
            totals[key] = totals.get(key, 0.0) + stats[0].seconds[key]
    return {key: value / epochs for key, value in totals.items()}


def layer_matmul_rate(rows: int, device: str, width: int = 300, seconds: float = 1.0) -> float:
    """float32 FLOP/s of a hidden (width x width) layer's three products over ``rows`` rows."""
    kw = dict(device=device)
    x, g, w = (
        torch.randn(rows, width, **kw),
        torch.randn(rows, width, **kw),
        torch.randn(width, width, **kw),
    )

    def layer() -> None:
        torch.matmul(x, w.T)
        torch.matmul(g, w)
        torch.matmul(g.T, x)

    layer()
    synchronize(device)
    best, spent = float("inf"), 0.0
    while spent < seconds:
        start = time.perf_counter()
        for _ in range(5):
            layer()
        synchronize(device)
        took = (time.perf_counter() - start) / 5
        best, spent = min(best, took), spent + 5 * took
    return 3 * 2 * rows * width * width / best


def side_by_side(setting: str, seeds: list[int], args: argparse.Namespace) -> float:
    """Wall seconds of one epoch of each seed as separate one-thread processes, started by a
    shared clock (their imports and set-up excluded)."""
    start_at = time.time() + 15 + 2 * len(seeds)
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "benchmarks.population",
                "--worker",
                str(seed),
                "--start-at",
                str(start_at),
                "--setting",
                setting,
                "--iters",
                str(args.iters),
                "--override",
                *args.override,
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        for seed in seeds
    ]
    spans = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in procs]
    return max(end for _, end in spans) - min(start for start, _ in spans)


def worker(args: argparse.Namespace) -> None:
    """One separate run: one thread, one warm-up epoch, then wait for the clock and time one."""
    torch.set_num_threads(1)
    keep_freed_memory()
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(member_configs(args.setting, [args.worker], args), Path(tmp) / "run")
        trainer.epoch()
        time.sleep(max(0.0, args.start_at - time.time()))
        start = time.time()
        trainer.epoch()
        print(json.dumps([start, time.time()]))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.population")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--setting", default=None, help="env-algo (default: per device)")
    parser.add_argument("--sizes", type=int, nargs="+", default=None)
    parser.add_argument("--iters", type=int, default=None, help="off-policy iterations")
    parser.add_argument("--epochs", type=int, default=2, help="timed epochs per size")
    parser.add_argument("--precision", default="float32", choices=("float32", "bf16", "tf32"))
    parser.add_argument("--threads", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("outputs/bench"))
    parser.add_argument("--override", nargs="*", default=[])
    parser.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--start-at", type=float, default=0.0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    gpu = args.device == "cuda"
    args.setting = args.setting or ("slope-hmepol" if gpu else "corridor-mepol")
    args.iters = args.iters or (30 if gpu else 3)
    if args.worker is not None:
        worker(args)
        return
    sizes = args.sizes or ([1, 4, 8, 16] if gpu else [1, 4])
    if args.threads:
        torch.set_num_threads(args.threads)
    keep_freed_memory()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in sizes:
            seeds = list(range(size))
            cfgs = member_configs(args.setting, seeds, args)
            trainer = Trainer(cfgs, [Path(tmp) / f"s{size}" / f"seed{s}" for s in seeds])
            a = trainer.cfg.algo
            particles = a.trajectories * a.horizon
            flops = 3 * forward_flops(trainer.population.member(0)) * particles * args.iters * size
            seconds = epoch_seconds(trainer, args.epochs, args.device)
            rate = layer_matmul_rate(particles, args.device)
            del trainer
            if gpu:
                torch.cuda.empty_cache()
            row = {
                "members": size,
                "epoch_s": seconds["epoch"],
                "per_seed_s": seconds["epoch"] / size,
                "collect_s": seconds["collect"],
                "neighbours_s": seconds["neighbours"],
                "update_s": seconds["update"],
                "update_tflops": flops / seconds["update"] / 1e12,
                "matmul_tflops": rate / 1e12,
                "fraction_of_matmul": flops / seconds["update"] / rate,
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
        single = rows[0]["epoch_s"] if sizes[0] == 1 else None
        for row in rows:
            if gpu and single is not None:
                row["separate_s"] = single * row["members"]  # one after the other on the GPU
            elif not gpu:
                row["separate_s"] = side_by_side(args.setting, list(range(row["members"])), args)
            if "separate_s" in row:
                row["speedup"] = row["separate_s"] / row["epoch_s"]
            print(json.dumps(row), flush=True)
    device = torch.cuda.get_device_name() if gpu else cpu_name()
    meta = {
        "device": device,
        "device_kind": args.device,
        "setting": args.setting,
        "iters": args.iters,
        "precision": args.precision,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "load": " ".join(f"{x:.1f}" for x in os.getloadavg()),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"population_{args.device}"
    (args.out / f"{name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    (args.out / f"{name}.md").write_text(markdown(meta, rows))
    print(markdown(meta, rows))


def markdown(meta: dict, rows: list[dict]) -> str:
    separate = (
        "S separate runs one after the other"
        if "cuda" in meta.get("device", "").lower() or "NVIDIA" in meta["device"]
        else "S one-thread runs side by side"
    )
    lines = [
        f"Population vs separate runs: {meta['setting']}, {meta['iters']} off-policy iterations, "
        f"{meta['device']}, torch {meta['torch']}, {meta['threads']} threads, "
        f"precision {meta['precision']}, load {meta['load']}.",
        "",
        f"| S | population s/epoch | per seed | {separate} | speed-up | update TFLOP/s "
        "| of matmul rate |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sep = f"{r['separate_s']:.2f}" if "separate_s" in r else "-"
        speed = f"{r['speedup']:.2f}x" if "speedup" in r else "-"
        lines.append(
            f"| {r['members']} | {r['epoch_s']:.2f} | {r['per_seed_s']:.2f} | {sep} | {speed} | "
            f"{r['update_tflops']:.2f} | {100 * r['fraction_of_matmul']:.0f}% "
            f"(of {r['matmul_tflops']:.1f}) |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
