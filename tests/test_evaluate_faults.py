"""`vfm evaluate` does at an instrument fault what the service does (issue 39, item 3).

While an input is flagged (frozen, out of range) the study predicts its rows with the
input's stand-in and a widened interval, and it learns nothing from the measurements paired
with a fault that holds learning (vfm_core.jobs.study_faults, the same vfm_core functions as
service/engine/learning.py and pairing.py). A field without a fault is studied exactly as
before.

The field (seed 6151, used by no other test, set no threshold): two wells; W01's rows
before the split removed, so that it starts after it in the service (streamed from the
split, its detectors see every row of it, as the study's) and in the study alike; its
``p_up`` frozen for 45 days from 200 days after its first row (a frozen ``p_down`` holds
nothing where the flow is critical, as W01's is: tests/test_sensor_hold.py).
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from vfm_core.faults_sim import inject_fault
from vfm_core.jobs.evaluate import run_study, write_study
from vfm_core.jobs.study import run_prequential
from vfm_core.jobs.study_faults import plan_sensor_faults
from vfm_core.learning import DEFAULT_TRAIN
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(300)

SPLIT = "2016-05-01"
WELL = "W01"
FAULT_DAYS = 45.0
#: a short initial fit, the same for the service and the study (the test is about agreement)
TRAIN = {"max_iter": 60, "patience": 10}


@pytest.fixture(scope="module")
def fields() -> tuple[pd.DataFrame, pd.DataFrame, dict[str, Any]]:
    """The clean field, the same with W01's p_up frozen, and the fault's truth."""
    frame = validate_frame(simulate_field(wells=2, years=1.3, seed=6151).observations).frame
    late = (frame["well"] == WELL) & (frame["time"] < pd.Timestamp(SPLIT, tz="UTC"))
    clean = validate_frame(frame[~late].reset_index(drop=True)).frame
    first = clean.loc[clean["well"] == WELL, "time"].min()
    start = first + pd.Timedelta(days=200)
    bad, truth = inject_fault(clean, WELL, "p_up", "frozen", start, days=FAULT_DAYS)
    return clean, validate_frame(bad).frame, truth


def test_a_clean_field_is_studied_as_before(fields: Any, tmp_path: Path) -> None:
    clean, _, _ = fields
    assert not plan_sensor_faults(clean).acts_on(np.arange(len(clean)))
    args = {"models": ["mm"], "methods": ["ol"], "split": SPLIT, "progress": False}
    watched = run_study(clean, **args)
    plain = run_study(clean, **args, sensor_faults=False)
    pd.testing.assert_frame_equal(watched.predictions, plain.predictions)
    assert watched.records == plain.records
    assert "held" not in watched.predictions.columns
    write_study(watched, tmp_path, report=False)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["held_at_fault"] == {"W02": 0, "W01": 0}
    assert metrics["fallback_at_fault"] == {"W02": 0, "W01": 0}


def test_the_study_holds_and_stands_in_at_a_frozen_input(fields: Any, tmp_path: Path) -> None:
    """The measurements at the frozen samples (once recognised) are held: the model learns
    nothing over them (its parameters stay put), and their rows are predicted with a
    stand-in for p_up; metrics.json counts them per well."""
    _, bad, truth = fields
    plan = plan_sensor_faults(bad)
    run = {"split": SPLIT, "track_parameters": True}
    acted = run_prequential(bad, "mm", "ol", sensor_faults=plan, **run)
    taken = run_prequential(bad, "mm", "ol", **run)
    p = acted.predictions
    w1 = p[p["well"] == WELL]
    held = w1[w1["held"]]
    t0, t1 = pd.Timestamp(truth["start"]), pd.Timestamp(truth["end"])
    assert len(held) > 20
    assert held["time"].between(t0, t1).all()  # inside the fault: no false hold
    assert (held["fallback"] == "p_up").all()  # the frozen p_up stood in for
    assert not p.loc[p["well"] != WELL, "held"].any()
    # learned nothing over the held rows: W01's parameters as they were before them
    par = acted.parameters[acted.parameters["well"] == WELL]
    span = par["time"].between(held["time"].min(), held["time"].max())
    assert len(par[span]) > 20
    assert par[span].groupby("name")["value"].nunique().eq(1).all()
    par_taken = taken.parameters[taken.parameters["well"] == WELL]
    moved = par_taken[par_taken["time"].between(held["time"].min(), held["time"].max())]
    assert moved.groupby("name")["value"].nunique().gt(1).any()  # without: it learned the fault
    # the stand-in changed the predictions during the fault; before it, nothing changed
    same = taken.predictions
    stood = (p["fallback"] != "").to_numpy()
    before = (p["time"] < held["time"].min()).to_numpy()
    assert not np.allclose(p["predicted"][stood], same["predicted"][stood])
    np.testing.assert_array_equal(p["predicted"][before], same["predicted"][before])
    # metrics.json: the held measurements and the stand-in rows per well
    result = run_study(bad, models=["mm"], methods=["ol"], split=SPLIT, progress=False)
    write_study(result, tmp_path, report=False)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["held_at_fault"] == {"W02": 0, WELL: len(held)}
    assert metrics["fallback_at_fault"]["W01"] == int(stood.sum())


def served_predictions(
    tmp_path: Path, data: Path, frame: pd.DataFrame, method: str
) -> tuple[dict[int, float], dict[int, str]]:
    """W01's published rates by time (Sm3/h) and its measurements' statuses by time, from a
    loopback service fitted on the rows before the split and streamed the rest."""
    from replay.client import FieldClient
    from service.app import Service
    from service.testing import study_settings, wait_until
    from service.transport import MemoryTransport

    # the study learns every well test it does not hold at a fault: the service's review
    # (a QC rule of its own, test_well_test_review.py) is off for the same learning
    settings = study_settings(tmp_path, data, "mm", method, SPLIT, TRAIN)
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service("W02")
            live = frame[frame["time"] >= pd.Timestamp(SPLIT, tz="UTC")]
            client.stream(live)
            last = live.loc[live["well"] == WELL, "time"].max().value
            wait_until(lambda: (WELL, last) in client.predictions, 120, "W01's predictions")
            st = service.engine.wells[WELL]
            wait_until(lambda: not st.pending, 30, "W01's measurements settled")
            rates = {t: q for (w, t), q in client.predictions.items() if w == WELL}
            _, measured = service.store.history(WELL, 0, 2**62, 100_000)
            statuses = {m.time_ns: m.status for m in measured}
    finally:
        service.stop()
    return rates, statuses


@pytest.mark.parametrize("method", ["bayes", "ol"])
def test_the_study_and_the_service_agree_at_a_fault(
    fields: Any, tmp_path: Path, method: str
) -> None:
    """The same rows held, the same predictions (to float noise) during the fault, with
    the stand-in, and after it, from a model that learned the same."""
    _, bad, _ = fields
    data = tmp_path / "field.parquet"
    bad.to_parquet(data)
    train = replace(DEFAULT_TRAIN["mm"], **TRAIN)
    study = run_prequential(
        bad, "mm", method, split=SPLIT, train=train, sensor_faults=plan_sensor_faults(bad)
    ).predictions
    rates, statuses = served_predictions(tmp_path, data, bad, method)
    w1 = study[study["well"] == WELL]
    times = w1["time"].map(lambda t: t.value).to_numpy()
    held_study = set(times[w1["held"].to_numpy()].tolist())
    held_service = {t for t, s in statuses.items() if s == "held"}
    assert len(held_study) > 20
    assert held_service == held_study
    served = np.array([rates.get(int(t), np.nan) for t in times])
    stood = (w1["fallback"] != "").to_numpy()
    assert stood.sum() > 20 and np.isfinite(served[stood]).all()
    predicted = w1["predicted"].to_numpy()
    np.testing.assert_allclose(served[stood], predicted[stood], rtol=1e-6)
    # after the fault: bayes to float noise; ol within 0.5 %: the study steps every well's
    # parameters with one Adam optimiser whose step count (its bias correction) goes on
    # while one well is held and the others learn, the service's optimiser is the well's own
    after = {"bayes": 1e-6, "ol": 5e-3}[method]
    np.testing.assert_allclose(served, predicted, rtol=after)


def test_vfm_evaluate_holds_at_a_fault_unless_told_not_to(fields: Any, tmp_path: Path) -> None:
    """The command line: ``vfm evaluate`` holds the frozen samples' measurements by default
    and learns from every one with ``--no-sensor-faults``."""
    from vfm_core.cli import main
    from vfm_core.observations import save_observations

    _, bad, _ = fields
    data = save_observations(bad, tmp_path / "field.parquet")
    held = {}
    for name, extra in (("default", []), ("off", ["--no-sensor-faults"])):
        out = tmp_path / name
        argv = [str(data), "--out", str(out), "--models", "mm", "--methods", "ol"]
        assert main(["evaluate", *argv, "--split", SPLIT, "--quiet", "--no-report", *extra]) == 0
        held[name] = json.loads((out / "metrics.json").read_text())["held_at_fault"]
    assert held["default"][WELL] > 20 and held["default"]["W02"] == 0
    assert held["off"] == {"W02": 0, WELL: 0}


def test_vfm_evaluate_keeps_a_reading_out_of_range_and_stands_in_for_it(
    fields: Any, tmp_path: Path
) -> None:
    """A p_down of -1 bar a (a transmitter out of its span) for 10 days before the split and
    10 days after it on W02: ``vfm evaluate`` drops no row (the loader keeps them raw and
    counts them), writes both spans to sensor_faults.json as ``out_of_range`` faults with
    their evidence, predicts the rows after the split with a stand-in for p_down (finite,
    within 5 % of the meter on average) and learns nothing from any of them: the
    predictions are those of the same field with the rows before the split removed."""
    from vfm_core.cli import main
    from vfm_core.observations import save_observations

    clean, _, _ = fields
    split = pd.Timestamp(SPLIT, tz="UTC")
    bad, early = inject_fault(
        clean, "W02", "p_down", "out_of_range", split - pd.Timedelta(days=20), days=10
    )
    bad, late = inject_fault(
        bad, "W02", "p_down", "out_of_range", split + pd.Timedelta(days=30), days=10
    )
    data = save_observations(bad, tmp_path / "field.parquet")
    out = tmp_path / "out"
    argv = [str(data), "--out", str(out), "--models", "mm", "--methods", "ol", "--split", SPLIT]
    assert main(["evaluate", *argv, "--quiet", "--no-report", "--jobs", "1"]) == 0
    faults = json.loads((out / "sensor_faults.json").read_text())["sensor_faults"]
    ranged = [f for f in faults if f["kind"] == "out_of_range"]
    assert [(f["well"], f["sensor"]) for f in ranged] == [("W02", "p_down")] * 2
    for fault, truth in zip(ranged, (early, late), strict=True):
        assert pd.Timestamp(fault["start"]) == pd.Timestamp(truth["start"])
        assert pd.Timestamp(fault["end"]) > pd.Timestamp(truth["end"])  # the next good row
        assert "p_down read -1 bar, outside its physical span 0..1500 bar" in fault["evidence"]
    pred = pd.read_parquet(out / "predictions.parquet")
    w2 = pred[pred["well"] == "W02"]
    after = bad[(bad["well"] == "W02") & (bad["time"] >= split) & (bad["source"] != "")]
    assert len(w2) == len(after)  # every measurement after the split predicted and scored
    t0, t1 = pd.Timestamp(late["start"]), pd.Timestamp(late["end"])
    inside = w2[w2["time"].between(t0, t1)]
    assert len(inside) >= 5 and (inside["fallback"] == "p_down").all() and inside["held"].all()
    error = (inside["predicted"] - inside["measured"]).abs() / inside["measured"]
    assert error.mean() < 0.05  # the stand-in's rate: as near the meter as elsewhere
    # the rows out of range before the split were not learned: the same study without them
    kept = validate_frame(bad, keep_out_of_range=True).frame
    gone = kept["time"].between(pd.Timestamp(early["start"]), pd.Timestamp(early["end"]))
    without = run_study(
        kept[~(gone & (kept["well"] == "W02"))].reset_index(drop=True),
        models=["mm"], methods=["ol"], split=SPLIT, progress=False,
    )  # fmt: skip
    np.testing.assert_allclose(pred["predicted"], without.predictions["predicted"], rtol=1e-9)
