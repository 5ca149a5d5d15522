"""A service's store diagnosed with the history it was fitted on (``with_history``).

The replay must start where the service started: the history file's rows before the
service's ``history_until`` in front of the store's rows from then on, the split there.
The end-to-end check (the replayed baseline equals the error the service recorded) is in
``tests/test_service_workbench.py``; here the join itself and the CLI's refusals.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from vfm_core.cli import main
from vfm_core.jobs.diagnose import with_history
from vfm_core.simulate import simulate_field


def _frames() -> tuple[pd.DataFrame, pd.DataFrame]:
    history = simulate_field(wells=2, years=0.5, seed=3).observations
    history["time"] = pd.to_datetime(history["time"], utc=True)
    store = history[history["time"] >= pd.Timestamp("2016-03-01", tz="UTC")].copy()
    store = store[store["well"] == "W01"].reset_index(drop=True)
    store["predicted"] = 1.0  # a store column the history lacks
    store.attrs["models"] = {"W01": {"model": "mm", "effects": [], "method": "ol"}}
    return history, store


def test_the_history_goes_in_front_of_the_store_and_sets_the_split() -> None:
    history, store = _frames()
    until = "2016-04-01"
    joined, split, note = with_history(store, history, until)
    ts = pd.Timestamp(until, tz="UTC")
    assert split == ts
    # only the store's wells; the history's rows before the split, the store's after it
    assert set(joined["well"]) == {"W01"}
    before, after = joined[joined["time"] < ts], joined[joined["time"] >= ts]
    own = history[(history["well"] == "W01") & (history["time"] < ts)]
    assert len(before) == len(own) and before["predicted"].isna().all()
    assert len(after) == int((store["time"] >= ts).sum()) and (after["predicted"] == 1.0).all()
    assert joined["time"].is_monotonic_increasing
    assert joined.attrs["models"] == store.attrs["models"]  # the store's record is kept
    assert "before 2016-04-01" in note and "left out" in note  # stored rows the history has


def test_the_cli_refuses_a_history_without_a_store(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    history, _ = _frames()
    data = tmp_path / "field.parquet"
    history.to_parquet(data)
    code = main(["diagnose", str(data), "--out", str(tmp_path / "d"), "--history", str(data)])
    assert code != 0
    assert "--history goes with --store" in capsys.readouterr().err
