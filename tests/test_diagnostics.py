"""The drop diagnostics on runs whose epochs sample only some configurations (multigrid)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from hmepol_cli.report.diagnostics import DROP_FROM, DROP_NATS, drop_table, entropy_changes
from hmepol_cli.report.runs import Group, Run


def sampled_run() -> Run:
    """Three configurations, each epoch sampling some of them (NaN: not sampled): epoch
    DROP_FROM + 2 has a fall of 2 nats in configuration 1; DROP_FROM + 3 samples a configuration
    the epoch before did not, so no configuration has a change there."""
    n = DROP_FROM + 5
    table = np.full((n, 3), np.nan)
    table[:, 1] = 1.0
    table[DROP_FROM + 2, 1] = -1.0
    table[DROP_FROM + 3, 1] = np.nan
    table[DROP_FROM + 3, 0] = 0.5
    table[:, 2] = np.where(np.arange(n) % 2 == 0, 2.0, np.nan)
    epochs = pd.DataFrame(table, columns=["entropy_c0", "entropy_c1", "entropy_c2"])
    epochs.insert(0, "epoch", range(n))
    epochs["entropy"] = np.nanmean(table, axis=1)
    meta = {"seed": 0, "env": "multigrid", "algo": "hmepol", "config_names": ["a", "b", "c"]}
    return Run(Path("run"), {"env.name": "multigrid", "algo.name": "hmepol"}, meta, epochs)


def test_an_epoch_where_no_configuration_changed_has_no_change_and_no_configuration():
    changes = entropy_changes(sampled_run())
    assert changes.loc[DROP_FROM + 2, "change"] == -2.0
    assert changes.loc[DROP_FROM + 2, "config"] == "1"
    empty = changes.loc[DROP_FROM + 3]
    assert np.isnan(empty["change"]) and pd.isna(empty["config"])


def test_the_drop_table_counts_the_one_drop_of_a_sampled_run():
    run = sampled_run()
    group = Group(key=(), runs=[run], label="HMepol")
    row = drop_table([group]).iloc[0]
    assert 2.0 > DROP_NATS
    assert row["drops"] == 1 and row["drops_c1"] == 1 and row["drop_epochs"] == str(DROP_FROM + 2)
