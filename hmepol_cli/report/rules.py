"""Which rules and settings made a group's runs, beside today's defaults: the edge and
backtracking rules a run ran with (run.json's ``edge`` and ``backtracking``; for a run.json
older than those keys, the rule its config meant: :data:`RULE_WITHOUT_SETTING`), and which of an
algorithm's groups ran at the algorithm's own settings (conf/algo/<name>.yaml: the thesis').
"""

from __future__ import annotations

from typing import Any

from hmepol_cli.report.defaults import algo_defaults, schema_defaults
from hmepol_cli.report.runs import Group, varying_keys

# The config key of each rule, and the run.json key that records the rule the run ran with.
RULE_KEYS = {"env.edge": "edge", "algo.backtracking": "backtracking"}
# The rule a config without the setting ran with, for a run.json that does not record it (made
# before it did, and not brought up to date by tools/backfill_run_json.py). The training code
# reads a missing setting so (hmepol_cli.envs.base.edge_rule, hmepol_cli.config.
# backtracking_rule): the settings came with today's rules, and a run started before them ran,
# and continues, with the rules of before.
RULE_WITHOUT_SETTING = {"env.edge": "mirror", "algo.backtracking": "first_step"}
# The worlds with an arena edge (hmepol_cli.envs' 2-D navigation worlds), for a run.json that
# records neither its edge rule nor its map; the others (a Gymnasium world) have no edge.
EDGED_WORLDS = ("slope", "corridor", "multigrid")
# Today's defaults of the rules (the schema's); a run made with another is said to be.
TODAY = {key: schema_defaults()[key] for key in RULE_KEYS}
# How long and how wide a run is, not how its algorithm works: left out of "thesis settings".
SCALE_KEYS = ("epochs", "algo.trajectories", "algo.horizon")


def _has_edge(config: dict[str, Any], meta: dict[str, Any]) -> bool:
    """Whether the run's world has an arena edge (a 2-D world): run.json records its edge rule,
    or, older than that key and the map, names one of those worlds."""
    if "edge" in meta:
        return True
    return "world_map" not in meta and config.get("env.name") in EDGED_WORLDS


def saved_rules(config: dict[str, Any], meta: dict[str, Any]) -> dict[str, str]:
    """The rules a run ran with (config key -> rule), from its run.json and, where that does not
    record them, its saved (flattened) config; the edge rule only for the worlds with edges."""
    rules = {}
    for key, recorded in RULE_KEYS.items():
        if key == "env.edge" and not _has_edge(config, meta):
            continue
        value = meta.get(recorded, config.get(key))
        rules[key] = RULE_WITHOUT_SETTING[key] if value is None else str(value)
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
