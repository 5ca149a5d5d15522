"""The Bayesian learning method: hand-worked updates, gating, calibration, and what it keeps.

The contract every method keeps is in tests/test_methods.py; here are the properties only a
method that carries its uncertainty promises.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pandas as pd
import pytest
import torch

from replay.replayer import replay_frame
from service.app import running
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.effects import add_features
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import mape, run_prequential
from vfm_core.learning import parse_method
from vfm_core.learning.streaming import WellLearner
from vfm_core.physics import PRIORS
from vfm_core.simulate import simulate_field

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SAMPLE = [0.5, 60.0, 20.0, 70.0, 0.1, 0.6]  # -, bar, bar, degC, -, -
T0 = 1_500_000_000_000_000_000  # epoch ns
HOUR = 3_600_000_000_000


def _one_parameter_learner() -> WellLearner:
    """mm whose filter tracks only C_D, with fixed meter noises and a plain Kalman step."""
    spec = (
        "bayes:params=c_d:iterations=1:huber=0:gate=0:adapt=0:calibrate=0"
        ":noise_mpfm=0.05:noise_well_test=0.01:drift=0"
    )
    learner = WellLearner("W1", "mm", spec)
    x = torch.tensor([SAMPLE] * 40, dtype=torch.float64)
    x[:, 0] += torch.linspace(-0.1, 0.1, 40, dtype=torch.float64)
    y = 1000.0 * x[:, 0] / 0.5  # Sm3/h, a linear valve
    t = T0 + torch.arange(40, dtype=torch.int64) * HOUR
    learner.fit_history(x, y, t)
    # a known state: C_D's standardised value has variance 1 (one prior sd)
    state = learner.method.state_dict()
    state["P"] = torch.zeros_like(state["P"])
    state["P"][0, 5, 5] = 1.0
    learner.method.load_state_dict(state)
    return learner


@pytest.mark.parametrize(("source", "noise"), [("well_test", 0.01), ("mpfm", 0.05)])
def test_a_measurement_moves_the_prediction_by_its_weight(source: str, noise: float) -> None:
    """One parameter by hand: C_D = mu + sigma z, the rate is proportional to C_D, so
    H = d log q / dz = sigma / C_D; the Kalman gain on z is K = P H / (H^2 P + s^2), and a
    surprise r = log(y / q) moves z by K r. A well test (s = 1 %) moves the prediction by
    most of the surprise, an MPFM reading (s = 5 %) by less than half of it."""
    learner = _one_parameter_learner()
    c_d = learner.physical_parameters()["c_d"]["value"]
    sigma = PRIORS["c_d"].std
    q_before = learner.predict(SAMPLE)["q_total"]
    assert q_before is not None
    y = 1.05 * q_before  # 5 % above the prediction
    h = sigma / c_d
    k = 1.0 * h / (h * h * 1.0 + noise**2)
    r = math.log(1.05)
    c_d_after = c_d + sigma * k * r
    expected = q_before * c_d_after / c_d
    when = pd.Timestamp(int(T0 + 40 * HOUR), tz="UTC")  # drift is 0: the time does not matter
    assert learner.learn(SAMPLE, y, when, source)
    q_after = learner.predict(SAMPLE)["q_total"]
    assert q_after == pytest.approx(expected, rel=1e-6)
    assert learner.physical_parameters()["c_d"]["value"] == pytest.approx(c_d_after, rel=1e-9)
    # the rate is proportional to C_D, so it moves by H K r = (its share of the surprise) r
    moved = (q_after / q_before - 1.0) / r
    weight = h * h / (h * h + noise**2)
    assert moved == pytest.approx(weight, rel=1e-3)
    # the numbers, for the record: 0.959 of the surprise for a well test, 0.485 for an MPFM
    assert (moved > 0.95) if source == "well_test" else (0.4 < moved < 0.55)


def test_an_outlier_is_refused_and_a_lasting_change_is_taken() -> None:
    learner = WellLearner("W1", "mm", "bayes:calibrate=0")
    x = torch.tensor([SAMPLE] * 60, dtype=torch.float64)
    x[:, 0] += torch.linspace(-0.1, 0.1, 60, dtype=torch.float64)
    y = (
        1000.0
        * x[:, 0]
        / 0.5
        * (
            1
            + 0.01
            * torch.randn(60, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        )
    )
    t = T0 + torch.arange(60, dtype=torch.int64) * HOUR
    learner.fit_history(x, y, t)
    q = learner.predict(SAMPLE)["q_total"]
    assert q is not None
    when = pd.Timestamp(int(T0 + 61 * HOUR), tz="UTC")
    learner.learn(SAMPLE, 1.6 * q, when, "mpfm")  # 60 % off: far outside the spread
    stats = learner.method.stats()
    assert int(stats["refused"][0]) == 1
    assert learner.predict(SAMPLE)["q_total"] == pytest.approx(q, rel=1e-9)
    for i in range(2, 5):  # the well really changed: the third refusal in a row resets
        learner.learn(SAMPLE, 1.6 * q, when + pd.Timedelta(hours=i), "mpfm")
    stats = learner.method.stats()
    assert int(stats["resets"][0]) >= 1
    assert learner.predict(SAMPLE)["q_total"] > 1.2 * q


def test_bad_options_say_what_is_wrong() -> None:
    with pytest.raises(ConfigError, match="unknown option"):
        parse_method("bayes:speed=2")
    with pytest.raises(ConfigError, match="not a number"):
        parse_method("bayes:drift_c_d=fast")
    with pytest.raises(ConfigError, match="no parameter"):
        WellLearner("W1", "mm", "bayes:params=c_d+nonsense")


@pytest.fixture(scope="module")
def plain_field() -> pd.DataFrame:
    return simulate_field(wells=3, years=3, seed=4, start="2016-07-01").observations


def test_intervals_cover_about_90_percent_when_the_model_is_right(plain_field) -> None:
    """No hidden effect: mm is the truth, so coverage is a property of the filter alone."""
    run = run_prequential(plain_field, "mm", "bayes", targets="all", split="2018-01-01")
    pr = run.predictions
    inside = (pr["measured"] >= pr["predicted_p05"]) & (pr["measured"] <= pr["predicted_p95"])
    assert len(pr) > 1000
    assert 0.85 <= float(inside.mean()) <= 0.95
    # the interval is the log-normal one: p05 * p95 = predicted^2
    np.testing.assert_allclose(
        pr["predicted_p05"] * pr["predicted_p95"], pr["predicted"] ** 2, rtol=1e-9
    )


def test_sparse_well_tests_track_a_wearing_well() -> None:
    """Case 2 (well tests only) with choke wear: the filter follows the wear between sparse
    tests better than online steps or periodic retraining."""
    field = simulate_field(
        wells=3, years=5, seed=6, start="2016-01-01", hidden=["erosion:rate=0.08"]
    ).observations
    scores = {}
    for method in ("ol", "pbl:14d", "bayes"):
        pr = run_prequential(field, "mm", method, targets="well_test").predictions
        scores[method] = mape(pr["predicted"], pr["measured"])
    assert scores["bayes"] < min(scores["ol"], scores["pbl:14d"]), scores


def _temperature_field() -> pd.DataFrame:
    """A field whose rates carry a temperature term the plain model lacks, constant in time:
    rates times 1 + 0.06 (t_up - 60 degC) / 10 K, with the upstream temperature swinging
    8 K over the seasons so that the slope can be told apart from each well's level."""
    frame = simulate_field(wells=2, years=3.2, seed=8, start="2016-01-01").observations.copy()
    day = (frame["time"] - pd.Timestamp("2016-01-01", tz="UTC")).dt.total_seconds() / 86400
    frame["t_up"] = frame["t_up"] + 8.0 * np.sin(2 * np.pi * day / 365.25)
    factor = 1.0 + 0.06 * (frame["t_up"] - 60.0) / 10.0
    for col in ("q_total", "q_gas", "q_oil", "q_water"):
        frame[col] = frame[col] * factor
    return frame


def test_an_added_effect_keeps_its_strength_for_a_year(monkeypatch: pytest.MonkeyPatch) -> None:
    """The effect found by a diagnosis, added to the model: online Bayesian updates keep its
    learned slope (structural parameters barely drift), and the error stays below the plain
    model's, offline (the study) and streaming (the service's learner)."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    effect = "my_effects:TemperatureScale"
    frame = add_features(_temperature_field(), [effect])
    split = pd.Timestamp("2017-09-01", tz="UTC")
    with_effect = run_prequential(
        frame, "mm", "bayes", split=split, effects=[effect], track_parameters=True
    )
    plain = run_prequential(frame, "mm", "bayes", split=split)
    assert mape(with_effect.predictions.predicted, with_effect.predictions.measured) < mape(
        plain.predictions.predicted, plain.predictions.measured
    )
    k = with_effect.parameters[with_effect.parameters["name"] == "temperature_scale.k"]
    fitted = k[k["time"] == split].set_index("well")["value"]
    year_on = k[k["time"] >= split + pd.Timedelta(days=365)].groupby("well")["value"].first()
    assert (fitted > 0.03).all(), fitted  # the fit found the slope (0.06 per 10 K)
    assert len(year_on) == len(fitted)
    np.testing.assert_allclose(year_on[fitted.index], fitted, rtol=0.2)

    # streaming, one well, as the service runs it
    well = str(frame["well"].iloc[0])
    rows = frame[(frame["well"] == well) & frame["source"].isin(["mpfm", "well_test"])]
    hist = rows[rows["time"] < split]
    live = rows[(rows["time"] >= split) & (rows["time"] < split + pd.Timedelta(days=366))]
    cols = ["choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil"]
    errors = {}
    for effects in ([effect], []):
        learner = WellLearner(well, "mm", "bayes", effects=effects)
        learner.fit_history(
            torch.tensor(hist[cols].to_numpy()),
            torch.tensor(hist["q_total"].to_numpy()),
            torch.tensor(pd.DatetimeIndex(hist["time"]).as_unit("ns").asi8),
            well_test=torch.tensor((hist["source"] == "well_test").to_numpy()),
        )
        start = learner.physical_parameters().get("temperature_scale.k", {}).get("value")
        ape = []
        for _, row in live.iterrows():
            q = learner.predict(row[cols].tolist(), when=row["time"])["q_total"]
            ape.append(abs(q - row["q_total"]) / row["q_total"])
            learner.learn(row[cols].tolist(), row["q_total"], row["time"], row["source"])
        errors[bool(effects)] = float(np.mean(ape))
        if effects:
            end = learner.physical_parameters()["temperature_scale.k"]["value"]
            assert end == pytest.approx(start, rel=0.2)
    assert errors[True] < errors[False], errors
    sys.modules.pop("my_effects", None)


def _serve_a_year(tmp_path: Path, frame: pd.DataFrame, effects: list[str]) -> dict[str, Any]:
    """A real service (in-memory transport) running mm with ``bayes`` and ``effects``, fitted
    on the history before the split, fed one year after it by the replay tool; the
    well's state a week in and at the end."""
    data = tmp_path / "field.parquet"
    frame.to_parquet(data)
    folder = tmp_path / ("with" if effects else "plain")
    settings = loopback_settings(
        folder,
        model={
            "name": "mm",
            "method": "bayes",
            "effects": effects,
            "effect_modules": ["my_effects"],
            "history": str(data),
            "history_until": "2017-09-01",
        },
    )
    bus = MemoryTransport(settings.prefix, settings.queues.receive_capacity)
    week = pd.Timestamp("2017-09-08", tz="UTC")
    year = pd.Timestamp("2018-09-01", tz="UTC")
    out: dict[str, Any] = {}
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=60) as http:
        first = frame[frame["time"] < week]
        rest = frame[(frame["time"] >= week) & (frame["time"] < year)]
        replay_frame(first, bus=bus, start="2017-09-01", progress=False, idle_timeout=2.0)
        out["week"] = {
            w["well"]: http.get(f"/wells/{w['well']}").json() for w in http.get("/wells").json()
        }
        done = replay_frame(rest, bus=bus, progress=False, idle_timeout=2.0)
        assert done.missing == 0
        out["year"] = {w: http.get(f"/wells/{w}").json() for w in out["week"]}
    return out


def test_an_added_effect_keeps_its_strength_through_the_service(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same, end to end: a service configured with the effect keeps its slope for a year of
    streaming, and its error stays below that of the same service without it."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    frame = _temperature_field()
    with_effect = _serve_a_year(tmp_path, frame, ["my_effects:TemperatureScale"])
    plain = _serve_a_year(tmp_path, frame, [])
    for well, state in with_effect["year"].items():
        start = with_effect["week"][well]["parameters"]["temperature_scale.k"]
        end = state["parameters"]["temperature_scale.k"]
        print(well, "slope a week in", start, "a year on", end)
        assert start["value"] > 0.03, start  # the fit found the slope (0.06 per 10 K)
        assert start["std"] is not None and start["std"] > 0
        assert end["value"] == pytest.approx(start["value"], rel=0.2), (well, start, end)
    for which in (with_effect, plain):
        assert all(s["rolling_mape"]["n"] > 0 for s in which["year"].values())
    err = {
        name: np.mean([s["rolling_mape"]["value"] for s in which["year"].values()])
        for name, which in (("with", with_effect), ("plain", plain))
    }
    print("rolling MAPE through the service:", err)
    assert err["with"] < err["plain"], err
    sys.modules.pop("my_effects", None)


@pytest.mark.parametrize("base", ["mm", "ham"])
def test_a_parameter_the_specification_sets_is_fixed_with_no_sd(base: str) -> None:
    """An effect's parameter the model's specification sets (``name:parameter=value``, as
    the diagnosis identifies it on a hybrid's core and "apply" adds it) is pinned by a
    prior of sd 1e-9: the well's parameters say ``fixed`` with no sd (a walk's page showed
    "± 0.0000", as if learned to certainty), and it stays at its value while the learned
    parameters keep theirs."""
    learner = WellLearner("W1", base, "bayes", effects=["valve_equal_percentage:weight=0.9"])
    x = torch.tensor([SAMPLE] * 40, dtype=torch.float64)
    x[:, 0] += torch.linspace(-0.1, 0.1, 40, dtype=torch.float64)
    y = 1000.0 * x[:, 0] / 0.5  # Sm3/h
    t = T0 + torch.arange(40, dtype=torch.int64) * HOUR
    learner.fit_history(x, y, t)
    for k in range(5):
        when = pd.Timestamp(int(T0 + (41 + k) * HOUR), tz="UTC")
        learner.learn(SAMPLE, 1.1 * 1000.0, when, "well_test")
    params = learner.physical_parameters()
    weight = params["valve_equal_percentage.weight"]
    assert weight["fixed"] is True and weight["std"] is None
    assert weight["value"] == pytest.approx(0.9, abs=1e-6)
    learned = params["rho_oil"]
    assert learned["fixed"] is False and learned["std"] is not None and learned["std"] > 1e-3
    assert all(p["fixed"] is False for n, p in params.items() if "." not in n)


@pytest.mark.parametrize("kernels", ["1", "0"])
@pytest.mark.parametrize(("model_name", "hybrid"), [("ham", True), ("hem", True), ("nn", False)])
def test_a_well_without_a_fit_starts_a_hybrids_output_weights_at_their_prior_mean(
    model_name: str, hybrid: bool, kernels: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A well with no history starts its filter at its first measurement. A hybrid's output
    weights start at their prior mean with no variance (its network's lower layers are
    unfitted draws on inputs not standardised: WellMLP.head_blocks), so a measurement moves
    its level and physics only; a network that is the whole model (``nn``) keeps the He
    prior. The compiled step starts it as the torch one does."""
    monkeypatch.setenv("VFM_KERNELS", kernels)
    learner = WellLearner("W1", model_name, "bayes")
    later = [SAMPLE[0] + 0.1, SAMPLE[1] + 5.0, *SAMPLE[2:]]  # inputs moved: features not 0
    for k, (x, y) in enumerate(((SAMPLE, 1000.0), (later, 1300.0))):
        assert learner.learn(x, y, pd.Timestamp(T0 + k * HOUR, tz="UTC"), "well_test")
    method: Any = learner.method
    heads = torch.tensor([label.startswith("head.w") for label in method._labels])
    fan_in = int(heads.sum())
    P = method.state_dict()["P"][0]
    weights = P[heads][:, heads]
    level = P[~heads][:, ~heads]
    assert float(torch.diagonal(level).min()) > 0  # the level and physics learn
    if hybrid:  # no variance but an hour's drift; the weights still at their prior mean
        assert float(weights.abs().max()) < 1e-9
        head = learner.model.net.weights[-1].detach()  # type: ignore[union-attr]
        assert float(head.abs().max()) < 1e-6
    else:  # the He prior (and an hour's drift) where the second test's features are 0
        assert float(torch.diagonal(weights).max()) == pytest.approx(2.0 / fan_in, rel=1e-6)
