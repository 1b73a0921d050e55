"""The config a command would run, composed and checked before anything is written.

``hmepol`` composes every config a command would run with Hydra's compose API (each job of a
sweep), refuses keys the schema lacks and output folders that are files, and validates the
values (:func:`hmepol_cli.config.validate`), so a mistake is one line and nothing is written.
Hydra's and OmegaConf's own errors are turned into that one line here: the unknown key with
the names it is close to, the options of a group, what kind of value a key takes.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from hmepol_cli import sweeps
from hmepol_cli.config import check_rules, validate
from hmepol_cli.errors import ConfigError
from hmepol_cli.resume import resumed_config
from hmepol_cli.run import run_config

CONFIG_MODULE = "hmepol_cli.conf"  # the configs, shipped inside the package


def compose(config_name: str, overrides: list[str]) -> DictConfig:
    """The config ``overrides`` compose to (Hydra's own keys left out), or one clear line."""
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
            return compose_here(config_name, overrides)
    finally:
        GlobalHydra.instance().clear()


def compose_here(config_name: str, overrides: list[str], with_hydra: bool = False) -> DictConfig:
    """:func:`compose` in the Hydra session already open; ``with_hydra``: Hydra's own node
    too, with the overrides of its keys (the config a job of it runs with)."""
    from hydra import compose as hydra_compose

    task = [o for o in overrides if not o.lstrip("+~").startswith("hydra")]
    _check_flags(task, config_name)
    try:
        return hydra_compose(
            config_name=config_name,
            overrides=overrides if with_hydra else task,
            return_hydra_config=with_hydra,
        )
    except (HydraException, OmegaConfBaseException) as error:
        raise ConfigError(_hydra_message(error, config_name)) from None
    except AssertionError:  # OmegaConf, setting a key below a group left at null
        nested = [o for o in task if "." in o.partition("=")[0]]
        raise ConfigError(
            f"cannot apply {' '.join(nested) or ' '.join(task)}: choose its group first "
            "(e.g. env=corridor, not env.name=corridor)"
        ) from None


def _check_flags(overrides: list[str], config_name: str) -> None:
    """A true-or-false setting takes true or false (OmegaConf would read 2 as true)."""
    from hmepol_cli.config import rules_of

    rules = rules_of(_schema(config_name))
    for item in overrides:
        key = item.lstrip("+~").partition("=")[0]
        rule = rules.get(key)
        if rule is None or rule.kind != "bool":
            continue
        try:
            (override,) = sweeps.parse([item])
        except (HydraException, ValueError):
            continue  # Hydra's own message, below
        if not override.is_sweep_override() and not isinstance(override.value(), bool):
            value = item.partition("=")[2]
            raise ConfigError(f"{key}={value!r} is not allowed: {key} takes {rule.describe()}")


def _hydra_message(error: Exception, config_name: str = "config") -> str:
    """Hydra's and OmegaConf's errors, as one line that says what is allowed."""
    text = str(error)
    key = re.search(r"Key '([^']+)' (?:is )?not in", text) or re.search(
        r"Could not override '([^']+)'", text
    )
    if key:
        return _unknown_key(key.group(1), config_name)
    choice = re.search(r"Could not find '([^']+)/([^'/]+)'", text)
    if choice:
        group, name = choice.groups()
        options = _group_options(group)
        listed = f"; choose one of: {', '.join(options)}" if options else ""
        return f"{group}={name!r} is not an option of {group}{listed}"
    merging = re.search(r"Error merging override (\S+?)=(.*)", text)
    if merging:
        name, value = merging.groups()
        kind = _schema_kind(name.lstrip("+~"), config_name)
        return f"{name}={value!r} is not allowed: {name} takes {kind}"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    unread = re.search(r"LexerNoViableAltException: (\S+?)=(.*)", text)
    if unread or "no viable alternative" in text or "mismatched input" in text:
        name, value = unread.groups() if unread else (None, None)
        quoting = "quote a value with spaces or other letters: key='value'"
        if name is None:
            return f"{lines[0] if lines else type(error).__name__}: cannot read it ({quoting})"
        kind = _schema_kind(name.lstrip("+~"), config_name)
        return f"{name}={value!r} cannot be read ({quoting}); {name} takes {kind}"
    return lines[0] if lines else type(error).__name__


def _schema(config_name: str):
    from hmepol_cli.config import Config, FinetuneConfig

    return FinetuneConfig if config_name == "finetune" else Config


def _schema_keys(cls, prefix: str = "") -> list[str]:
    """Every dotted key of a schema dataclass."""
    import dataclasses
    import typing

    keys = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        inner = [t for t in typing.get_args(hints[f.name]) or [hints[f.name]]
                 if dataclasses.is_dataclass(t)]  # fmt: skip
        keys.append(f"{prefix}{f.name}")
        if inner:
            keys += _schema_keys(inner[0], f"{prefix}{f.name}.")
    return keys


def _unknown_key(key: str, config_name: str) -> str:
    import difflib

    keys = _schema_keys(_schema(config_name))
    near = difflib.get_close_matches(key, keys, n=3, cutoff=0.6)
    if not near:  # the right name in the wrong place (lr for algo.lr)
        leaves = {k.rpartition(".")[2]: k for k in keys}
        near = [leaves[m] for m in difflib.get_close_matches(key, list(leaves), n=2, cutoff=0.6)]
    hint = f"; did you mean {' or '.join(near)}?" if near else " (--help lists the settings)"
    return f"unknown key {key!r}: not a hmepol setting{hint}"


def _group_options(group: str) -> list[str]:
    """The options of a config group: its YAML files (hydra/launcher: ours and Hydra's)."""
    from importlib.resources import files

    folder = files(CONFIG_MODULE).joinpath(*group.split("/"))
    options = sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))
    if group == "hydra/launcher":
        options = sorted({*options, "basic", "joblib", "submitit_local", "submitit_slurm"})
    return options


def _schema_kind(key: str, config_name: str) -> str:
    """What a key of the schema takes, in words: its rule's (hmepol_cli/config.py)."""
    from hmepol_cli.config import rules_of

    rule = rules_of(_schema(config_name)).get(key)
    return rule.describe() if rule is not None else "another kind of value"


def override_value(item: str) -> str:
    """The value of one ``key=value`` override as Hydra reads it: quotes taken off
    (``resume='/runs/dir with spaces/run'``), escapes undone. Every path a user gives (resume=,
    init=, report's folders, hydra.run.dir, hydra.sweep.dir, output_dir) goes through here."""
    raw = item.partition("=")[2]
    try:
        (override,) = sweeps.parse([item])
    except (HydraException, ValueError):
        return unquote(raw)
    if override.is_sweep_override():
        return raw
    value = override.value()
    return value if isinstance(value, str) else raw


def unquote(text: str) -> str:
    """A path written the way Hydra quotes one, without its quotes ('a b' -> a b)."""
    text = text.strip()
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    return text


def given_keys(overrides: list[str]) -> list[str]:
    """The settings an override list sets (``+a.b=1`` -> ``a.b``), Hydra's own left out."""
    keys = [o.lstrip("+~").partition("=")[0] for o in overrides]
    return [k for k in keys if k and not k.startswith("hydra")]


def check_applies(cfg: DictConfig, overrides: list[str], schema=None) -> None:
    """Refuse a setting given on the command line that the chosen world or objective does not
    use (wind on the slope, alpha on Mepol's mean objective): it would change nothing."""
    from hmepol_cli.config import not_applicable

    found = not_applicable(cfg, given_keys(overrides), schema)
    if found:
        raise ConfigError(f"{found[0]}; leave it out")


def check_known_keys(cfg: DictConfig, schema: DictConfig, prefix: str = "") -> None:
    """Refuse keys the schema does not have (Hydra lets ``+key=value`` add any)."""
    for key in cfg:
        path = f"{prefix}{key}"
        if key not in schema:
            raise ConfigError(_unknown_key(path, "config"))
        node, spec = cfg[key], schema[key]
        if OmegaConf.is_dict(node) and OmegaConf.is_dict(spec):
            check_known_keys(node, spec, f"{path}.")


def check_output_dirs(overrides: list[str]) -> None:
    """An output folder given on the command line must be a folder, if it exists; a launcher
    must be one there is."""
    for item in overrides:
        key, _, value = item.partition("=")
        if key == "hydra/launcher" and value not in _group_options("hydra/launcher"):
            options = ", ".join(_group_options("hydra/launcher"))
            raise ConfigError(
                f"hydra/launcher={value!r} is not a launcher; choose one of: {options}"
            )
    for item in overrides:
        key, value = item.partition("=")[0], override_value(item)
        if key in ("hydra.run.dir", "hydra.sweep.dir", "output_dir") and value:
            if Path(value).exists() and not Path(value).is_dir():
                raise ConfigError(f"{key}={value!r} is a file, not a folder")


def check_train(overrides: list[str]) -> DictConfig:
    """The config of ``hmepol train overrides``, checked, before Hydra writes anything."""
    check_output_dirs(overrides)
    return check_config(compose("config", overrides), overrides, compose)


def check_config(
    cfg: DictConfig, overrides: list[str], compose_with: Callable[..., DictConfig]
) -> DictConfig:
    """``cfg``, the config ``overrides`` composed to (Hydra's reading of every value, quoted
    paths too), checked: its keys, its values, a resumed run's, every population member's
    (composed with ``compose_with``). -> the config the run has (a resumed run's own)."""
    from hmepol_cli.config import Config

    check_known_keys(cfg, OmegaConf.structured(Config))
    if cfg.resume is not None:
        run_config(Path(cfg.resume))  # a clear error for a folder that is not a run
        cfg = resumed_config(cfg, Path(cfg.resume), overrides)
    validate(cfg)
    if cfg.resume is None:  # a continued run keeps what it started with
        check_applies(cfg, overrides)
    if cfg.seeds or cfg.members:
        check_members_of(cfg, overrides, compose_with)
    return cfg


def check_members_of(
    cfg: DictConfig, overrides: list[str], compose_with: Callable[..., DictConfig]
) -> None:
    """Each member of a population (``seeds=[...]``, ``members=[...]``) composed as the run will
    compose it, and validated, before anything is written; a refusal names the member."""
    from hmepol_cli.members import check_members, common_overrides, member_config, member_overrides

    common = common_overrides(overrides)
    members = []
    for own in member_overrides(cfg):
        try:
            member = member_config(cfg, common, own, compose_with)
            validate(member)
            check_applies(member, [*common, *own])
        except ConfigError as error:
            raise ConfigError(f"member {' '.join(own)!r}: {error}") from None
        members.append(member)
    check_members(members)


def check_sweep(overrides: list[str]) -> int:
    """Check the config of every job a sweep would run, before anything is written. -> jobs"""
    check_output_dirs(overrides)
    task = [o for o in overrides if not o.lstrip("+~").startswith("hydra")]
    try:
        jobs = sweeps.jobs(task)
    except HydraException as error:
        raise ConfigError(_hydra_message(error, "config")) from None
    seen = set()
    for job in jobs:
        key = tuple(job)
        if key not in seen:
            seen.add(key)
            check_train(list(job))
    return len(jobs)


def check_finetune_overrides(overrides: list[str]) -> DictConfig:
    """The config of ``hmepol finetune overrides``, checked (its targets included), before
    Hydra writes anything."""
    from hmepol_cli.config import FinetuneConfig
    from hmepol_cli.finetune import check_finetune

    check_output_dirs(overrides)
    cfg = compose("finetune", overrides)
    check_known_keys(cfg, OmegaConf.structured(FinetuneConfig))
    check_rules(cfg, FinetuneConfig)
    check_finetune(cfg)
    return cfg
