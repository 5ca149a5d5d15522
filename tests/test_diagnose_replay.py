"""The diagnosis under the well's own learning method (format 3): the live baseline is the
replay of that method, candidates are tested with paired block tests under one
Benjamini-Hochberg family, a candidate that raises the error is never offered, a well's
diagnosis stands beside its pool, and hybrids are identified on their mechanistic core.

Kept small for the suite's budget: 3 wells over 3 years (seeds no other test uses), the
replay with ``bayes`` (a Kalman filter: a real learning method, and fast), two candidates.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path

import pandas as pd
import pytest

from vfm_core.jobs.diagnose import Diagnosis, format_summary, run_diagnosis, write_diagnosis
from vfm_core.jobs.study import mape, run_prequential
from vfm_core.simulate import simulate_field

SPLIT = "2018-07-01"


@cache
def _frame(hidden: str, seed: int) -> pd.DataFrame:
    field = simulate_field(
        wells=3,
        years=3.0,
        seed=seed,
        start="2016-07-01",
        hidden=[] if hidden == "none" else [hidden],
    )
    return field.observations


@cache
def _diagnose(hidden: str, seed: int, well: str | None = None) -> Diagnosis:
    return run_diagnosis(
        _frame(hidden, seed),
        "mm",
        method="bayes",
        split=SPLIT,
        candidates=["erosion", "critical_ratio"],
        suggest=False,
        well=well,
    )


def test_the_live_baseline_is_the_replay_of_the_wells_method() -> None:
    diag = _diagnose("erosion:rate=0.3", 41)
    frame = _frame("erosion:rate=0.3", 41)
    replay = run_prequential(frame, "mm", "bayes", split=pd.Timestamp(SPLIT, tz="UTC"))
    expected = mape(replay.predictions["predicted"], replay.predictions["measured"])
    assert diag.live["mape"] == pytest.approx(expected, rel=1e-6)
    assert diag.headline["baseline_mape"] == pytest.approx(expected, rel=1e-6)
    assert diag.headline["method"] == "bayes"
    # the outage protocol scores only inside its windows, where nothing is learned
    assert diag.outage["windows"] >= 3 and 0 < diag.outage["n"] < diag.live["n"]


def test_strong_wear_is_the_verdict_with_intervals_and_evidence() -> None:
    diag = _diagnose("erosion:rate=0.3", 41)
    summary = format_summary(diag)
    assert diag.verdict_kind == "effect" and diag.verdict_effect == "erosion", summary
    erosion = next(c for c in diag.candidates if c.effect == "erosion")
    assert erosion.replayed and erosion.offer and erosion.raises_error is False
    live = erosion.test("live")
    assert live is not None and live["change"] < 0 and live["rejected"]
    assert live["low"] <= live["change"] <= live["high"]
    # the change is the difference of the two replays' MAPE on the same measurements
    assert live["change"] == pytest.approx(live["mape"] - live["base_mape"])
    assert live["base_mape"] == pytest.approx(diag.live["mape"], rel=1e-6)
    data = diag.to_json()
    assert data["format"] == "vfm-diagnosis/3"
    assert data["verdict"]["live"]["change"] == pytest.approx(live["change"])
    assert "Benjamini-Hochberg" in data["fdr"]["procedure"]
    assert data["fit_once"]["verdict"]["kind"] in ("effect", "driver", "noise")


def test_a_candidate_that_raises_the_error_is_never_offered() -> None:
    for diag in (_diagnose("erosion:rate=0.3", 41), _diagnose("none", 42)):
        for c in diag.candidates:
            t = c.test("live")
            if c.replayed and t is not None and t["change"] is not None and t["change"] > 0:
                assert c.raises_error and not c.offer, format_summary(diag)
            if c.offer:
                assert t is not None and t["change"] <= 0
        for v in diag.well_verdicts.values():
            if v["kind"] == "effect":
                assert v["live"]["change"] <= 0


def test_a_clean_field_is_noise_for_the_field_and_every_well() -> None:
    diag = _diagnose("none", 42)
    summary = format_summary(diag)
    assert diag.verdict_kind == "noise", summary
    assert {v["kind"] for v in diag.well_verdicts.values()} == {"noise"}, summary
    assert diag.fdr["rejected"] == 0 or all(not c.offer for c in diag.candidates), summary


def test_a_wells_diagnosis_stands_beside_its_pool(tmp_path: Path) -> None:
    diag = _diagnose("erosion:rate=0.3", 41, "W02")
    assert diag.pool["focus"] == "W02" and diag.pool["wells"] == ["W01", "W02", "W03"]
    erosion = next(c for c in diag.candidates if c.effect == "erosion")
    field, mine = erosion.test("live"), erosion.test("live", "W02")
    assert field is not None and mine is not None and mine is not field
    # one well's evidence is weaker: fewer blocks, a larger p-value
    assert mine["n_blocks"] < field["n_blocks"] and mine["p_value"] >= field["p_value"]
    assert diag.headline["baseline_mape"] == pytest.approx(diag.live["per_well"]["W02"]["mape"])
    if diag.verdict_kind == "effect":
        assert "this well alone" in diag.verdict
    write_diagnosis(diag, tmp_path)
    data = json.loads((tmp_path / "diagnosis.json").read_text())
    assert set(data["well_verdicts"]) == {"field", "W01", "W02", "W03"}
    page = (tmp_path / "report.html").read_text()
    assert "What adding each candidate does" in page and "W02 (diagnosed)" in page


def test_hybrids_are_identified_on_their_mechanistic_core() -> None:
    diag = run_diagnosis(
        _frame("erosion:rate=0.3", 41),
        "ham",
        method="pbl:3650d",
        split=SPLIT,
        candidates=["erosion"],
        suggest=False,
        replay_top=1,
        outage=None,
        shifts=0,
    )
    assert diag.screen_model == "mm" and diag.to_json()["fit_once"]["model"] == "mm"
    assert any("mechanistic core" in n for n in diag.notes)
    erosion = diag.candidates[0]
    assert erosion.replayed and erosion.live_run is not None
    assert erosion.live_run.model.startswith("ham")


def test_a_service_diagnosis_replays_the_wells_own_method_beside_its_pool() -> None:
    """Over HTTP the method is the well's own (its API snapshot) unless the request names
    one; from a store, the pool is the wells that run the same model and method."""
    from service.http.diagnosis import request_method
    from vfm_core.jobs.diagnose import pool_frame, stored_method

    assert request_method({"method": "bayes"}, None) == "bayes"
    assert request_method({"method": "bayes"}, "ol") == "ol"
    assert request_method({}, None) == "ol"
    frame = _frame("none", 42).copy()
    frame.attrs["models"] = {
        "W01": {"model": "mm", "effects": [], "method": "bayes"},
        "W02": {"model": "mm", "effects": ["erosion"], "method": "bayes"},
        "W03": {"model": "mm", "effects": [], "method": "bayes"},
    }
    pooled, note = pool_frame(frame, "W01")
    assert sorted(set(pooled["well"])) == ["W01", "W03"] and "W03" in note
    assert pooled.attrs["models"] == frame.attrs["models"]
    assert stored_method(pooled, "W01") == "bayes" and stored_method(pooled, None) == "bayes"
    frame.attrs["models"] = {}
    assert sorted(set(pool_frame(frame, "W02")[0]["well"])) == ["W01", "W02", "W03"]
    assert stored_method(frame, "W02") is None
