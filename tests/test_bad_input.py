"""Bad input gets one line naming the bad value and what is allowed, never a traceback, and
nothing is written: every case runs the command's entry point in-process."""

from __future__ import annotations

import pickle

import pytest
import torch

from hmepol_cli.cli import main
from tests.gym_toy import WALK_ID

TRAIN = [
    (["env=nowhere"], "nowhere"),
    (["estimator.k=0"], "estimator.k=0"),
    (["estimator.k=-3"], "estimator.k=-3"),
    (["algo.alpha=1.5"], "algo.alpha=1.5"),
    (["algo.alpha=0"], "algo.alpha=0"),
    (["algo.alpha=nan"], "algo.alpha=nan"),
    (["algo.lr=inf"], "algo.lr=inf"),
    (["algo.lr=0"], "algo.lr=0"),
    (["algo.kl_threshold=nan"], "algo.kl_threshold=nan"),
    (["wind=-1"], "wind=-1"),
    (["wind=abc"], "abc"),
    (["wind=inf"], "wind=inf"),
    (["resume=/nonexistent/run"], "/nonexistent/run"),
    (["device=tpu"], "device='tpu'"),
    (["algo.lrr=1"], "lrr"),
    (["+foo=1"], "'foo'"),
    (["+algo.foo=2"], "'algo.foo'"),
    (["epochs=many"], "many"),
    (["epochs=-1"], "epochs=-1"),
    (["policy.bptt=zero"], "policy.bptt='zero'"),
    (["policy=nosuch"], "nosuch"),
    (["algo=nosuch"], "nosuch"),
    (["experiment=nosuch"], "nosuch"),
    (["seeds=[1,1]"], "seeds=[1, 1]"),
    (["algo.trajectories=7"], "algo.trajectories=7"),
    (["policy.init_log_std=nan"], "policy.init_log_std=nan"),
    (["alarms.stall_epochs=0"], "alarms.stall_epochs=0"),
    (["algo.trust_region=loose"], "algo.trust_region='loose'"),
    (["algo.adam_reset=never"], "algo.adam_reset takes one of: epoch (or null)"),
    # Gymnasium worlds: the id, the indices, the class of configurations
    (["env=gym"], "env.id"),
    (["env=gym", "env.id=NoSuchEnv-v0"], "env.id='NoSuchEnv-v0' is not a registered"),
    (["env=gym", "env.id=MountainCarContinuous-v1"], "MountainCarContinuous-v0"),  # a hint
    (["env=mountaincar", "env.features=[0,5]"], "env.features=[0, 5]"),
    (["env=mountaincar", "env.features=[1,1]"], "env.features=[1, 1]"),
    (["env=mountaincar", "env.projection=[0]"], "env.projection=[0]"),
    (["env=mountaincar", "env.workers=-1"], "env.workers=-1"),
    (["env=mountaincar", "env.probs=[1,2]"], "env.probs=[1.0, 2.0] must hold 1 finite number"),
    (["env=gym", "env.id=Pendulum-v1", "env.configs=[{gravity:5}]"], "env.configs[0]"),
    (["env=gym", f"env.id={WALK_ID}", "env.configs=[{},{dim:3}]"], "env.configs[1]"),
    # Hydra's own messages, with what is allowed
    (["policy=nosuch"], "choose one of: gru, lstm, markov, recursive, twohead"),
    (["algo.lrr=1e-3"], "did you mean algo.lr"),
    (["lrr=1e-3"], "did you mean algo.lr"),
    (["seed=abc"], "seed takes a whole number"),
    (["algo.lr=fast"], "algo.lr takes a finite number > 0"),
    (["policy.hidden=3"], "policy.hidden takes a list of whole numbers"),
    (["hydra/launcher=nosuch"], "choose one of: basic,"),
    # values that mean nothing
    (["epochs=0"], "epochs=0 is not allowed: epochs takes a whole number >= 1"),
    (["env.probs=[0.5,0.5]"], "slope takes no such key"),
    (["env=corridor", "env.workers=2"], "corridor takes no such key"),
    (["env=corridor", "wind=1e308"], "wind takes a finite number >= 0 and < 12"),
    (["env=corridor", "env.wind=0.1"], "set the corridor's wind with wind=0.1"),
    (
        ["env=gym", f"env.id={WALK_ID}", "env.configs=[{},{}]", "env.probs=[0.5,0.6]"],
        "sum to 1.1: p_M must sum to 1",
    ),
    (["precision=tf32"], "precision='tf32' is a GPU precision"),
    (["chunk_members=-1"], "chunk_members=-1"),
    # a population's members, each checked as the run composes it, before anything is written
    (["env=corridor", 'members=["seed=0 wind=-1","seed=1"]'], "member 'seed=0 wind=-1': wind=-1"),
    (['members=["seed=0","seed=1 algo.alpha=0.3"]'], "member 'seed=1 algo.alpha=0.3'"),
    (['members=["seed=0 policy=recursive","seed=1"]'], "these differ in policy.name"),
]


def run(capsys, *args: str) -> tuple[int, str]:
    with pytest.raises(SystemExit) as stopped:
        main(list(args))
    captured = capsys.readouterr()
    return stopped.value.code, captured.err + captured.out


def assert_one_line(code: int, text: str, expected: str) -> None:
    assert code == 2, text
    assert expected in text, text
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("hmepol: error: "), text
    assert "Traceback" not in text


@pytest.mark.parametrize("args, expected", TRAIN, ids=lambda a: a[0] if isinstance(a, list) else "")
@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_train_refuses_a_bad_value_in_one_line_and_writes_nothing(tmp_path, capsys, args, expected):
    run_dir = tmp_path / "run"
    code, text = run(capsys, "train", *args, f"hydra.run.dir={run_dir}")
    assert_one_line(code, text, expected)
    assert not run_dir.exists()


def test_a_sweep_refuses_a_bad_value_in_any_job(tmp_path, capsys):
    code, text = run(
        capsys, "sweep", "algo=alphamepol", "algo.alpha=0.5,2", "seed=0,1",
        f"hydra.sweep.dir={tmp_path / 's'}",
    )
    assert_one_line(code, text, "algo.alpha=2")
    assert not (tmp_path / "s").exists()


def test_output_folders_that_are_files_are_refused(tmp_path, capsys):
    file = tmp_path / "a_file"
    file.write_text("keep me")
    for command, key in (("train", "hydra.run.dir"), ("sweep", "hydra.sweep.dir")):
        assert_one_line(*run(capsys, command, f"{key}={file}"), "is a file")
    assert file.read_text() == "keep me"


def test_resume_of_a_file_or_a_folder_that_is_not_a_run(tmp_path, capsys):
    folder = tmp_path / "not_a_run"
    folder.mkdir()
    (folder / "notes.txt").write_text("keep me")
    assert_one_line(*run(capsys, "train", f"resume={folder}"), "not a hmepol run directory")
    assert_one_line(*run(capsys, "train", f"resume={folder / 'notes.txt'}"), "not a directory")
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]


FINETUNE = [
    (["max_kl=-1"], "max_kl=-1"),
    (["gamma=1.5"], "gamma=1.5"),
    (["gamma=nan"], "gamma=nan"),
    (["policy.bptt=zero"], "policy.bptt='zero'"),
    (["goal=somewhere"], "goal='somewhere'"),
    (["goal=[[0,0]]"], "goal=[0, 0]"),  # the slope world's central wall
    (["goal=[[5,5]]"], "goal=[5, 5]"),  # outside the arena
    (["epochs=0"], "epochs=0"),
    (["config=7"], "config=7"),
    (["env=moon"], "moon"),
    (["env.name=corridor"], "env=corridor"),
    (["init=/no/such/run"], "/no/such/run"),
    (["goal_size=5"], "goal_size=5"),
    (["wind=-2"], "wind=-2"),
    (["+foo=1"], "'foo'"),
    (["device=tpu"], "device='tpu'"),
    (["env=mountaincar", "goal=[[0,0]]"], "is fine-tuned on its own reward"),
    (["env=gym", "env.id=NoSuchEnv-v0"], "NoSuchEnv-v0"),
]


@pytest.mark.parametrize(
    "args, expected", FINETUNE, ids=lambda a: a[0] if isinstance(a, list) else ""
)
def test_finetune_refuses_a_bad_value_in_one_line_and_writes_nothing(
    tmp_path, capsys, args, expected
):
    out = tmp_path / "out"
    code, text = run(capsys, "finetune", *args, f"hydra.run.dir={out}", f"output_dir={out}")
    assert_one_line(code, text, expected)
    assert not out.exists()


class Payload:
    """Unpickling this calls open(marker, "w"): code a checkpoint must never run."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("kind", ["hostile", "corrupt", "not weights"])
def test_a_bad_checkpoint_is_refused_in_one_line_and_runs_no_code(tmp_path, capsys, kind):
    from tests.test_trpo import _fake_run

    run_dir = _fake_run(tmp_path)
    checkpoint = run_dir / "checkpoints" / "last.pt"
    marker = tmp_path / "pwned"
    if kind == "hostile":
        checkpoint.write_bytes(pickle.dumps({"policy": Payload(str(marker))}))
    elif kind == "corrupt":
        checkpoint.write_bytes(checkpoint.read_bytes()[:100])
    else:
        torch.save({"policy": {"weights": torch.zeros(3)}, "state_dim": 2, "action_dim": 2},
                   checkpoint)  # fmt: skip
    for init in (run_dir, checkpoint):
        code, text = run(capsys, "finetune", f"init={init}", f"output_dir={tmp_path / 'o'}")
        assert_one_line(code, text, str(checkpoint))
    assert not marker.exists() and not (tmp_path / "o").exists()


REPORT_AND_SHOW = [
    (["report", "/no/such/folder"], "/no/such/folder"),
    (["show", "env=moon"], "moon"),
    (["show", "env=gym"], "env=gym needs env.id"),
    (["show", "env=slope", "env.id=Pendulum-v1"], "slope takes no such key"),
    (["show", "env=gym", "env.id=NoSuchWorld-v0"], "not a registered Gymnasium id"),
    (["show", "wind=abc"], "abc"),
    (["show", "wind=-1"], "wind=-1.0"),
    (["show", "wind=inf"], "wind=inf"),
    (["show", "foo=1"], "foo"),
    (["nosuchcommand"], "nosuchcommand"),
]


@pytest.mark.parametrize(
    "args, expected", REPORT_AND_SHOW, ids=lambda a: "-".join(a) if isinstance(a, list) else ""
)
def test_report_show_and_unknown_commands_refuse_in_one_line(capsys, args, expected):
    assert_one_line(*run(capsys, *args), expected)


def test_a_report_into_a_file_is_refused(tmp_path, capsys):
    (tmp_path / "runs").mkdir()
    target = tmp_path / "report.html"
    target.write_text("keep")
    assert_one_line(
        *run(capsys, "report", str(tmp_path / "runs"), "--out", str(target)), "is a file"
    )


def _broken(*args, **kwargs):
    raise RuntimeError("a bug nobody foresaw")


@pytest.mark.parametrize("command", ["show", "report", "train"])
def test_an_unexpected_error_is_one_line_and_a_log_with_its_traceback(
    tmp_path, capsys, monkeypatch, command
):
    import hmepol_cli.cli as cli

    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.setattr(cli, {"show": "_show", "report": "_report", "train": "_train"}[command],
                        _broken)  # fmt: skip
    args = [f"hydra.run.dir={tmp_path / 'run'}"] if command == "train" else []
    code, text = run(capsys, command, *args)
    lines = [line for line in text.splitlines() if line.strip()]
    assert code == 1, text
    assert len(lines) == 1 and "unexpected RuntimeError: a bug nobody foresaw" in lines[0], text
    assert "Traceback" not in text
    log = lines[0].split("the traceback is in ")[1].split(";")[0]
    logged = open(log).read()
    assert "Traceback" in logged and "a bug nobody foresaw" in logged and "_broken" in logged


def test_debug_keeps_the_traceback(monkeypatch):
    import hmepol_cli.cli as cli

    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.setattr(cli, "_show", _broken)
    with pytest.raises(RuntimeError, match="a bug nobody foresaw"):
        main(["show", "--debug"])
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(RuntimeError, match="a bug nobody foresaw"):
        main(["show"])
