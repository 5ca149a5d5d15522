"""Scores of a predictive distribution (issue 38 item 4): the interval score and the CRPS.

Every number here can be checked by hand or by a second, independent computation:

- Interval score (Gneiting and Raftery 2007, eq. 43), alpha = 0.1, interval [90, 110]:
  y = 100 inside: 110 - 90 = 20; y = 115 above: 20 + (2 / 0.1)(115 - 110) = 120;
  y = 80 below: 20 + 20 (90 - 80) = 220.
- CRPS of a normal N(mu, sd^2), z = (y - mu) / sd: sd [z (2 Phi(z) - 1) + 2 phi(z) - 1/sqrt(pi)].
  At y = mu (z = 0): sd (2 phi(0) - 1/sqrt(pi)) = sd (2/sqrt(2 pi) - 1/sqrt(pi))
  = sd (sqrt(2) - 1) / sqrt(pi) = 0.233695 sd, so 0.467390 for sd = 2. At z = 1, sd = 1:
  (2 x 0.841345 - 1) + 2 x 0.241971 - 0.564190 = 0.682689 + 0.483941 - 0.564190 = 0.602441.
- CRPS of a log-normal LN(mu, s^2) (Baran and Lerch 2015), w = (log y - mu) / s:
  y (2 Phi(w) - 1) - 2 exp(mu + s^2/2) [Phi(w - s) + Phi(s / sqrt 2) - 1]. At mu = 0, s = 1,
  y = 1 (w = 0): -2 e^0.5 [Phi(-1) + Phi(0.70711) - 1] = -2 x 1.648721 x (0.158655 + 0.760250
  - 1) = 0.267405. Elsewhere against the definition, the integral of (F(x) - 1{x >= y})^2,
  by scipy's quad.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import integrate, stats

from vfm_core.cli import main
from vfm_core.jobs.study import (
    crps_lognormal,
    crps_normal,
    interval_score,
    lognormal_from_interval,
    metrics_records,
    probabilistic_scores,
)

Z95 = 1.6448536269514722


def test_interval_score_by_hand() -> None:
    scores = interval_score([90.0, 90.0, 90.0], [110.0, 110.0, 110.0], [100.0, 115.0, 80.0])
    np.testing.assert_allclose(scores, [20.0, 120.0, 220.0])
    # alpha sets the price of a miss: at 0.5 a miss costs 4 times its distance
    assert interval_score(90.0, 110.0, 115.0, alpha=0.5) == pytest.approx(40.0)


def test_crps_normal_by_hand() -> None:
    assert crps_normal(5.0, 2.0, 5.0) == pytest.approx(
        2.0 * (math.sqrt(2) - 1) / math.sqrt(math.pi)
    )
    assert crps_normal(5.0, 2.0, 5.0) == pytest.approx(0.467390, abs=1e-6)
    assert crps_normal(0.0, 1.0, 1.0) == pytest.approx(0.602441, abs=1e-6)
    # symmetric about the mean, and a point forecast (sd 0) scores its absolute error
    assert crps_normal(0.0, 1.0, -1.0) == pytest.approx(0.602441, abs=1e-6)
    np.testing.assert_allclose(crps_normal([3.0, 3.0], [0.0, 0.0], [5.0, 1.5]), [2.0, 1.5])


def _crps_by_integration(cdf, y: float, lower: float = -np.inf) -> float:
    """The CRPS from its definition, integral of (F(x) - 1{x >= y})^2 dx."""
    below = integrate.quad(lambda x: cdf(x) ** 2, lower, y, limit=200)[0]
    above = integrate.quad(lambda x: (1.0 - cdf(x)) ** 2, y, np.inf, limit=200)[0]
    return below + above


@pytest.mark.parametrize("y", [-2.5, 0.3, 4.0])
def test_crps_normal_is_the_integral_of_its_definition(y: float) -> None:
    mu, sd = 0.5, 1.7
    expected = _crps_by_integration(lambda x: stats.norm.cdf(x, mu, sd), y)
    assert crps_normal(mu, sd, y) == pytest.approx(expected, rel=1e-7)


def test_crps_lognormal_by_hand_and_in_its_limits() -> None:
    assert crps_lognormal(0.0, 1.0, 1.0) == pytest.approx(0.267405, abs=1e-6)
    # sigma 0: a point forecast at exp(mu), the absolute error
    assert crps_lognormal(math.log(100.0), 0.0, 130.0) == pytest.approx(30.0)
    # a narrow log-normal is nearly the normal of sd median x sigma (the delta method)
    narrow = crps_lognormal(math.log(100.0), 0.002, 100.1)
    assert narrow == pytest.approx(crps_normal(100.0, 0.2, 100.1), rel=2e-3)
    # no score for a measurement that is not positive (its log is undefined)
    assert np.isnan(crps_lognormal(0.0, 1.0, 0.0))


@pytest.mark.parametrize(
    ("mu", "sigma", "y"),
    [
        (math.log(100.0), 0.1, 115.0),
        (math.log(100.0), 0.1, 70.0),
        (1.0, 0.8, 0.9),
        (2.0, 0.03, 7.4),
    ],
)
def test_crps_lognormal_is_the_integral_of_its_definition(
    mu: float, sigma: float, y: float
) -> None:
    expected = _crps_by_integration(
        lambda x: stats.lognorm.cdf(x, sigma, scale=math.exp(mu)), y, lower=0.0
    )
    assert crps_lognormal(mu, sigma, y) == pytest.approx(expected, rel=1e-6)


def test_the_lognormal_comes_back_from_its_quantiles() -> None:
    # what bayes gives: rate x exp(+-1.6449 sd), the rate the median
    rate, sd = np.array([100.0, 3.0]), np.array([0.1, 0.4])
    mu, sigma = lognormal_from_interval(rate * np.exp(-Z95 * sd), rate * np.exp(Z95 * sd))
    np.testing.assert_allclose(mu, np.log(rate))
    np.testing.assert_allclose(sigma, sd)
    # and its 5 % and 95 % quantiles are the interval
    np.testing.assert_allclose(
        stats.lognorm.ppf(0.95, sigma, scale=np.exp(mu)), rate * np.exp(Z95 * sd)
    )


def test_probabilistic_scores_by_hand() -> None:
    measured = [100.0, 115.0, np.nan, 0.0]
    p05 = [90.0, 90.0, 90.0, 90.0]
    p95 = [110.0, 110.0, 110.0, 110.0]
    score90, crps = probabilistic_scores(measured, p05, p95)
    # rows 3 (no measurement) and 4 (zero) are not scored: (20/100 + 120/115) / 2 in %
    assert score90 == pytest.approx((20.0 / 100.0 + 120.0 / 115.0) / 2.0 * 100.0)
    mu, sigma = 0.5 * (math.log(90.0) + math.log(110.0)), math.log(110.0 / 90.0) / (2 * Z95)
    by_hand = [
        _crps_by_integration(lambda x: stats.lognorm.cdf(x, sigma, scale=math.exp(mu)), y, 0.0) / y
        for y in (100.0, 115.0)
    ]
    assert crps == pytest.approx(np.mean(by_hand) * 100.0, rel=1e-6)
    assert all(math.isnan(v) for v in probabilistic_scores([np.nan], [90.0], [110.0]))


def test_a_correct_forecast_scores_better_than_a_wider_a_narrower_or_a_biased_one() -> None:
    """Properness, seen on draws: the measured rates are log-normal about 100 Sm3/h with a
    log sd of 0.05; the forecast that says exactly that beats every other."""
    rng = np.random.default_rng(20261126)
    truth_sd = 0.05
    y = 100.0 * np.exp(truth_sd * rng.standard_normal(20_000))

    def scores(median: float, sd: float) -> tuple[float, float]:
        lo = np.full_like(y, median * math.exp(-Z95 * sd))
        hi = np.full_like(y, median * math.exp(Z95 * sd))
        return probabilistic_scores(y, lo, hi)

    correct = scores(100.0, truth_sd)
    for other in (
        scores(100.0, 3 * truth_sd),
        scores(100.0, truth_sd / 3),
        scores(108.0, truth_sd),
    ):
        assert correct[0] < other[0]  # interval score
        assert correct[1] < other[1]  # CRPS
    # the CRPS of the correct forecast lies below the MAPE of its median as a point forecast
    assert correct[1] < np.mean(np.abs(y - 100.0) / y) * 100.0


def test_records_gain_the_scores_only_with_intervals() -> None:
    preds = pd.DataFrame(
        {
            "model": ["mm"] * 4,
            "method": ["bayes"] * 2 + ["ol"] * 2,
            "well": ["A"] * 4,
            "predicted": [100.0, 100.0, 100.0, 100.0],
            "measured": [100.0, 115.0, 100.0, 115.0],
            "predicted_p05": [90.0, 90.0, np.nan, np.nan],
            "predicted_p95": [110.0, 110.0, np.nan, np.nan],
        }
    )
    bayes, ol = metrics_records(preds)
    assert bayes["interval_score90"] == pytest.approx((0.2 + 120.0 / 115.0) / 2 * 100.0)
    assert bayes["crps"] == pytest.approx(
        probabilistic_scores([100.0, 115.0], [90.0] * 2, [110.0] * 2)[1]
    )
    assert bayes["coverage90"] == pytest.approx(0.5)  # the existing fields stay
    assert not {"interval_score90", "crps", "coverage90"} & set(ol)


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scores")
    data = root / "field.parquet"
    args = ["simulate", "--out", str(data), "--wells", "2", "--years", "1.2"]
    assert main([*args, "--start", "2018-06-01", "--seed", "8", "--quiet"]) == 0
    out = root / "eval"
    args = ["evaluate", str(data), "--out", str(out), "--models", "mm", "--methods", "ol,bayes"]
    assert main([*args, "--jobs", "1", "--quiet"]) == 0
    return out


def test_vfm_evaluate_writes_the_scores_for_bayes_and_not_for_ol(evaluated: Path) -> None:
    metrics = json.loads((evaluated / "metrics.json").read_text(encoding="utf-8"))
    preds = pd.read_parquet(evaluated / "predictions.parquet")
    totals = [r for r in metrics["records"] if "target" not in r]
    bayes = [r for r in totals if r["method"] == "bayes"]
    ol = [r for r in totals if r["method"] == "ol"]
    assert len(bayes) == 2 and len(ol) == 2
    for r in ol + [s for s in metrics["summary"] if s["method"] == "ol"]:
        assert not {"interval_score90", "crps"} & set(r)
    for r in bayes:
        g = preds[(preds["method"] == "bayes") & (preds["well"] == r["well"])]
        # the record is the score of what predictions.parquet holds, recomputed here
        score90, crps = probabilistic_scores(g["measured"], g["predicted_p05"], g["predicted_p95"])
        assert r["interval_score90"] == pytest.approx(score90)
        assert r["crps"] == pytest.approx(crps)
        # the interval score is at least the relative width, which is about width90
        assert r["interval_score90"] >= 0.5 * r["width90"]
        assert 0.0 < r["crps"] < r["interval_score90"]
    (summary,) = [s for s in metrics["summary"] if s["method"] == "bayes" and "target" not in s]
    assert summary["crps"] == pytest.approx(np.mean([r["crps"] for r in bayes]))
    assert summary["interval_score90"] == pytest.approx(
        np.mean([r["interval_score90"] for r in bayes])
    )


def test_the_report_gives_the_crps_beside_the_coverage(evaluated: Path) -> None:
    preds = pd.read_parquet(evaluated / "predictions.parquet")
    g = preds[preds["method"] == "bayes"]
    _, crps = probabilistic_scores(g["measured"], g["predicted_p05"], g["predicted_p95"])
    html = (evaluated / "report.html").read_text(encoding="utf-8")
    # pooled over the wells, as the coverage beside it
    caption = html.split("Predictive intervals: calibration")[1].split("</figure>")[0]
    assert f"(CRPS {crps:.1f}&nbsp;%)" in caption
    assert caption.count("(CRPS ") == 1  # one run with intervals (bayes), none for ol
