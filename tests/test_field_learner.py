"""The field-wide learner (``mtl`` streamed message by message) against the prequential study.

A small simulated field, fitted on its history and then fed in time order (each row's
sample predicted, then its measurement learned), must give the predictions of
:func:`vfm_core.jobs.study.run_prequential` to float noise, with a per-measurement method
(``ol``: day rounds) and with periodic batch learning (``pbl``: retrains on the study's
calendar); a checkpoint taken mid-stream (with a day still open) must continue exactly as
an uninterrupted run; a well first seen live grows the model without moving the others,
and learns.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import target_mask
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import mape, run_prequential
from vfm_core.learning import DEFAULT_TRAIN, OnlineSettings
from vfm_core.learning.field import FieldLearner
from vfm_core.observations import validate_frame
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(300)

SPLIT = pd.Timestamp("2016-10-01", tz="UTC")
#: a short initial fit, the same for the study and the stream (the test is about agreement)
TRAIN = replace(DEFAULT_TRAIN["mtl"], max_iter=80, patience=10)


@pytest.fixture(scope="module")
def frame() -> pd.DataFrame:
    return validate_frame(simulate_field(wells=3, years=1, seed=3).observations).frame


def _history(frame: pd.DataFrame, wells: list[str] | None = None) -> dict[str, tuple]:
    measured = frame[target_mask(frame, "all") & (frame["time"] < SPLIT).to_numpy()]
    rows = {}
    for well, g in measured.groupby("well", sort=False):
        if wells is not None and well not in wells:
            continue
        rows[str(well)] = (
            torch.tensor(g[list(INPUT_COLUMNS)].to_numpy()),
            torch.tensor(g["q_total"].to_numpy()),
            torch.tensor(pd.DatetimeIndex(g["time"]).as_unit("ns").asi8),
            torch.tensor((g["source"] == "well_test").to_numpy()),
        )
    return rows


def _fitted(frame: pd.DataFrame, method: str, wells: list[str] | None = None) -> FieldLearner:
    field = FieldLearner("mtl", method, train=TRAIN)
    field.fit_history(_history(frame, wells), SPLIT)
    return field


def _stream(field: FieldLearner, rows: pd.DataFrame) -> dict[tuple[str, int], float | None]:
    """Each row's sample predicted, then its measurement (if any) learned; in time order."""
    out: dict[tuple[str, int], float | None] = {}
    measured = target_mask(rows, "all")
    for (_, row), is_measured in zip(rows.iterrows(), measured, strict=True):
        inputs = row[list(INPUT_COLUMNS)].tolist()
        out[(row["well"], row["time"].value)] = field.well(row["well"]).predict(
            inputs, row["time"]
        )["q_total"]
        if is_measured:
            field.well(row["well"]).learn(inputs, row["q_total"], row["time"], row["source"])
    return out


def _live(frame: pd.DataFrame) -> pd.DataFrame:
    return frame[frame["time"] >= SPLIT].reset_index(drop=True)


@pytest.mark.parametrize("method", ["ol", "pbl:30d", "bayes"])
def test_the_stream_reproduces_the_study(frame: pd.DataFrame, method: str) -> None:
    study = run_prequential(frame, "mtl", method, split=SPLIT, train=TRAIN).predictions
    field = _fitted(frame, method)
    streamed = _stream(field, _live(frame))
    got = np.array(
        [streamed[(w, t.value)] for w, t in zip(study["well"], study["time"], strict=True)]
    )
    np.testing.assert_allclose(got, study["predicted"].to_numpy(), rtol=1e-9)
    assert mape(got, study["measured"]) == pytest.approx(
        mape(study["predicted"], study["measured"]), rel=1e-9
    )
    if method != "pbl:30d":  # one version per day round, after the history fit
        days = pd.DatetimeIndex(study["time"]).normalize().nunique()
        # ... and one per refit under bayes's filter (mtl's network, every 14 days)
        assert field.version - field.method.n_retrains in (days, days + 1)  # last may be open
    else:
        assert field.method.n_retrains >= 2


def test_a_checkpoint_mid_stream_continues_exactly(frame: pd.DataFrame) -> None:
    live = _live(frame)
    whole = _stream(_fitted(frame, "ol"), live)
    field = _fitted(frame, "ol")
    # stop in the middle of a day: that day's measurements are held, not learned yet
    cut = int(np.flatnonzero(live["time"].dt.hour.to_numpy() >= 12)[40])
    first = _stream(field, live.iloc[:cut])
    assert field._held, "the checkpoint should be taken with a day still open"
    blob = field.checkpoint()
    again = FieldLearner.restore(blob)
    assert again.version == field.version and again.n_learned == field.n_learned
    rest = _stream(again, live.iloc[cut:])
    both = {**first, **rest}
    keys = list(whole)
    np.testing.assert_array_equal(
        np.array([both[k] for k in keys], dtype=float),
        np.array([whole[k] for k in keys], dtype=float),
    )


def test_a_well_first_seen_live_grows_the_model_and_learns(frame: pd.DataFrame) -> None:
    """W03 has no history: first seen live it gets a task vector at its prior without moving
    the others. Its meter then reads 25 % high from its 10th day on (a recalibration): the
    field learns that (a step size of 1e-2, so that a few weeks suffice), and what it learned
    sits in W03's task vector."""
    field = FieldLearner("mtl", "ol", train=TRAIN, online=OnlineSettings(lr=1e-2, steps=10))
    field.fit_history(_history(frame, ["W01", "W02"]), SPLIT)
    live = _live(frame)
    probe = live[live["well"] == "W01"].iloc[0][list(INPUT_COLUMNS)].tolist()
    before = field.well("W01").predict(probe)["q_total"]
    new = field.well("W03")  # first sight
    assert field.wells == ["W01", "W02", "W03"] and not new.ready
    assert field.well("W01").predict(probe)["q_total"] == before  # the others do not move
    assert new.predict(probe)["q_total"] is None
    w3 = (live["well"] == "W03").to_numpy() & target_mask(live, "all")
    shifted = live.copy()
    later = np.flatnonzero(w3)[10:]
    shifted.loc[later, "q_total"] *= 1.25
    streamed = _stream(field, shifted)
    assert new.ready and new.remembered == int(w3.sum())
    rows = shifted.iloc[later]
    predicted = np.array(
        [streamed[(w, t.value)] for w, t in zip(rows["well"], rows["time"], strict=True)]
    )
    err_first = mape(predicted[:5], rows["q_total"].iloc[:5])
    err_last = mape(predicted[-20:], rows["q_total"].iloc[-20:])
    assert err_last < 0.5 * err_first, (err_first, err_last)
    # set back to its prior, W03's task vector loses part of what was learned (the shared
    # network took up the rest)
    x = rows[list(INPUT_COLUMNS)].tail(20).to_numpy().tolist()
    with torch.no_grad():
        field.model.beta[2].zero_()  # type: ignore[operator]
    prior = [new.predict(v)["q_total"] for v in x]
    assert err_last < 0.8 * mape(prior, rows["q_total"].iloc[-20:])


def test_growing_keeps_the_optimiser_and_the_calendar(frame: pd.DataFrame) -> None:
    field = _fitted(frame, "pbl:30d", wells=["W01", "W02"])
    due = field.method.next_due()
    field.well("W09")
    assert field.method.next_due() == due  # the new well retrains with the field
    assert int(field.method.iterations[-1]) == int(field.method.iterations[:-1].max())
    online = _fitted(frame, "ol", wells=["W01", "W02"])
    live = _live(frame)
    _stream(online, live[live["well"].isin(["W01", "W02"])].head(12))
    online.flush()
    moments = online.method.state_dict()["optimizer"]["state"]
    online.well("W09")
    grown = online.method.state_dict()["optimizer"]["state"]
    beta = [k for k, v in grown.items() if v["exp_avg"].shape[0] == 3]
    assert beta and all(float(grown[k]["exp_avg"][2].abs().sum()) == 0.0 for k in beta)
    for k in beta:
        torch.testing.assert_close(grown[k]["exp_avg"][:2], moments[k]["exp_avg"])


def test_refusals_say_what_to_do() -> None:
    with pytest.raises(ConfigError, match="per well"):
        FieldLearner("mm", "ol")
    with pytest.raises(ConfigError, match="cannot run"):
        FieldLearner("mtl", "pbl:auto")
    field = FieldLearner("mtl", "ol", wells=["W01"])
    with pytest.raises(ConfigError, match="model.name"):
        field.well("W01").refit_as("mm")
    with pytest.raises(ConfigError, match="field checkpoint cannot be read"):
        FieldLearner.restore(torch.zeros(1).numpy().tobytes())


@pytest.mark.parametrize("method", ["ol", "pbl:7d"])
def test_a_field_without_history_starts_on_its_first_measurements(
    frame: pd.DataFrame, method: str
) -> None:
    """No history fit: ``ol`` sets the field up on its first day's round, ``pbl`` starts its
    calendar at its first measurement and fits the field at its first retrain; both then
    answer."""
    field = FieldLearner("mtl", method, train=TRAIN)
    live = _live(frame)
    streamed = _stream(field, live.head(150))
    assert field.well("W01").ready and field.version >= 1
    if method != "ol":
        first = int(live["time"].iloc[0].value)
        week = 7 * 86_400 * 10**9
        assert field.method.retrains[:2] == [first + week, first + 2 * week]
    rows = live.head(150)[target_mask(live.head(150), "all")]
    got = np.array(
        [streamed[(w, t.value)] for w, t in zip(rows["well"], rows["time"], strict=True)],
        dtype=float,
    )
    answered = np.isfinite(got)
    assert answered[-30:].all()
    assert mape(got[-30:], rows["q_total"].iloc[-30:]) < 50.0


def test_one_well_alone_predicts_what_the_whole_field_does(frame: pd.DataFrame) -> None:
    """The fast path (one well's parameters with the shared ones) = the field's batch."""
    field = _fitted(frame, "ol")
    _stream(field, _live(frame).head(30))
    live = _live(frame).head(30)
    for _, row in live.iterrows():
        j = field.wells.index(row["well"])
        x = torch.tensor(row[list(INPUT_COLUMNS)].tolist(), dtype=torch.float64)
        whole = field.model.predict(x.reshape(1, 1, 6).expand(len(field.wells), 1, 6))[j, 0]
        alone = field._one_well(j, x)
        assert alone is not None
        assert alone == pytest.approx(float(whole), rel=1e-12)


def test_a_well_used_again_starts_afresh(frame: pd.DataFrame) -> None:
    """An id the field knew (purged in the service, then seen again) starts at its prior with
    nothing remembered; the other wells keep what they learned."""
    field = _fitted(frame, "ol")
    live = _live(frame)
    _stream(field, live.head(40))
    probe = live[live["well"] == "W01"].iloc[0][list(INPUT_COLUMNS)].tolist()
    before = field.well("W01").predict(probe)["q_total"]
    assert field.well("W02").ready and field.n_learned["W02"] > 0
    again = field.fresh("W02")
    assert not again.ready and again.remembered == 0 and field.n_learned["W02"] == 0
    assert float(field.model.beta.detach()[1].abs().sum()) == 0.0  # type: ignore[operator]
    assert all(h[0] != 1 for h in field._held)
    assert field.well("W01").predict(probe)["q_total"] == before
    rest = _stream(field, live.iloc[40:120])
    later = live.iloc[40:120]
    w2 = later[(later["well"] == "W02") & target_mask(later, "all")]
    assert again.ready and again.remembered == len(w2)
    assert rest[("W02", w2["time"].iloc[-1].value)] is not None


def test_a_measurement_late_for_its_round_is_learned_with_it(frame: pd.DataFrame) -> None:
    """W02's measurement of one day arrives after W01's first row of the next day (the wells'
    queues out of time order): the round that closed without it is learned again with it,
    so every later prediction is that of the stream in time order; only the predictions
    made in between differ."""
    live = _live(frame).head(90).reset_index(drop=True)
    in_order = _stream(_fitted(frame, "ol"), live)
    days = live["time"].dt.floor("D")
    measured = target_mask(live, "all")
    day = days.unique()[5]
    w2 = int(np.flatnonzero((days == day).to_numpy() & (live["well"] == "W02").to_numpy())[-1])
    nxt = int(np.flatnonzero((days > day).to_numpy() & (live["well"] == "W01").to_numpy())[0])
    assert measured[w2]
    order = [i for i in range(len(live)) if i != w2]
    order.insert(order.index(nxt) + 1, w2)
    # W02's sample is answered in its place; its measurement comes after W01's next-day row
    field = _fitted(frame, "ol")
    out: dict[tuple[str, int], float | None] = {}
    for i in order:
        row = live.iloc[i]
        inputs = row[list(INPUT_COLUMNS)].tolist()
        facade = field.well(row["well"])
        if i != w2:
            out[(row["well"], row["time"].value)] = facade.predict(inputs, row["time"])["q_total"]
        else:
            out[(row["well"], row["time"].value)] = in_order[(row["well"], row["time"].value)]
        if measured[i]:
            facade.learn(inputs, row["q_total"], row["time"], row["source"])
    # the predictions from the next day's first message to the late measurement's arrival
    # used the round without it; every later one is the in-order stream's
    start = int(np.flatnonzero((days > day).to_numpy())[0])
    between = {(live.iloc[i]["well"], live.iloc[i]["time"].value) for i in range(start, nxt + 1)}
    assert all(out[k] != in_order[k] for k in between)
    rest = [k for k in in_order if k not in between]
    np.testing.assert_allclose(
        np.array([out[k] for k in rest], dtype=float),
        np.array([in_order[k] for k in rest], dtype=float),
        rtol=1e-12,
    )
