"""Rival explanations (:mod:`vfm_core.jobs.diagnose_rivals`), on constructed runs with a known
answer (no fitting: fast).

Four wells, two years of daily measurements. The baseline misses two things: ``a`` (up to 8 %,
following one variable) and ``b`` (up to 3 %, following another). A candidate that removes ``a``
and one that removes ``b`` are both at work; one that removes ``a`` only partly is
explained by the one that removes all of it; two that remove the same ``a`` cannot be told
apart. The pair's run is what fitting both together would give. Two that neither adds beyond
are told apart by their shape beyond the trend: the residual follows the physics' ups and
downs, not a trend proxy's.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from vfm_core.jobs import diagnose as dg
from vfm_core.jobs import diagnose_rivals as rv
from vfm_core.jobs import diagnose_verdicts as dv
from vfm_core.jobs.study import RunResult

WELLS = ["W01", "W02", "W03", "W04"]
DAYS = 730


@pytest.fixture(scope="module")
def parts() -> dict[str, np.ndarray]:
    """The two misfits, the noise, and the frame they are added to."""
    rng = np.random.default_rng(7)
    n = DAYS * len(WELLS)
    x1 = rng.uniform(-1, 1, n)  # what ``a`` follows (the choke, say)
    x2 = np.sin(np.linspace(0, 6 * np.pi, n))  # what ``b`` follows (the gas fraction)
    return {"a": 0.08 * x1, "b": 0.03 * x2, "noise": 0.01 * rng.normal(size=n)}


def _frame() -> pd.DataFrame:
    times = pd.date_range("2020-01-01", periods=DAYS, freq="D", tz="UTC")
    return pd.concat(
        [
            pd.DataFrame(
                {
                    "time": times,
                    "well": w,
                    "source": "mpfm",
                    "measured": 100.0,
                    "in_outage": np.zeros(DAYS, dtype=bool),
                }
            )
            for w in WELLS
        ],
        ignore_index=True,
    )


def _cand(
    name: str, rel_error: np.ndarray, delta_bic: float, base_mape: float
) -> dg.CandidateResult:
    p = _frame()
    p["predicted"] = p["measured"] * (1.0 + rel_error)
    m = dg.mape(p["predicted"], p["measured"])
    return dg.CandidateResult(
        effect=name,
        mape=m,
        delta_mape=m - base_mape,
        bic=0.0,
        delta_bic=delta_bic,
        n_parameters=4,
        parameters={},
        meaning=f"{name} fitted.",
        material=True,
        run=RunResult("mm", "pbl:36500d", p),
        delta_bic_all=delta_bic,
        spec=name,
    )


def _base_mape(parts: dict[str, np.ndarray]) -> float:
    return float(100.0 * np.mean(np.abs(parts["a"] + parts["b"] + parts["noise"])))


def test_two_effects_at_work_are_both_kept(parts: dict[str, np.ndarray]) -> None:
    base = _base_mape(parts)
    lead = _cand("valve_sigmoid", parts["b"] + parts["noise"], -300.0, base)
    rival = _cand("slip", parts["a"] + parts["noise"], -200.0, base)
    pair = _cand("valve_sigmoid+slip", parts["noise"], -600.0, base)
    assert rv.relate(lead, rival, pair, 0) == "both"
    assert lead.explained_by is None and rival.explained_by is None
    assert lead.rivals["slip"]["relation"] == "both"
    assert rival.rivals["valve_sigmoid"]["relation"] == "both"
    assert lead.rivals["slip"]["it_adds"]["adds"] and lead.rivals["slip"]["adds_beyond_it"]["adds"]
    assert "diagnose again" in rv.rivals_text(lead)


def test_a_partial_explanation_is_explained_by_the_whole_one(parts: dict[str, np.ndarray]) -> None:
    base = _base_mape(parts)
    whole = parts["b"] + parts["noise"]  # removes all of a
    lead = _cand("slip", whole, -300.0, base)
    rival = _cand("valve_sigmoid", 0.5 * parts["a"] + parts["b"] + parts["noise"], -150.0, base)
    pair = _cand("slip+valve_sigmoid", whole, -290.0, base)  # nothing more: 4 more parameters
    assert rv.relate(lead, rival, pair, 0) == "explains"
    assert rival.explained_by == "slip" and lead.explained_by is None
    assert not rival.named and lead.named
    # the other way round: the lead is the partial one, and the rival takes over
    lead2 = _cand("valve_sigmoid", 0.5 * parts["a"] + parts["b"] + parts["noise"], -310.0, base)
    rival2 = _cand("slip", whole, -300.0, base)
    pair2 = _cand("valve_sigmoid+slip", whole, -330.0, base)
    assert rv.relate(lead2, rival2, pair2, 0) == "explained_by"
    assert lead2.explained_by == "slip" and rival2.explained_by is None


def test_two_forms_of_the_same_misfit_cannot_be_told_apart(parts: dict[str, np.ndarray]) -> None:
    base = _base_mape(parts)
    same = parts["b"] + parts["noise"]
    lead = _cand("valve_sigmoid", same, -300.0, base)
    rival = _cand("erosion", same + 0.001 * parts["a"], -290.0, base)
    pair = _cand("valve_sigmoid+erosion", same, -295.0, base)
    assert rv.relate(lead, rival, pair, 0) == "indistinguishable"
    assert lead.explained_by is None and rival.explained_by is None
    assert "cannot tell them apart" in rv.rivals_text(lead)
    # the one ranked second is neither offered nor named on its own: its evidence is the lead's
    assert rv.second_to(rival) == "valve_sigmoid" and rv.second_to(lead) is None
    rival.replayed = True
    ok, reason = dv.offer(rival, None)
    assert not ok and reason.startswith("the data cannot tell it from valve_sigmoid")
    assert not dv._fit_once_names(rival, None)


def test_rivals_are_other_physics_and_explained_physics_is_explained_in_every_form(
    parts: dict[str, np.ndarray],
) -> None:
    base = _base_mape(parts)
    e = parts["noise"]
    results = [
        _cand("valve_sigmoid", e, -300.0, base),
        _cand("valve_convex", e, -290.0, base),  # same physics: not a rival
        _cand("slip", e, -250.0, base),
        _cand("erosion_time", e, -240.0, base),
        _cand("real_gas", e, -230.0, base),  # past RIVALS
    ]
    results[-1].material = True
    lead, others = rv.rivals(results)
    assert lead is results[0] and [c.effect for c in others] == ["slip", "erosion_time"]
    assert rv.RIVALS == 2
    results[0].explained_by = "slip"
    rv.explain_families(results)
    assert results[1].explained_by == "slip"  # the weaker valve form too
    assert results[2].explained_by is None and results[3].explained_by is None


def test_an_explained_candidate_is_neither_offered_nor_named(parts: dict[str, np.ndarray]) -> None:
    base = _base_mape(parts)
    c = _cand("valve_sigmoid", parts["noise"], -300.0, base)
    c.replayed = True
    c.explained_by = "slip"
    ok, reason = dv.offer(c, None)
    assert not ok and reason.startswith("explained by slip")


def _run_cand(
    name: str, p: pd.DataFrame, delta_bic: float, n_parameters: int = 4
) -> dg.CandidateResult:
    """A material candidate whose fit-once run predicted ``p`` (baseline MAPE 3 %)."""
    m = dg.mape(p["predicted"], p["measured"])
    return dg.CandidateResult(
        effect=name,
        mape=m,
        delta_mape=m - 3.0,
        bic=0.0,
        delta_bic=delta_bic,
        n_parameters=n_parameters,
        parameters={},
        meaning="",
        material=True,
        run=RunResult("mm", "pbl:36500d", p),
        delta_bic_all=delta_bic,
    )


def _log_run(log_pred_shift: np.ndarray) -> pd.DataFrame:
    """A prediction frame whose log prediction is 100 shifted by ``log_pred_shift``."""
    p = _frame()
    p["predicted"] = p["measured"] * np.exp(log_pred_shift)
    return p


def _misfit(seed: int, per_year: float, sd: float) -> tuple[np.ndarray, ...]:
    """Over every well's days: a trend of ``per_year``, two wiggles of sd ``sd`` (in two
    variables) and a noise of sd 0.002, drawn in that order from ``seed``."""
    rng = np.random.default_rng(seed)
    n = DAYS * len(WELLS)
    years = np.tile(np.arange(DAYS) / 365.25, len(WELLS))
    one, two = sd * rng.normal(size=n), sd * rng.normal(size=n)
    return per_year * years, one, two, 0.002 * rng.normal(size=n)


def test_the_shape_beyond_the_trend_tells_the_physics_from_a_trend_proxy() -> None:
    """The misfit is a trend (5 % over the years) plus a small wiggle in one variable (0.3 %):
    the physics removes both, a trend proxy the trend and a wiggle in another variable. Their
    errors differ too little to be material, so the encompassing test cannot tell them apart;
    the shape beyond the trend can."""
    trend, wiggle, other, noise = _misfit(3, 0.025, 0.003)
    base = _log_run(-(trend + wiggle) + noise)  # r = trend + wiggle - noise
    physics = _log_run(noise)  # its correction: trend + wiggle
    proxy = _log_run(-(trend + wiggle) + noise + trend + other)
    (holds,) = rv.shape_beyond_trend(base, physics)
    (rejected,) = rv.shape_beyond_trend(base, proxy)
    assert holds["beta"] == pytest.approx(1.0, abs=3 * holds["se"]) and not holds["rejected"]
    assert rejected["beta"] < 0.5 and rejected["rejected"]
    assert holds["confirmed"] and not rejected["confirmed"]
    # a fitted correction a little too large (slope 0.87, as estimation errors shrink it) is
    # still the physics: only a slope closer to 0 than to 1 is rejected
    (shrunk,) = rv.shape_beyond_trend(base, _log_run(noise + 0.15 * (trend + wiggle)))
    assert 0.8 < shrunk["beta"] < 0.95 and not shrunk["rejected"] and shrunk["confirmed"]
    # judged side by side, the same answer
    holds2, rejected2 = rv.shape_beyond_trend(base, physics, proxy)
    assert not holds2["rejected"] and rejected2["rejected"]
    # a correction that is only a trend predicts nothing beyond it: nothing to reject, and
    # the other is still judged
    flat, beside = rv.shape_beyond_trend(base, _log_run(-(trend + wiggle) + noise + trend), proxy)
    assert flat["spread"] < 1e-6 and not flat["rejected"] and flat["beta"] is None
    assert beside["rejected"]

    lead, rival = _run_cand("slip", proxy, -300.0), _run_cand("erosion", physics, -280.0)
    pair = _run_cand("slip+erosion", physics, -275.0)
    assert rv.relate(lead, rival, pair, 0, base) == "shape_loses"
    assert lead.explained_by == "erosion" and rival.explained_by is None
    assert "does not fit the residual" in rv.why_explained(lead)
    assert "fits the residual less than" in rv.rivals_text(rival)
    # without the comparison's predictions the two stay indistinguishable
    lead2, rival2 = _run_cand("slip", proxy, -300.0), _run_cand("erosion", physics, -280.0)
    assert rv.relate(lead2, rival2, pair, 0) == "indistinguishable"


def test_relations_with_an_explained_candidate_go_stale(parts: dict[str, np.ndarray]) -> None:
    """valve is at work beside slip (``both``), then explained by erosion: slip's verdict
    no longer lists valve as its next step, nor does anything stay second to it."""
    base = _base_mape(parts)
    e = parts["noise"]
    slip = _cand("slip", e, -300.0, base)
    valve = _cand("valve_sigmoid", e, -290.0, base)
    slip.rivals["valve_sigmoid"] = {"relation": "both", "ranked_first": True}
    valve.rivals["slip"] = {"relation": "both", "ranked_first": False}
    valve.explained_by = "erosion"
    rv.prune_stale([slip, valve])
    assert rv.current(slip, "both") == [] and slip.rivals["valve_sigmoid"]["stale"]
    assert "valve_sigmoid" not in rv.rivals_text(slip)


def test_a_shape_that_is_nearly_all_trend_decides_nothing_and_loses_to_nothing() -> None:
    """Wear beside slip on a field whose gas fraction rises: both take up the trend, slip's
    correction also follows the gas fraction's ups and downs (its shape is confirmed), wear's
    is a trend with a slight bend (a hundredth of a percent beyond the straight line), and
    a slow misfit that neither explains (0.3 %, over months) is left. Wear's test cannot tell a trend proxy from the physics (``decisive`` false): it is
    neither rejected nor beaten by slip's confirmed shape, and the two stay
    indistinguishable, the one ranked first by the evidence named."""
    rng = np.random.default_rng(5)
    n = DAYS * len(WELLS)
    years = np.tile(np.arange(DAYS) / 365.25, len(WELLS))
    trend, wiggle = 0.03 * years, 0.003 * rng.normal(size=n)
    noise = 0.002 * rng.normal(size=n)
    kernel = np.ones(90) / 90.0  # a misfit neither explains, slow (months) as real ones are
    slow = 0.03 * np.concatenate(
        [np.convolve(rng.normal(size=DAYS + 89), kernel, "valid") for _ in WELLS]
    )
    base = _log_run(-(trend + wiggle + slow) + noise)
    slip = _log_run(noise - slow)  # its correction: the trend and the wiggle
    bend = 0.0004 * (years - 1.0) ** 2
    wear = _log_run(-(trend + wiggle + slow) + noise + trend + bend)
    s_slip, s_wear = rv.shape_beyond_trend(base, slip, wear)
    assert s_slip["decisive"] and s_slip["confirmed"] and not s_slip["rejected"]
    assert 0 < s_wear["spread"] < 0.05 and not s_wear["decisive"]
    assert not s_wear["rejected"] and not s_wear["confirmed"]

    lead, rival = _run_cand("erosion", wear, -300.0, 1), _run_cand("slip", slip, -290.0, 1)
    pair = _run_cand("erosion+slip", slip, -295.0, 1)  # neither adds materially beyond the other
    assert rv.relate(lead, rival, pair, 0, base) == "indistinguishable"
    assert lead.explained_by is None and rival.explained_by is None
    assert rv.stands_alone(lead) and rv.second_to(rival) == "erosion"


def test_a_gain_below_a_tenth_of_a_point_is_not_offered(parts: dict[str, np.ndarray]) -> None:
    """A replay over years finds a few hundredths of a point beyond chance for a candidate that
    only absorbs misfit: lower beyond chance, but under :data:`dv.MIN_CHANGE`, it is not
    offered (and a tenth of a point is)."""
    base = _base_mape(parts)
    c = _cand("erosion", parts["noise"], -300.0, base)
    c.replayed = True
    c.live_run = c.run
    c.tests["fit_once"] = {"change": -0.5, "rejected": True, "p_value": 1e-6, "per_well": {}}
    small = {"change": -0.03, "low": -0.05, "high": -0.02, "rejected": True, "per_well": {}}
    c.tests["live"] = dict(small)
    c.tests["outage"] = {**small, "rejected": False}
    assert c.named
    ok, reason = dv.offer(c, None)
    assert not ok and "less than 0.1 points" in reason
    c.tests["live"] = {**small, "change": -dv.MIN_CHANGE}
    assert dv.offer(c, None) == (True, "live")


def test_a_named_candidate_whose_shape_cannot_decide_says_its_evidence_is_a_trend(
    parts: dict[str, np.ndarray],
) -> None:
    """own_shapes tests each material candidate alone; a wear-like one (nearly all trend)
    gets the caveat in its verdict, one whose shape decides does not."""
    rng = np.random.default_rng(11)
    n = DAYS * len(WELLS)
    years = np.tile(np.arange(DAYS) / 365.25, len(WELLS))
    trend, wiggle = 0.03 * years, 0.01 * rng.normal(size=n)
    kernel = np.ones(90) / 90.0
    slow = 0.03 * np.concatenate(
        [np.convolve(rng.normal(size=DAYS + 89), kernel, "valid") for _ in WELLS]
    )
    base = _log_run(-(trend + wiggle + slow))
    base_mape = _base_mape(parts)
    wear = _cand("erosion", parts["noise"], -300.0, base_mape)
    wear.run = RunResult("mm", "pbl:36500d", _log_run(-(wiggle + slow) + 0.0004 * years**2))
    valve = _cand("valve_sigmoid", parts["noise"], -200.0, base_mape)
    valve.run = RunResult("mm", "pbl:36500d", _log_run(-(trend + slow)))
    rv.own_shapes([wear, valve], base)
    assert wear.shape is not None and not wear.shape["decisive"]
    assert valve.shape is not None and valve.shape["decisive"] and valve.shape["confirmed"]
    assert "mostly a trend in time" in rv.trend_text(wear)
    assert rv.trend_text(valve) == ""


def test_a_lead_whose_own_shape_is_rejected_is_a_trend_proxy_neither_named_nor_offered() -> None:
    """Clean Bernoulli seed 5502 with ``mm``: a valve curve lowered the fit-once error by
    0.44 points, with no material rival of other physics to weigh it against, and was named
    (``carried``), though beyond the trend its slope was 0.06 +/- 0.16: the choke opened as
    the field depleted, and the curve stood in for the trend. Here: the misfit is a trend
    and a wiggle in one variable; the valve removes the trend and follows another variable;
    wear removes the trend only (its own test cannot decide: it stays the lead)."""
    trend, wiggle, other, noise = _misfit(13, 0.025, 0.003)
    base = _log_run(-(trend + wiggle) + noise)
    valve = _run_cand("valve_quick_opening", _log_run(-wiggle + noise + other), -300.0)
    wear = _run_cand("erosion", _log_run(-wiggle + noise + 0.0004 * trend**2), -250.0)
    valve.replayed = wear.replayed = True
    rv.own_shapes([valve, wear], base)
    assert valve.shape is not None and valve.shape["decisive"] and valve.shape["rejected"]
    assert valve.trend_proxy and not valve.named and not rv.stands_alone(valve)
    assert wear.shape is not None and not wear.trend_proxy and wear.named
    lead, others = rv.rivals([valve, wear])
    assert lead is wear and others == []
    ok, reason = dv.offer(valve, None)
    assert not ok and "a trend it stands in for, not its physics" in reason
    assert valve.to_json()["trend_proxy"] is True
    # a shape that holds is no proxy: the physics' own correction (trend and wiggle)
    physics = _run_cand("valve_quick_opening", _log_run(noise), -300.0)
    rv.own_shapes([physics], base)
    assert physics.shape is not None and physics.shape["confirmed"] and not physics.trend_proxy


def _with_wells(c: dg.CandidateResult, key: str, values: list[float], sds: list[float]) -> None:
    """Give ``c`` one parameter with these per-well values and Laplace sds."""
    c.parameters = {
        key: {
            "value": float(np.median(values)),
            "per_well": dict(zip(WELLS, values, strict=True)),
            "per_well_sd": dict(zip(WELLS, sds, strict=True)),
        }
    }


def test_a_field_wide_effect_whose_wells_disagree_explains_no_effect_of_the_wells(
    parts: dict[str, np.ndarray],
) -> None:
    """Slip is one physics at every well. Fitted alone on a worn field it takes up each
    well's wear with its own exponent (1.9, 1.0, 1.6, 1.0 +- 0.1-0.3: Cochran's Q far beyond
    chance) and would "explain" the wear; with its wells' values agreeing it still does."""
    base = _base_mape(parts)
    whole = parts["b"] + parts["noise"]

    def rivalry(exponents: list[float]) -> tuple[str, dg.CandidateResult, dg.CandidateResult]:
        lead = _cand("slip", whole, -300.0, base)
        _with_wells(lead, "slip.exponent", exponents, [0.1, 0.1, 0.1, 0.3])
        rival = _cand("erosion", 0.5 * parts["a"] + parts["b"] + parts["noise"], -150.0, base)
        _with_wells(rival, "erosion.rate", [0.07, 0.0, 0.05, 0.01], [0.005] * 4)
        pair = _cand("slip+erosion", whole, -290.0, base)
        rv.own_consistency([lead, rival])
        return rv.relate(lead, rival, pair, 0), lead, rival

    agree, lead, rival = rivalry([1.0, 1.1, 0.95, 1.05])
    assert lead.consistency is not None and lead.consistency["consistent"]
    assert rival.consistency is None  # wear belongs to each well: its rates may differ
    assert agree == "explains" and rival.explained_by == "slip"

    disagree, lead, rival = rivalry([1.9, 1.0, 1.6, 1.0])
    k = lead.consistency
    assert k is not None and k["df"] == 3 and k["p_value"] < 0.001 and not k["consistent"]
    assert disagree == "explained_by"
    assert lead.explained_by == "erosion" and rival.explained_by is None
    assert lead.rivals["erosion"]["reason"] == "wells_disagree"
    assert "its wells' values disagree (Cochran's Q" in rv.why_explained(lead)
    assert "It explains slip too" in rv.rivals_text(rival)


def test_cochrans_q_by_hand() -> None:
    """Values 1 and 2 with sds 0.5 and 0.5: weighted mean 1.5, Q = 2 (0.5 / 0.5)^2 = 2 on
    1 df, p = 0.157; a single well, or an effect of the wells, is not tested."""
    c = dg.CandidateResult("slip", 3.0, -0.1, 0.0, -10.0, 2, {}, "", True)
    c.parameters = {
        "slip.exponent": {
            "per_well": {"W01": 1.0, "W02": 2.0},
            "per_well_sd": {"W01": 0.5, "W02": 0.5},
        }
    }
    k = rv.consistency(c)
    assert k is not None and k["df"] == 1 and abs(k["q"] - 2.0) < 1e-12
    assert abs(k["p_value"] - 0.1573) < 1e-4 and k["consistent"]
    c.parameters["slip.exponent"]["per_well"] = {"W01": 1.0}
    assert rv.consistency(c) is None
    c.effect = "erosion"
    assert rv.consistency(c) is None


def test_a_slope_above_one_beyond_chance_is_no_confirmation() -> None:
    """The residual beyond the trend moves three times as much as a candidate's correction
    does (slope about 3, far above 1 beyond chance): the size its trend calls for is not
    the size of its ups and downs, so its shape is not confirmed (a fitted correction's
    errors shrink the slope below 1, never above). Against a rival whose shape holds at
    a slope a little below 1 (a valve, on the Bernoulli truth's sigmoid valve: 0.85 +/-
    0.03 beside wear's 1.89 +/- 0.25) the overshooting one loses."""
    trend, wiggle, valve_wiggle, noise = _misfit(11, 0.03, 0.004)
    # r = trend + 3 wiggle + valve_wiggle - noise
    base = _log_run(-(trend + 3.0 * wiggle + valve_wiggle) + noise)
    over = _log_run(-(trend + 3.0 * wiggle + valve_wiggle) + noise + trend + wiggle)
    valve = _log_run(-(trend + 3.0 * wiggle + valve_wiggle) + noise + trend + valve_wiggle / 0.85)
    (alone,) = rv.shape_beyond_trend(base, over)
    assert alone["beta"] > 2.0 and alone["decisive"] and alone["overshoots"]
    assert not alone["confirmed"] and not alone["rejected"] and not alone["at_physics"]
    assert "above 1 beyond chance" in rv._shape_text(alone)
    s_over, s_valve = rv.shape_beyond_trend(base, over, valve)
    assert s_valve["confirmed"] and not s_valve["overshoots"] and not s_over["confirmed"]

    lead, rival = _run_cand("erosion", over, -300.0, 1), _run_cand("valve_sigmoid", valve, -290.0)
    pair = _run_cand("erosion+valve_sigmoid", valve, -295.0)  # neither adds beyond the other
    assert rv.relate(lead, rival, pair, 0, base) == "shape_loses"
    assert lead.explained_by == "valve_sigmoid" and rival.explained_by is None


def test_an_undecided_trend_loses_to_a_field_wide_physics_at_its_own_slope() -> None:
    """The construction of the test above on wear beside slip (wear nearly all trend, slip's
    shape confirmed at slope about 1), now with slip's wells agreeing on one exponent: slip
    carries the trend as well as wear (neither adds beyond the other) and its ups and downs
    at their size, with one value at every well; wear, predicting nothing beyond the trend,
    is explained by it. With slip's wells disagreeing (each well's own exponent taking up
    its own trend, as on worn fields) wear explains slip, as before."""
    rng = np.random.default_rng(5)
    n = DAYS * len(WELLS)
    years = np.tile(np.arange(DAYS) / 365.25, len(WELLS))
    trend, wiggle = 0.03 * years, 0.003 * rng.normal(size=n)
    noise = 0.002 * rng.normal(size=n)
    kernel = np.ones(90) / 90.0
    slow = 0.03 * np.concatenate(
        [np.convolve(rng.normal(size=DAYS + 89), kernel, "valid") for _ in WELLS]
    )
    base = _log_run(-(trend + wiggle + slow) + noise)
    slip_run = _log_run(noise - slow)
    bend = 0.0004 * (years - 1.0) ** 2
    wear_run = _log_run(-(trend + wiggle + slow) + noise + trend + bend)

    def rivalry(exponents: list[float]) -> tuple[str, dg.CandidateResult, dg.CandidateResult]:
        lead, rival = (
            _run_cand("erosion", wear_run, -300.0, 1),
            _run_cand("slip", slip_run, -290.0, 1),
        )
        _with_wells(rival, "slip.exponent", exponents, [0.1, 0.1, 0.1, 0.3])
        pair = _run_cand("erosion+slip", slip_run, -295.0, 1)
        return rv.relate(lead, rival, pair, 0, base), lead, rival

    agree, lead, rival = rivalry([1.0, 1.1, 0.95, 1.05])
    assert rival.consistency is not None and rival.consistency["consistent"]
    shape = lead.rivals["slip"]["its_shape"]
    assert shape["at_physics"] and not lead.rivals["slip"]["shape"]["decisive"]
    assert agree == "shape_loses" and lead.explained_by == "slip" and rival.explained_by is None
    assert "one value at every well" in rv.why_explained(lead)

    disagree, lead, rival = rivalry([1.9, 1.0, 1.6, 1.0])
    assert disagree == "explains" and rival.explained_by == "erosion"


def test_a_lead_that_is_mostly_trend_must_beat_the_operating_point_physics(
    parts: dict[str, np.ndarray],
) -> None:
    """Wear named by a trend alone (its own shape cannot decide) is weighed against the best
    field-wide candidate that lowers the error, material or not (on the clean Bernoulli field
    of seed 75, slip: -0.13 points alone, under the material minimum); a lead whose shape
    decides, or one already weighed against a field-wide rival, is not."""
    base = _base_mape(parts)
    wear = _cand("erosion", parts["b"] + parts["noise"], -100.0, base)
    slip = _cand("slip", parts["a"] + parts["noise"], -110.0, base)
    slip.material, slip.delta_mape = False, -0.13
    gas = _cand("real_gas", parts["a"] + parts["noise"], +20.0, base)
    gas.material, gas.delta_mape = False, 0.09
    undecided = {"beta": -2.6, "se": 0.83, "blocks": 70, "spread": 0.08, "decisive": False}
    wear.shape = {**undecided, "rejected": False, "confirmed": False}
    assert rv.mostly_trend(wear)
    lead, others = rv.rivals([slip, wear, gas])
    assert lead is wear and others == [slip]
    wear.shape = {**wear.shape, "decisive": True}
    assert rv.rivals([slip, wear, gas]) == (wear, [])
    wear.shape = {**wear.shape, "decisive": False}
    slip.material = True  # a material field-wide rival is weighed anyway, once
    assert rv.rivals([wear, slip, gas]) == (wear, [slip])
