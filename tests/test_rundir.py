"""Run directories: one writer at a time, the config they started with, every epoch exactly
once, files a cluster's other users can read, and failures recorded rather than hidden."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess

import pandas as pd
import pytest
import torch

from hmepol_cli.cli import train_runs
from hmepol_cli.errors import RunDirError, RunFailure
from hmepol_cli.run import (
    CHECKPOINT,
    COMMANDS,
    CONFIG,
    EPOCHS_CSV,
    LOCK,
    RUN_INFO,
    RunDirectory,
    atomic_write_text,
    read_json,
)
from hmepol_cli.trainer import Trainer
from tests.test_trainer import compose_cfg


# ------------------------------------------------------------------ ownership
def test_a_second_writer_is_refused_naming_the_holder(tmp_path):
    cfg = compose_cfg()
    first = RunDirectory(tmp_path / "run", cfg).open()
    try:
        with pytest.raises(RunDirError, match=f"pid {os.getpid()} on {socket.gethostname()}"):
            RunDirectory(tmp_path / "run", cfg).open()
    finally:
        first.close()
    assert not (tmp_path / "run" / LOCK).exists()
    RunDirectory(tmp_path / "run", cfg).open().close()  # free again once released


def test_the_lock_of_a_process_that_is_gone_is_taken_over_with_a_warning(tmp_path):
    gone = subprocess.Popen(["true"])
    gone.wait()
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    holder = {"pid": gone.pid, "host": socket.gethostname(), "started": "earlier"}
    (run_dir / LOCK).write_text(json.dumps(holder))
    with pytest.warns(UserWarning, match="is gone"):
        directory = RunDirectory(run_dir, compose_cfg()).open()
    assert json.loads((run_dir / LOCK).read_text())["pid"] == os.getpid()
    directory.close()


def test_a_lock_held_on_another_host_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / LOCK).write_text(json.dumps({"pid": 1, "host": "elsewhere", "started": "x"}))
    with pytest.raises(RunDirError, match="host elsewhere"):
        RunDirectory(run_dir, compose_cfg()).open()


# ------------------------------------------------------------------ identity and provenance
def test_continuing_a_run_with_another_config_is_refused_naming_the_keys(tmp_path):
    RunDirectory(tmp_path / "run", compose_cfg("algo.lr=0.001")).open().close()
    started = (tmp_path / "run" / CONFIG).read_text()
    with pytest.raises(RunDirError, match=r"algo\.lr=0\.001 \(now 0\.5\)") as refused:
        RunDirectory(tmp_path / "run", compose_cfg("algo.lr=0.5")).open()
    assert "\n" not in str(refused.value)
    assert (tmp_path / "run" / CONFIG).read_text() == started  # nothing it started with changes
    # What a continuation may change (epochs, device, threads, progress ...) is not a new config.
    RunDirectory(
        tmp_path / "run", compose_cfg("algo.lr=0.001", "epochs=9", "threads=1")
    ).open().close()
    assert len((tmp_path / "run" / COMMANDS).read_text().splitlines()) == 2


def test_a_setting_added_later_as_null_is_no_other_config():
    """A run started before a key existed (env.id, env.features ...) continues with a config
    that holds it as null; a key that is set, or removed while set, is a difference."""
    from hmepol_cli.run import identity_differences

    old = {"env": {"name": "slope"}, "algo": {"lr": 0.1}}
    assert (
        identity_differences(old, {"env": {"name": "slope", "id": None}, "algo": {"lr": 0.1}}) == []
    )
    changed = identity_differences(
        old, {"env": {"name": "slope", "id": "Ant-v5"}, "algo": {"lr": 0.1}}
    )
    assert changed == ["env.id='<absent>' (now 'Ant-v5')"]
    assert identity_differences({"env": {"name": "gym", "id": "Ant-v5"}}, {"env": {"name": "gym"}})
    # How many processes step a Gymnasium world changes no number: a run continues with another.
    assert identity_differences({"env": {"workers": 0}}, {"env": {"workers": 4}}) == []
    configs = {"env": {"configs": [{"g": 5.0}, {"g": 15.0}]}}
    assert identity_differences(configs, {"env": {"configs": [{"g": 5.0}, {"g": 10.0}]}})


def test_run_json_records_provenance_and_the_owner(tmp_path):
    directory = RunDirectory(tmp_path / "run", compose_cfg()).open("cpu")
    info = json.loads((tmp_path / "run" / RUN_INFO).read_text())
    directory.close()
    p = info["provenance"]
    assert p["torch"] == torch.__version__ and p["host"] == socket.gethostname()
    assert {"numpy", "scipy", "hmepol", "threads", "device", "command", "cpu"} <= set(p)
    assert p["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert info["owner"]["pid"] == os.getpid() and info["status"] == "running"
    assert len(info["identity"]) == 16
    assert [m["from_epoch"] for m in info["machines"]] == [0]
    assert info["machines"][0]["cpu"] == p["cpu"] and info["machines"][0]["device"] == "cpu"


def test_run_json_keeps_each_machine_a_run_was_continued_on(tmp_path, monkeypatch):
    """A run trained for 7 epochs on one CPU, continued on another for 5, and again on the
    second: machines names both, from the epochs they took it up from; provenance the last."""
    from hmepol_cli import hardware

    cfg, path = compose_cfg(), tmp_path / "run"

    def session(cpu: str, epochs_done: int) -> dict:
        monkeypatch.setattr(hardware, "cpu_model", lambda: cpu)
        directory = RunDirectory(path, cfg).open("cpu")
        directory.update(epochs_done=epochs_done)
        directory.close()
        return directory.info()

    session("AMD EPYC 7B13", 7)
    session("Intel(R) Xeon(R) Processor (family 6, model 167)", 12)
    info = session("Intel(R) Xeon(R) Processor (family 6, model 167)", 15)
    assert [(m["from_epoch"], m["cpu"]) for m in info["machines"]] == [
        (0, "AMD EPYC 7B13"),
        (7, "Intel(R) Xeon(R) Processor (family 6, model 167)"),
    ]
    assert info["provenance"]["cpu"] == "Intel(R) Xeon(R) Processor (family 6, model 167)"


# ------------------------------------------------------------------ files
def test_files_get_the_permissions_the_umask_gives_and_temporaries_are_removed(tmp_path):
    old = os.umask(0o022)
    try:
        run_dir = tmp_path / "run"
        run_dir.mkdir()
        (run_dir / f".{EPOCHS_CSV}.abc123.tmp").write_text("half a write")
        directory = RunDirectory(run_dir, compose_cfg()).open()
        atomic_write_text(run_dir / "some.txt", "x")
        directory.close()
    finally:
        os.umask(old)
    for name in (CONFIG, RUN_INFO, COMMANDS, "some.txt"):
        assert (run_dir / name).stat().st_mode & 0o777 == 0o644, name
    assert not list(run_dir.glob("*.tmp")) and not list(run_dir.glob(".*.tmp"))


def test_rows_written_before_a_first_checkpoint_are_not_kept(tmp_path):
    """A crash after epoch 0's rows but before its checkpoint (a full disk, say): the next run
    into that directory starts again from epoch 0, and writes it once."""
    cfg = compose_cfg("epochs=2", "progress=false")
    train_runs([(cfg, tmp_path / "run")])
    reference = pd.read_csv(tmp_path / "run" / EPOCHS_CSV)
    (tmp_path / "run" / CHECKPOINT).unlink()  # as if the crash came before the first checkpoint
    info = json.loads((tmp_path / "run" / RUN_INFO).read_text())
    (tmp_path / "run" / RUN_INFO).write_text(json.dumps({**info, "status": "running"}))
    train_runs([(cfg, tmp_path / "run")])
    again = pd.read_csv(tmp_path / "run" / EPOCHS_CSV)
    assert list(again.epoch) == [0, 1]
    timing = ["seconds", "collect_seconds", "neighbours_seconds", "update_seconds", "wall_time"]
    pd.testing.assert_frame_equal(again.drop(columns=timing), reference.drop(columns=timing))


# ------------------------------------------------------------------ loud failures
def test_a_member_whose_numbers_stop_being_finite_fails_alone_and_says_what(tmp_path, monkeypatch):
    """From epoch 1 on, member 1's world returns NaN positions: member 1 stops with its reason
    (the positions), its epoch and last finite values recorded; member 0 finishes."""
    trainer = Trainer(
        [compose_cfg("epochs=3", "progress=false", f"seed={s}") for s in (0, 1)],
        [tmp_path / f"seed{s}" for s in (0, 1)],
    )
    world, calls = trainer.world, {"n": 0}
    real_step = world.step
    steps_per_epoch = trainer.cfg.algo.horizon

    def poisoned(positions, actions, configurations, generator=None, *, noise=None, strength=None):
        moved = real_step(positions, actions, configurations, generator, noise=noise)
        calls["n"] += 1
        both = moved.shape[0] == 2 * trainer.cfg.algo.trajectories  # members 0 and 1 stepping
        if calls["n"] > steps_per_epoch and both:  # from the second epoch on
            moved[moved.shape[0] // 2 :] = math.nan  # member 1's agents
        return moved

    monkeypatch.setattr(world, "step", poisoned)
    trainer.train()
    assert set(trainer.failures) == {tmp_path / "seed1"}
    info = json.loads((tmp_path / "seed1" / RUN_INFO).read_text())
    assert info["status"] == "failed" and info["failure"]["epoch"] == 1
    assert "non-finite positions" in info["failure"]["reason"]
    assert info["failure"]["last_finite"]["epoch"] == 0
    assert len(pd.read_csv(tmp_path / "seed1" / EPOCHS_CSV)) == 1
    assert json.loads((tmp_path / "seed0" / RUN_INFO).read_text())["status"] == "finished"
    assert len(pd.read_csv(tmp_path / "seed0" / EPOCHS_CSV)) == 3


def test_train_runs_reports_a_failed_member_as_a_failure(tmp_path, monkeypatch):
    cfg = compose_cfg("epochs=2", "progress=false", "algo.lr=1e-3")
    monkeypatch.setattr(
        "hmepol_cli.alarms.MemberAlarms.non_finite", lambda self, stats, params: ["log-std"]
    )
    with pytest.raises(RunFailure, match="non-finite log-std at epoch 0"):
        train_runs([(cfg, tmp_path / "run")])
    assert json.loads((tmp_path / "run" / RUN_INFO).read_text())["status"] == "failed"


def test_a_stall_warns(tmp_path, caplog):
    cfg = compose_cfg(
        "epochs=3", "progress=false", "algo.kl_threshold=1e-12", "algo.lr_backtrack_tries=0",
        "alarms.stall_epochs=2",
    )  # fmt: skip
    with caplog.at_level("WARNING", logger="hmepol"):
        train_runs([(cfg, tmp_path / "run")])
    assert "no off-policy step accepted for 2 epochs" in caplog.text
    assert (pd.read_csv(tmp_path / "run" / EPOCHS_CSV).off_iters == 0).all()


# ------------------------------------------------------------------ damaged files on resume
def trained(tmp_path, epochs: int = 3):
    """A finished tiny run of ``epochs`` epochs, and a function that continues it to 5."""
    run = tmp_path / "run"
    Trainer(compose_cfg(f"epochs={epochs}"), run).train()

    def resume() -> pd.DataFrame:
        Trainer(compose_cfg("epochs=5"), run).train(resume=True)
        return pd.read_csv(run / "epochs.csv")

    return run, resume


def edit_lines(path, change) -> None:
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(change(lines)))


def test_rows_past_the_checkpoint_and_a_garbage_last_line_are_dropped(tmp_path):
    run, resume = trained(tmp_path)
    # A crash after an epoch's rows and before its checkpoint, then a line of garbage.
    edit_lines(run / "epochs.csv", lambda lines: [*lines, lines[-1].replace("2,", "3,", 1),
                                                  "x,y\n"])  # fmt: skip
    epochs = resume()
    assert list(epochs.epoch) == [0, 1, 2, 3, 4]
    assert epochs.entropy.notna().all()


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda lines: lines[:-1], r"epochs.csv no row \(epoch 2\) is not what the run wrote"),
        (lambda lines: [*lines[:3], lines[2], *lines[3:]], r"line 3 \(epoch 1\)"),  # duplicated
        (lambda lines: [lines[0], lines[1], "1,garbage\n", *lines[3:]], r"line 3 cannot be read"),
    ],
    ids=["deleted", "duplicated", "garbage"],
)
def test_a_missing_or_damaged_row_is_refused_naming_the_file_and_line(tmp_path, damage, message):
    run, resume = trained(tmp_path)
    edit_lines(run / "epochs.csv", damage)
    with pytest.raises(RunDirError, match=message):
        resume()


def test_a_number_cut_short_is_refused(tmp_path):
    run, resume = trained(tmp_path)
    rows = pd.read_csv(run / "epochs.csv")
    entropy = repr(float(rows.entropy[1]))

    def cut(lines):
        assert entropy in lines[2]
        return [*lines[:2], lines[2].replace(entropy, entropy[:6], 1), *lines[3:]]

    edit_lines(run / "epochs.csv", cut)
    with pytest.raises(RunDirError, match=r"epochs.csv line 3 \(epoch 1\)"):
        resume()


def test_a_damaged_batches_csv_is_refused_too(tmp_path):
    run, resume = trained(tmp_path)
    edit_lines(run / "batches.csv", lambda lines: [*lines[:4], *lines[5:]])
    with pytest.raises(RunDirError, match=r"batches.csv line \d+ \(epoch 1\)"):
        resume()


def test_a_damaged_run_json_is_rewritten_by_the_run_that_continues(tmp_path, recwarn):
    run, resume = trained(tmp_path, epochs=2)
    (run / "run.json").write_text("{not json")
    with pytest.raises(RunDirError, match=r"run.json is damaged \(JSONDecodeError"):
        read_json(run / "run.json")
    assert list(resume().epoch) == [0, 1, 2, 3, 4]
    assert read_json(run / "run.json")["status"] == "finished"
    assert any("rewriting it" in str(w.message) for w in recwarn)


# ------------------------------------------------------------------ a full disk
def test_a_full_disk_is_one_line_naming_the_path_and_the_run_continues_after(
    tmp_path, monkeypatch, capsys
):
    """The disk fills during epoch 1: the command says which file could not be written and
    what was kept, in one line; with space again the same command finishes, exactly."""
    import errno

    from hmepol_cli.cli import main
    from tests.test_cli import TINY

    args = ["train", *TINY, "epochs=4", f"hydra.run.dir={tmp_path / 'run'}"]
    real_fsync = os.fsync

    def filling(fd):
        if (tmp_path / "run" / "epochs.csv").exists() and len(
            pd.read_csv(tmp_path / "run" / "epochs.csv")
        ) >= 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", filling)
    with pytest.raises(SystemExit) as stopped:
        main(args)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert stopped.value.code == 1 and "Traceback" not in err
    assert len(lines) == 1 and "no space left on the device" in lines[0]
    # epochs.csv had its second row when batches.csv could not be written: one epoch kept
    assert "kept" in lines[0] and "up to epoch 1" in lines[0], lines
    monkeypatch.setattr(os, "fsync", real_fsync)
    main(args)  # space again: the same command continues
    assert list(pd.read_csv(tmp_path / "run" / "epochs.csv").epoch) == [0, 1, 2, 3]


# ------------------------------------------------------------------ resume and populations
def test_giving_a_run_the_value_it_already_has_is_no_change(tmp_path, capsys):
    from hmepol_cli.cli import main
    from tests.test_cli import TINY

    run = tmp_path / "run"
    main(["train", *TINY, "epochs=1", f"hydra.run.dir={run}"])
    main(["train", f"resume={run}", "epochs=2", "algo.lr=1e-3"])  # the run's own lr
    with pytest.raises(SystemExit) as other:
        main(["train", f"resume={run}", "epochs=3", "algo.lr=2e-3"])
    assert other.value.code == 2 and "algo.lr=2e-3 cannot change" in capsys.readouterr().err


@pytest.mark.slow  # end to end: runs of the installed command (make test runs it)
def test_a_population_resumed_with_a_member_behind_equals_an_uninterrupted_one(tmp_path):
    """Member 1's checkpoint is one epoch older than member 0's (a kill between the two
    saves): resumed, the population ends with every member's files equal to an uninterrupted
    population's, bit for bit."""
    import shutil

    cfgs = [compose_cfg("epochs=3", f"seed={s}", "checkpoint.keep_every=1") for s in (0, 1)]
    plain = Trainer(cfgs, [tmp_path / "plain" / f"seed{s}" for s in (0, 1)])
    plain.train()
    broken = [tmp_path / "broken" / f"seed{s}" for s in (0, 1)]
    Trainer([c.copy() for c in cfgs], broken).train()
    for d in broken:  # back to epoch 2 for member 0, epoch 1 for member 1, as if killed
        info = read_json(d / RUN_INFO)
        info["status"] = "running"
        (d / RUN_INFO).write_text(json.dumps(info))
    shutil.copy(broken[0] / "checkpoints" / "epoch_0002.pt", broken[0] / CHECKPOINT)
    shutil.copy(broken[1] / "checkpoints" / "epoch_0001.pt", broken[1] / CHECKPOINT)
    Trainer([c.copy() for c in cfgs], broken).train(resume=True)
    drop = ["seconds", "collect_seconds", "neighbours_seconds", "update_seconds", "wall_time"]
    for s, d in enumerate(broken):
        for name in ("epochs.csv", "batches.csv"):
            a = pd.read_csv(tmp_path / "plain" / f"seed{s}" / name)
            b = pd.read_csv(d / name)
            pd.testing.assert_frame_equal(
                a.drop(columns=drop, errors="ignore"), b.drop(columns=drop, errors="ignore"),
                check_exact=True,
            )  # fmt: skip
        final = torch.load(d / CHECKPOINT, weights_only=True)["policy"]
        reference = torch.load(tmp_path / "plain" / f"seed{s}" / CHECKPOINT, weights_only=True)
        assert all(torch.equal(final[k], reference["policy"][k]) for k in final)


# ------------------------------------------------------------------ fine-tuning a running run
def test_fine_tuning_refuses_a_run_that_is_still_being_trained(tmp_path):
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from hmepol_cli.errors import ConfigError
    from hmepol_cli.finetune import check_finetune

    run = tmp_path / "run"
    Trainer(compose_cfg("epochs=2", "checkpoint.keep_every=1"), run).train()
    holder = subprocess.Popen(["sleep", "300"])
    try:
        lock = {"pid": holder.pid, "host": socket.gethostname(), "started": "now"}
        (run / LOCK).write_text(json.dumps(lock))

        def plan(*extra):
            GlobalHydra.instance().clear()
            with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
                cfg = compose(config_name="finetune", overrides=[*extra, "targets=1", "config=0"])
            GlobalHydra.instance().clear()
            return check_finetune(cfg)

        with pytest.raises(ConfigError, match=f"still being trained \\(pid {holder.pid}"):
            plan(f"init={run}")
        assert plan(f"init={run}@1").init_epoch == 1  # a kept checkpoint: it cannot change
        assert plan(f"init={run}", "allow_running=true").init_epoch == 2
    finally:
        holder.kill()
        holder.wait()
