"""Which rules and settings made a group's runs, beside today's defaults: the edge and
backtracking rules a run ran with (for a run older than the key, the rule the run package gives
it: :func:`~hmepol_cli.envs.base.edge_rule`, :func:`~hmepol_cli.config.backtracking_rule`), and
which of an algorithm's groups ran at the algorithm's own settings (conf/algo/<name>.yaml: the
thesis').
"""

from __future__ import annotations

from typing import Any

from hmepol_cli.config import AlgoConfig, EnvConfig, backtracking_rule
from hmepol_cli.envs import ENVIRONMENTS, NavigationWorld
from hmepol_cli.envs.base import edge_rule
from hmepol_cli.report.defaults import algo_defaults
from hmepol_cli.report.runs import Group, varying_keys

# Today's defaults of the rules (the schema's); a run made with another is said to be.
TODAY = {"env.edge": EnvConfig.edge, "algo.backtracking": AlgoConfig.backtracking}
# How long and how wide a run is, not how its algorithm works: left out of "thesis settings".
SCALE_KEYS = ("epochs", "algo.trajectories", "algo.horizon")


def saved_rules(config: dict[str, Any]) -> dict[str, str]:
    """The rules a run ran with, from its saved (flattened) config; the edge rule only for the
    2-D worlds, the only ones that have edges."""
    rules = {
        "algo.backtracking": backtracking_rule({"backtracking": config.get("algo.backtracking")})
    }
    world = ENVIRONMENTS.get(str(config.get("env.name")))
    if world is not None and issubclass(world, NavigationWorld):
        rules["env.edge"] = edge_rule({"edge": config.get("env.edge")})
    return rules


def old_rules(group: Group) -> dict[str, str]:
    """The rules of ``group``'s runs that are not today's defaults (key -> value)."""
    return {
        key: str(value)
        for key, today in TODAY.items()
        if (value := group.first.config.get(key, today)) != today
    }


def old_rules_text(groups: list[Group]) -> str:
    """'Made with the old rules (env.edge=mirror, algo.backtracking=first_step).', naming the
    groups when only some were; '' when every group ran with today's rules."""
    several_envs = len({g.env for g in groups}) > 1
    made = {f"{g.env} {g.label}" if several_envs else g.label: old_rules(g) for g in groups}
    made = {label: rules for label, rules in made.items() if rules}
    if not made:
        return ""

    def listed(rules: dict[str, str]) -> str:
        return ", ".join(f"{k}={v}" for k, v in rules.items())

    today = ", ".join(f"{k}={v}" for k, v in TODAY.items())
    if len(made) == len(groups) and len({listed(r) for r in made.values()}) == 1:
        text = f"Made with the old rules ({listed(next(iter(made.values())))})"
    else:
        text = "Made with the old rules: " + "; ".join(
            f"{label} ({listed(rules)})" for label, rules in made.items()
        )
    return f"{text}; today's defaults are {today}."


def thesis_settings(groups: list[Group]) -> set[str]:
    """Labels of the groups that ran at their algorithm's own settings where that algorithm has
    several groups in ``groups`` (one env and wind): every key in which its groups differ (the
    runs' scale aside) has the value conf/algo/<algo>.yaml gives it."""
    found = set()
    for algo in dict.fromkeys(g.algo for g in groups):
        same = [g for g in groups if g.algo == algo]
        defaults = algo_defaults(algo)
        if len(same) < 2 or defaults is None:
            continue
        keys = [
            k
            for k in varying_keys([g.first for g in same])
            if k not in SCALE_KEYS and k not in ("wind", "env.name", "algo.name")
        ]
        for group in same:
            if all(k in defaults and group.first.config.get(k) == defaults[k] for k in keys):
                found.add(group.label)
    return found
