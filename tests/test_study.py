"""Prequential study: metrics by hand, learning tracks a drifting truth, outputs as a user sees them."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.jobs.evaluate import run_study, summarise, write_study
from vfm_core.jobs.study import mape, metrics_records, run_prequential
from vfm_core.simulate import simulate_field


def test_mape_hand_computed() -> None:
    # |110-100|/100 = 10 %, |45-50|/50 = 10 %, |200-200|/200 = 0 %, NaN prediction skipped
    assert mape([110.0, 45.0, 200.0, np.nan], [100.0, 50.0, 200.0, 80.0]) == pytest.approx(
        20.0 / 3.0
    )


def test_metrics_records_and_summary_by_hand() -> None:
    preds = pd.DataFrame(
        {
            "model": ["mm"] * 4,
            "method": ["ol"] * 4,
            "well": ["A", "A", "B", "B"],
            "predicted": [110.0, 90.0, 52.0, np.nan],
            "measured": [100.0, 100.0, 50.0, 50.0],
        }
    )
    records = metrics_records(preds)
    assert records == [
        {"model": "mm", "method": "ol", "well": "A", "mape": pytest.approx(10.0), "n": 2},
        {"model": "mm", "method": "ol", "well": "B", "mape": pytest.approx(4.0), "n": 1},
    ]
    (row,) = summarise(records)
    assert row["mean_mape"] == pytest.approx(7.0)


@pytest.fixture(scope="module")
def eroding_field():
    return simulate_field(wells=3, years=3.0, seed=11, start="2017-01-01", hidden=["erosion"])


def test_online_learning_tracks_erosion_and_beats_pbl_182d(eroding_field) -> None:
    from vfm_core.data import make_batch, target_mask

    frame = eroding_field.observations
    truth = eroding_field.truth_samples
    ol = run_prequential(frame, "mm", "ol", targets="all", track_parameters=True)
    pbl = run_prequential(frame, "mm", "pbl:182d", targets="all")
    frozen = run_prequential(
        frame, "mm", "pbl:3650d", targets="all"
    )  # the initial fit, never updated
    mape_ol = mape(ol.predictions["predicted"], ol.predictions["measured"])
    mape_pbl = mape(pbl.predictions["predicted"], pbl.predictions["measured"])
    assert mape_ol < mape_pbl, (mape_ol, mape_pbl)

    split = pd.Timestamp("2019-01-01", tz="UTC")
    wells = list(ol.final_model.wells)
    rows = np.flatnonzero(target_mask(frame, "all"))
    last = make_batch(frame, wells, rows)
    keep = last.mask & (
        torch.cumsum(last.mask.flip(1).long(), 1).flip(1) <= 50
    )  # latest 50 per well
    growth = ol.final_model.predict(last.x) / frozen.final_model.predict(last.x)
    params = ol.parameters[ol.parameters["name"] == "c_d"]
    coverage = []
    for j, well in enumerate(wells):
        t_truth = truth[truth["well"] == well]
        true_change = (
            t_truth["c_d_true"].iloc[-1] / t_truth.loc[t_truth["time"] < split, "c_d_true"].iloc[-1]
            - 1
        )
        assert true_change > 0.02  # the simulator did erode the choke
        # At fixed inputs the learned model now predicts a rate grown like the eroded choke.
        learned_growth = float(growth[j][keep[j]].mean()) - 1.0
        assert learned_growth > 0.4 * true_change, (well, learned_growth, true_change)
        g = params[params["well"] == well]
        c_d_change = g["value"].iloc[-1] / g.loc[g["time"] <= split, "value"].iloc[-1] - 1.0
        assert c_d_change > 0, (well, c_d_change)  # C_D moved toward the true trend
        coverage.append(c_d_change / true_change)
    # Only part of the growth lands in C_D: M_gas and p_cr scale the rate too, and plain
    # mm cannot tell them apart; `vfm diagnose` with the erosion effect isolates it.
    assert np.mean(coverage) > 0.2, coverage


def test_evaluate_outputs_follow_the_contract(tmp_path) -> None:
    frame = simulate_field(wells=2, years=1.2, seed=5, start="2018-06-01").observations
    result = run_study(
        frame,
        models=["last", "mm"],
        methods=["ol", "pbl:60d"],
        targets="all",
        progress=False,
        data_path="synthetic",
    )
    written = {p.name for p in write_study(result, tmp_path, report=False)}
    assert {"metrics.json", "predictions.parquet"} <= written
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["targets"] == "all" and metrics["split"].startswith("2019-01-01")
    assert {r["model"] for r in metrics["records"]} == {"last", "mm"}
    for r in metrics["records"]:
        assert set(r) == {"model", "method", "well", "mape", "n"} and r["n"] > 0 and r["mape"] > 0
    preds = pd.read_parquet(tmp_path / "predictions.parquet")
    assert set(preds.columns) >= {"time", "well", "model", "method", "predicted", "measured"}
    # every scored observation is after the split, predicted before being learned from
    assert (preds["time"] >= pd.Timestamp("2019-01-01", tz="UTC")).all()
    assert not list(tmp_path.glob(".staging-*"))
