"""Every setting of the schema has a rule, and every rule refuses what it does not accept.

The fuzz test enumerates the schema's fields itself (``schema_fields``), draws one and a value of
a kind its rule does not accept (wrong type, out of range, a huge whole number, a negative, NaN
or inf, an empty list, an unknown choice, text with spaces or other letters), runs the command's
entry point in-process and expects exit 2, one line naming the field and what is allowed, no
traceback and no folder. A field without a rule makes it fail."""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hmepol_cli.cli import main
from hmepol_cli.config import Config, FinetuneConfig, Rule, rules_of, schema_fields

WORDS = ("takes", "choose", "must", "allowed", "only to")


def bad_values(rule: Rule) -> list[str]:
    """Overrides of kinds a rule does not accept, derived from the rule alone."""
    low = rule.at_least if rule.at_least is not None else rule.above
    negative = ["-1"] if low is not None and low >= 0 else []
    if rule.kind == "other":
        return list(rule.bad)
    if rule.kind == "int":
        too_big = [] if rule.at_most is None and rule.below is None else ["1000000000"]
        return ["abc", "1.5", str(10**30), "nan", "inf", "'a b'", "é", *negative, *too_big]
    if rule.kind == "float":
        high = ["1e308"] if rule.at_most is not None or rule.below is not None else []
        return ["abc", "nan", "inf", "-inf", "[1]", "'a b'", "ü", *negative, *high]
    if rule.kind == "bool":
        return ["maybe", "2", "'a b'", "[]"]
    if rule.kind == "text":
        return ["[1,2]", *([] if rule.null else ["null"])]
    if rule.kind == "choice":
        return ["nosuch", "'a b'", "é", "[1]", "1"]
    item_negative = [f"[{v}]" for v in negative]
    empty = ["[]"] if rule.nonempty else []
    if rule.kind == "ints":
        return ["3", "[1.5]", "[abc]", f"[{10**30}]", "'a b'", *empty, *item_negative]
    if rule.kind == "floats":
        return ["3", "[nan]", "[inf]", "[abc]", *empty, *item_negative]
    raise AssertionError(f"rule kind {rule.kind!r} has no bad values")


# What makes a field apply: its world, its objective, its logger.
def base(key: str, rule: Rule) -> list[str]:
    if key.startswith("logger.wandb."):
        return ["logger=[csv,wandb]"]
    if key.startswith("logger.mlflow."):
        return ["logger=[csv,mlflow]"]
    if rule.worlds:
        return ["env=mountaincar" if "gym" in rule.worlds else f"env={rule.worlds[0]}"]
    if rule.objectives:
        return ["algo=alphamepol"]
    return []


def run_in_empty_folder(args: list[str]) -> tuple[int, str, list[str]]:
    """main(args) in a fresh working folder -> exit code, what it printed, what it left."""
    here = os.getcwd()
    with tempfile.TemporaryDirectory() as folder:
        os.chdir(folder)
        out = io.StringIO()
        try:
            with contextlib.redirect_stderr(out), contextlib.redirect_stdout(out):
                with pytest.raises(SystemExit) as stopped:
                    main([*args, f"hydra.run.dir={folder}/run"])
        finally:
            os.chdir(here)
        return stopped.value.code, out.getvalue(), sorted(os.listdir(folder))


def assert_refused(key: str, code: int, text: str, left: list[str]) -> None:
    lines = [line for line in text.splitlines() if line.strip()]
    assert code == 2, text
    assert len(lines) == 1 and lines[0].startswith("hmepol: error: "), text
    assert key in lines[0], text  # the field
    assert any(word in lines[0] for word in WORDS), text  # and what is allowed
    assert "Traceback" not in text
    assert left == [], left


TRAIN_FIELDS = schema_fields(Config)
# finetune's env.* and policy.* share train's rules (the same ENV_RULES, POLICY_RULES)
FINETUNE_FIELDS = [
    k for k in schema_fields(FinetuneConfig) if not k.startswith(("env.", "policy."))
]


@pytest.mark.parametrize("cls", [Config, FinetuneConfig], ids=["train", "finetune"])
def test_every_schema_field_has_a_rule_and_every_rule_a_field(cls):
    fields, rules = set(schema_fields(cls)), set(rules_of(cls))
    assert fields - rules == set(), "settings without a rule (hmepol_cli/config.py RULES)"
    assert rules - fields == set(), "rules of no setting"
    for key in fields:
        assert bad_values(rules_of(cls)[key]), f"{key}: its rule names no value it refuses"


def test_a_field_without_a_rule_is_found(monkeypatch):
    """The check above can fail: a setting added to the schema but not to the rules."""
    import hmepol_cli.config as config

    trimmed = {k: v for k, v in config.RULES.items() if k != "epochs"}
    monkeypatch.setattr(config, "RULES", trimmed)
    assert set(schema_fields(Config)) - set(rules_of(Config)) == {"epochs"}


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_train_refuses_any_bad_value_of_any_field(data):
    key = data.draw(st.sampled_from(TRAIN_FIELDS), label="field")
    rule = rules_of(Config)[key]
    value = data.draw(st.sampled_from(bad_values(rule)), label="value")
    code, text, left = run_in_empty_folder(["train", *base(key, rule), f"{key}={value}"])
    assert_refused(key, code, text, left)


@settings(max_examples=15, deadline=None)
@given(st.data())
def test_finetune_refuses_any_bad_value_of_any_field(data):
    key = data.draw(st.sampled_from(FINETUNE_FIELDS), label="field")
    value = data.draw(st.sampled_from(bad_values(rules_of(FinetuneConfig)[key])), label="value")
    code, text, left = run_in_empty_folder(["finetune", f"{key}={value}", "output_dir=ft"])
    assert_refused(key, code, text, left)


def test_precision_fp8_is_refused_with_the_precisions_there_are():
    code, text, left = run_in_empty_folder(["train", "precision=fp8"])
    assert_refused("precision", code, text, left)
    assert "precision='fp8'" in text and "float32, float64, bf16, tf32, auto" in text


def test_seeds_3_is_refused_with_an_example_of_seeds():
    code, text, left = run_in_empty_folder(["train", "seeds=3"])
    assert_refused("seeds", code, text, left)
    assert "seeds=[0,1,2]" in text and "[300,300]" not in text


@pytest.mark.parametrize(
    "args, named",
    [
        (["env=slope", "wind=0.3"], "wind=0.3 does not apply to env=slope"),
        (["env=multigrid", "wind=0.1"], "wind=0.1 does not apply to env=multigrid"),
        (["algo=mepol", "algo.alpha=0.2"], "algo.alpha=0.2 does not apply to algo=mepol"),
        (["algo=hmepol", "algo.alpha=0.5"], "algo.alpha=0.5 does not apply to algo=hmepol"),
    ],
)
def test_a_setting_that_does_not_apply_is_refused(args, named):
    code, text, left = run_in_empty_folder(["train", *args])
    assert_refused(named.partition("=")[0], code, text, left)
    assert named in text


def test_a_setting_that_applies_is_accepted():
    from hmepol_cli.checks import check_train

    assert check_train(["env=corridor", "wind=0.3"]).wind == 0.3
    assert check_train(["algo=alphamepol", "algo.alpha=0.2"]).algo.alpha == 0.2


def test_a_swept_value_that_does_not_apply_is_refused_before_any_job(tmp_path, capsys):
    with pytest.raises(SystemExit) as stopped:
        main(["sweep", "env=corridor,slope", "wind=0.1", f"hydra.sweep.dir={tmp_path / 's'}"])
    assert stopped.value.code == 2
    assert "wind=0.1 does not apply to env=slope" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_hydra_quoting_is_read_the_same_everywhere():
    from hmepol_cli.checks import override_value, unquote

    for written in ("resume='/a/dir with spaces/run'", 'resume="/a/dir with spaces/run"',
                    "resume=/a/dir with spaces/run"):  # fmt: skip
        assert override_value(written) == "/a/dir with spaces/run"
    assert unquote("'/runs/x y'") == "/runs/x y" and unquote("/runs/'x'") == "/runs/'x'"
    assert override_value("hydra.sweep.dir='out/my sweep'") == "out/my sweep"
    assert Path(override_value("init='/r/a b@3'")).name == "a b@3"


def test_importing_the_cli_registers_nothing():
    """The schema, the resolvers and the launcher are registered by setup() (main calls it),
    not by importing the module."""
    import subprocess
    import sys

    code = (
        "import hmepol_cli.cli\n"
        "from hydra.core.config_store import ConfigStore\n"
        "from omegaconf import OmegaConf\n"
        "assert 'config_schema.yaml' not in ConfigStore.instance().repo\n"
        "assert not OmegaConf.has_resolver('hmepol_run_dir')\n"
        "hmepol_cli.cli.setup()\n"
        "assert 'config_schema.yaml' in ConfigStore.instance().repo\n"
        "assert OmegaConf.has_resolver('hmepol_run_dir')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr


TINY = ["algo.trajectories=4", "algo.horizon=20", "algo.batch_size=2", "algo.max_off_iters=2",
        "estimator.k=3", "policy.hidden=[8]", "eval.trajectories=2", "eval.horizon=10",
        "progress=false"]  # fmt: skip


@pytest.mark.slow  # end to end: runs of the installed command (make test runs it)
def test_hydra_quoted_paths_with_spaces_work_for_resume_and_init(tmp_path, capsys):
    """hydra.run.dir, resume= and init= quoted the way Hydra quotes, in a folder with spaces."""
    import json

    run = tmp_path / "dir with spaces" / "run 1"
    main(["train", *TINY, "epochs=1", f"hydra.run.dir='{run}'"])
    assert json.loads((run / "run.json").read_text())["epochs_done"] == 1
    main(["train", f"resume='{run}'", "epochs=2"])
    assert json.loads((run / "run.json").read_text())["epochs_done"] == 2
    out = tmp_path / "fine tuned"
    main(["finetune", f"init='{run}'", "epochs=1", "episodes=2", "horizon=10", "targets=1",
          "config=0", "progress=false", f"hydra.run.dir='{out}'"])  # fmt: skip
    assert (out / "finetune.csv").exists()
    assert not list(tmp_path.glob("*'*"))  # no folder named with a quote
    capsys.readouterr()
