"""Experiment tracking, read back with each tracker's own library: TensorBoard's
event reader, W&B's offline run files (its protobuf records), MLflow's client on the SQLite
store. Every epoch's entropy once, per member of a population, and once more after a kill and
a resume; a tracker that fails is one warning; a missing package is one line."""

from __future__ import annotations

import glob
import json
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from tests.test_cli import TINY

pytest.importorskip("tensorboard")
pytest.importorskip("wandb")
pytest.importorskip("mlflow")

LOGGERS = "logger=[csv,tensorboard,wandb,mlflow]"


def tensorboard_entropy(run: Path) -> list[tuple[int, float]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    return [(e.step, e.value) for e in events.Scalars("entropy")]


def wandb_records(run: Path) -> tuple[list[dict], list]:
    """The history rows and run records of every offline W&B run file under ``run`` (a resumed
    run writes a second file with the same id), read with W&B's protobuf Record."""
    from wandb.proto import wandb_internal_pb2 as pb

    history, runs = [], []
    for path in sorted(glob.glob(str(run / "wandb" / "offline-run-*" / "*.wandb"))):
        data = Path(path).read_bytes()
        assert data[:4] == b":W&B"
        block, pos, pending, chunks = 32768, 7, b"", []
        while pos + 7 <= len(data):  # LevelDB log records: crc, length, type; 32 KiB blocks
            left = block - pos % block
            if left < 7:
                pos += left
                continue
            _, length, kind = struct.unpack("<IHB", data[pos : pos + 7])
            if length == 0 and kind == 0:
                pos += left
                continue
            chunk, pos = data[pos + 7 : pos + 7 + length], pos + 7 + length
            if kind == 1:
                chunks.append(chunk)
            elif kind == 2:
                pending = chunk
            elif kind == 3:
                pending += chunk
            elif kind == 4:
                chunks.append(pending + chunk)
        for chunk in chunks:
            record = pb.Record()
            record.ParseFromString(chunk)
            kind = record.WhichOneof("record_type")
            if kind == "history":
                history.append(
                    {
                        i.key or "/".join(i.nested_key): json.loads(i.value_json)
                        for i in record.history.item
                    }  # fmt: skip
                )
            elif kind == "run":
                runs.append(record.run)
    return history, runs


def wandb_entropy(run: Path) -> list[tuple[int, float]]:
    """What W&B shows once the offline files are synced, in order: a step's first value (a
    value logged below a run's current step is ignored)."""
    history, _ = wandb_records(run)
    shown: dict[int, float] = {}
    for row in history:
        if "entropy" in row:
            shown.setdefault(int(row["_step"]), row["entropy"])
    return sorted(shown.items())


def mlflow_runs(store: Path) -> dict[str, object]:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{store}")
    experiment = client.get_experiment_by_name("hmepol")
    runs = client.search_runs([experiment.experiment_id])
    return {r.data.tags["mlflow.runName"]: (r, client) for r in runs}


def mlflow_entropy(store: Path, name: str) -> list[tuple[int, float]]:
    run, client = mlflow_runs(store)[name]
    return sorted((m.step, m.value) for m in client.get_metric_history(run.info.run_id, "entropy"))


def hmepol(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "hmepol_cli", *args],
        cwd=cwd, capture_output=True, text=True, timeout=600,
    )  # fmt: skip


def expected(run: Path) -> list[tuple[int, float]]:
    rows = pd.read_csv(run / "epochs.csv")
    return list(zip(rows.epoch.astype(int), rows.entropy, strict=True))


@pytest.mark.slow
def test_each_member_of_a_population_is_a_tracking_run_of_its_own(tmp_path):
    proc = hmepol("train", *TINY, "epochs=3", "seeds=[0,1]", LOGGERS,
                  f"hydra.run.dir={tmp_path / 'pop'}", cwd=tmp_path)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    store = tmp_path / "pop" / "mlflow.db"  # the members' folder: no outputs/ above them
    runs = mlflow_runs(store)
    parents = set()
    for seed in (0, 1):
        run = tmp_path / "pop" / f"seed{seed}"
        truth = expected(run)
        assert [s for s, _ in truth] == [0, 1, 2]
        for name, got in (
            ("tensorboard", tensorboard_entropy(run)),
            ("wandb", wandb_entropy(run)),
            ("mlflow", mlflow_entropy(store, run.name)),
        ):
            assert [s for s, _ in got] == [0, 1, 2], name
            assert [v for _, v in got] == pytest.approx([v for _, v in truth], rel=1e-6), name
        _, (record, *_) = wandb_records(run)
        assert record.display_name == run.name and record.run_group.startswith("population-")
        mlflow_run, _ = runs[run.name]
        parents.add(mlflow_run.data.tags["mlflow.parentRunId"])
        assert mlflow_run.data.params["seed"] == str(seed)  # the config as hyperparameters
    assert len(parents) == 1  # one parent run: the population
    (parent,) = parents
    assert runs[_wandb_group(tmp_path)][0].info.run_id == parent


def _wandb_group(tmp_path: Path) -> str:
    _, (record, *_) = wandb_records(tmp_path / "pop" / "seed0")
    return record.run_group


@pytest.mark.slow
def test_a_killed_run_continues_its_tracking_runs_with_every_epoch_once(tmp_path):
    args = ("train", *TINY, "epochs=10", "algo.trajectories=20", "algo.horizon=100", LOGGERS,
            f"hydra.run.dir={tmp_path / 'run'}")  # fmt: skip
    proc = subprocess.Popen(
        [sys.executable, "-m", "hmepol_cli", *args], cwd=tmp_path,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    run = tmp_path / "run"
    deadline = time.time() + 300
    while not (run / "epochs.csv").exists() or len(pd.read_csv(run / "epochs.csv")) < 3:
        assert proc.poll() is None and time.time() < deadline
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    again = hmepol(*args, cwd=tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    truth = expected(run)
    assert [s for s, _ in truth] == list(range(10))
    store = tmp_path / "mlflow.db"
    for name, got in (
        ("tensorboard", tensorboard_entropy(run)),
        ("wandb", wandb_entropy(run)),
        ("mlflow", mlflow_entropy(store, run.name)),
    ):
        assert [s for s, _ in got] == list(range(10)), (name, got)
        assert [v for _, v in got] == pytest.approx([v for _, v in truth], rel=1e-6), name
    assert len(mlflow_runs(store)) == 1  # continued, not a second run


@pytest.mark.slow
def test_mlflow_writes_its_store_and_artifacts_beside_the_run_not_in_the_current_folder(
    tmp_path,
):
    here, elsewhere = tmp_path / "here", tmp_path / "elsewhere"
    here.mkdir()
    proc = hmepol("train", *TINY, "epochs=1", "logger=[csv,mlflow]",
                  f"hydra.run.dir={elsewhere / 'run'}", cwd=here)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(here.iterdir()) == []  # no mlruns/, no outputs/
    assert sorted(p.name for p in elsewhere.iterdir()) == ["mlflow-artifacts", "mlflow.db", "run"]
    (run, client) = mlflow_runs(elsewhere / "mlflow.db")["run"]
    experiment = client.get_experiment(run.info.experiment_id)
    assert experiment.artifact_location == (elsewhere / "mlflow-artifacts").as_uri()
    logged = [a.path for a in client.list_artifacts(run.info.run_id, "heatmap/0000")]
    assert logged == ["heatmap/0000/heatmap.png"]
    (picture,) = (elsewhere / "mlflow-artifacts").rglob("heatmap.png")
    assert picture.read_bytes() == next((elsewhere / "run").rglob("heatmap.png")).read_bytes()


def test_the_default_mlflow_store_is_the_outputs_folder_above_the_run_else_beside_it(tmp_path):
    from hmepol_cli.tracking import default_mlflow_uri, mlflow_artifact_root

    outputs = tmp_path / "outputs"
    for run in (outputs / "runs" / "a", outputs / "sweep" / "job" / "seed0"):
        assert default_mlflow_uri(run) == f"sqlite:///{outputs / 'mlflow.db'}"
    assert default_mlflow_uri(tmp_path / "pop" / "seed1") == f"sqlite:///{tmp_path}/pop/mlflow.db"
    run = tmp_path / "x" / "run"
    for uri, root in (
        (f"sqlite:///{tmp_path}/db/store.db", tmp_path / "db" / "store-artifacts"),
        ("sqlite:///rel/store.db?timeout=5", Path("rel").resolve() / "store-artifacts"),
        ("sqlite://", tmp_path / "x" / "mlflow-artifacts"),  # in memory: where the default is
        ("postgresql+psycopg2://u@host/db", tmp_path / "x" / "mlflow-artifacts"),
    ):
        assert mlflow_artifact_root(uri, run) == root.as_uri(), uri
    for uri in ("http://localhost:5000", f"file://{tmp_path}/mlruns", str(tmp_path / "mlruns")):
        assert mlflow_artifact_root(uri, run) is None, uri  # the server's or the store's own


def test_a_failing_tracker_is_one_warning_and_the_run_goes_on(tmp_path, recwarn, monkeypatch):
    from hmepol_cli import tracking
    from hmepol_cli.trainer import Trainer
    from tests.test_trainer import compose_cfg

    def broken(self, epoch, values):
        raise OSError("the disk of the tracking server is gone")

    monkeypatch.setattr(tracking.TensorBoardTracker, "scalars", broken)
    Trainer(compose_cfg("epochs=3", "logger=[csv,tensorboard]"), tmp_path / "run").train()
    assert len(pd.read_csv(tmp_path / "run" / "epochs.csv")) == 3
    messages = [str(w.message) for w in recwarn if "logger=tensorboard" in str(w.message)]
    assert len(messages) == 1 and "failed to log" in messages[0] and "goes on" in messages[0]


def test_a_tracker_whose_package_is_missing_is_one_line_naming_the_extra(capsys, monkeypatch):
    import importlib.util

    from hmepol_cli.cli import main

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "wandb" else real(name, *a)
    )
    with pytest.raises(SystemExit) as stopped:
        main(["train", "logger=[csv,wandb]"])
    err = capsys.readouterr().err
    assert stopped.value.code == 2
    assert err.strip() == (
        "hmepol: error: logger=wandb needs the wandb package: pip install 'hmepol[tracking]'"
    )
