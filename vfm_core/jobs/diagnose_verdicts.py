"""The verdicts of ``vfm diagnose`` under the live and outage protocols, and the fit-once one.

Each candidate replayed under the well's own learning method is compared with the replayed
baseline by paired block tests (:func:`protocol_test`, :func:`test_candidate`; the tests
themselves in :mod:`vfm_core.jobs.diagnose_live`), all tests of a diagnosis in one
Benjamini-Hochberg family (:func:`fdr`). A candidate is offered when it raises neither
error and a test finds a lower one beyond chance (:func:`offer`). :func:`live_verdict`
gives one verdict, the field's or a well's: ``effect``, ``driver``, ``carried`` or
``noise``; :func:`physics_behind_driver` names a library effect through the driver a
correction was fitted in; :func:`instrument_check` turns a verdict whose evidence
coincides with a sensor fault into ``instrument``; :func:`fit_once_verdict` is the verdict
the fit-once evidence alone gives (format 2's rule). The protocol that calls them is
:func:`vfm_core.jobs.diagnose.run_diagnosis`; everything here reads the result types of
:mod:`vfm_core.jobs.diagnose_results` and writes into them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from vfm_core.data import target_mask
from vfm_core.effects import Effect, effect_spec
from vfm_core.jobs import diagnose_instrument as inst
from vfm_core.jobs import diagnose_live as live
from vfm_core.jobs import diagnose_rivals as rivals
from vfm_core.jobs import diagnose_stats as stats
from vfm_core.jobs.diagnose_results import (
    HYBRIDS,
    MATERIAL_BIC,
    MATERIAL_MAPE_NEAR_FLOOR,
    CandidateResult,
    Suggestion,
    brief,
)
from vfm_core.jobs.diagnose_stats import acts_through
from vfm_core.jobs.study import mape
from vfm_core.schema import TIME, WELL

if TYPE_CHECKING:
    from vfm_core.jobs.study import RunResult

__all__ = [
    "REPLAY_TOP",
    "PHYSICS_ALPHA",
    "MIN_CHANGE",
    "VerdictContext",
    "model_label",
    "protocol_test",
    "test_candidate",
    "fdr",
    "offer",
    "live_verdict",
    "driver_found",
    "physics_behind_driver",
    "set_offers",
    "bound_wells",
    "at_bound",
    "weigh_forms",
    "baseline_info",
    "outage_info",
    "service_error",
    "instrument_check",
    "fit_once_verdict",
    "few_blocks_text",
    "untested_text",
    "below_minimum",
    "below_minimum_text",
    "suggestive",
    "suggestive_text",
]

#: Candidates replayed under the well's own learning method (live and outage), best first by
#: the fit-once BIC among those that lowered the fit-once error: a compute budget, not a test
#: (the others count in the false-discovery family with p = 1).
REPLAY_TOP = 3
#: The physics behind a driver (:func:`physics_behind_driver`): a library effect that acts
#: through the variable a correction was fitted in
#: (:func:`vfm_core.jobs.diagnose_stats.acts_through`) is the verdict in place of the
#: correction unless the correction's error is lower beyond the replay's noise: a
#: one-sided paired block test at this level (not adjusted: adjusting would make "the
#: correction is better" harder to find, and so favour the library effect) and the effect's
#: gain outside the correction's own 95 % interval (:func:`_beats`).
PHYSICS_ALPHA = 0.05
#: The smallest fall of the live or the outage MAPE (points) that offers a change of model.
#: Replayed over years, a flexible candidate that absorbs misfit which is not its physics
#: lowers a learner's error by a few hundredths of a point, beyond chance (erosion on a
#: clean field of another physics whose misfit drifts with depletion: -0.03 points); a
#: change that small is not worth a model change, and naming an effect for it misleads. The
#: same minimum a candidate must remove near the noise floor in the fit-once evidence
#: (:data:`vfm_core.jobs.diagnose_results.MATERIAL_MAPE_NEAR_FLOOR`).
MIN_CHANGE = MATERIAL_MAPE_NEAR_FLOOR


def model_label(model: str, classes: Sequence[type[Effect]]) -> str:
    """``mm``, or ``mm+erosion`` with effects."""
    return "+".join([model, *(effect_spec(c) for c in classes)])


def _untested(wells: Sequence[str], reason: str) -> dict[str, Any]:
    one: dict[str, Any] = {
        "change": None,
        "low": None,
        "high": None,
        "p_value": 1.0,
        "n": 0,
        "n_blocks": 0,
        "replayed": False,
        "reason": reason,
    }
    return {**one, "per_well": {w: dict(one) for w in wells} if len(wells) > 1 else {}}


def protocol_test(
    base: pd.DataFrame,
    cand: pd.DataFrame,
    wells: Sequence[str],
    seed: int,
    in_outage: bool = False,
) -> dict[str, Any]:
    """The paired block test of one candidate under one protocol: the field's (pooled over
    the wells) with each well's own beside it (same block length)."""
    if in_outage:
        keep = base["in_outage"].to_numpy(dtype=bool)
        base, cand = base[keep], cand[keep]
    pairs = live.paired_differences(base, cand)
    pooled = live.paired_test(pairs, seed=seed)
    per_well: dict[str, Any] = {}
    if len(wells) > 1:
        days = pooled["block_days"]
        for w in wells:
            per_well[w] = live.paired_test(pairs[pairs["well"] == w], days, seed=seed)
            per_well[w]["replayed"] = True
    return {**pooled, "replayed": True, "per_well": per_well}


def trial_test(
    base: pd.DataFrame, cand: pd.DataFrame, wells: Sequence[str], since: pd.Timestamp
) -> dict[str, Any]:
    """The trial forecast of one candidate (:func:`vfm_core.jobs.diagnose_live.trial_forecast`):
    ``cand`` is its backtest run (fitted before ``since``, the last
    :data:`~vfm_core.jobs.diagnose_live.TRIAL_DAYS` days of data, then learning), ``base``
    the baseline's live replay (the shadow) on the same rows; the field's (pooled over the
    wells) with each well's own beside it."""
    keep = (pd.to_datetime(base["time"], utc=True) >= since).to_numpy()
    shadow = base[keep].reset_index(drop=True)
    cand = cand.reset_index(drop=True)
    key = ["well", "time", "measured"]
    if len(shadow) != len(cand) or not shadow[key].equals(cand[key]):
        # the same measurements by key (a row the shadow lacks is dropped as not finite)
        shadow = cand[key].merge(shadow.drop_duplicates(key), on=key, how="left")
    pairs = live.paired_differences(shadow, cand)
    one = live.trial_forecast(pairs)
    per_well = (
        {
            w: {**live.trial_forecast(pairs[pairs["well"] == w]), "since": since.isoformat()}
            for w in wells
        }
        if len(wells) > 1
        else {}
    )
    return {**one, "since": since.isoformat(), "replayed": True, "per_well": per_well}


def test_candidate(
    c: CandidateResult,
    comp: RunResult,
    base: RunResult,
    base_out: RunResult | None,
    wells: Sequence[str],
    seed: int,
    replay_top: int = REPLAY_TOP,
    trial_since: pd.Timestamp | None = None,
) -> None:
    """Fill ``c.tests``: fit-once against the comparison baseline; live and outage against
    the replayed baseline (untested, p = 1, when the candidate was not replayed: only the
    best ``replay_top`` are); the trial forecast from ``trial_since`` (:func:`trial_test`)
    when the candidate has its backtest run."""
    if c.run is not None:
        c.tests["fit_once"] = protocol_test(comp.predictions, c.run.predictions, wells, seed)
    why = (
        f"not replayed: only the best {replay_top} candidates by the fit-once evidence that "
        "lowered the fit-once error are"
    )
    if c.replayed and c.live_run is not None:
        c.tests["live"] = protocol_test(base.predictions, c.live_run.predictions, wells, seed)
    else:
        c.tests["live"] = _untested(wells, why)
    if base_out is not None:
        if c.replayed and c.outage_run is not None:
            c.tests["outage"] = protocol_test(
                base_out.predictions, c.outage_run.predictions, wells, seed, in_outage=True
            )
        else:
            c.tests["outage"] = _untested(wells, why)
    if c.replayed and c.trial_run is not None and trial_since is not None:
        c.tests["trial"] = trial_test(base.predictions, c.trial_run.predictions, wells, trial_since)


def fdr(
    results: Sequence[CandidateResult],
    suggestion: CandidateResult | None,
    slots: int,
    n_wells: int,
) -> dict[str, Any]:
    """Benjamini-Hochberg over every test of the diagnosis that can reach significance
    (:func:`vfm_core.jobs.diagnose_live.filtered_bh`); writes ``q_value``, ``rejected`` and
    ``in_family`` into each. A candidate not replayed and a correction not fitted
    (``slots``) still count, with p = 1: the family is fixed before the data decide what
    is replayed or fitted. Each such placeholder takes the smallest attainable p-value of
    the tests actually made of its protocol and unit (the field, or its well): it could
    have reached what they can, so it stays in the family whenever they are."""
    tests: list[tuple[tuple[str, str], dict[str, Any]]] = []
    protocols: set[str] = set()
    for c in [*results, *([suggestion] if suggestion is not None else [])]:
        for proto, t in c.tests.items():
            if proto == "trial":  # a forecast of the trial, not a test of the verdict
                continue
            protocols.add(proto)
            tests.append(((proto, ""), t))
            tests += [((proto, w), tw) for w, tw in t.get("per_well", {}).items()]
    reach: dict[tuple[str, str], float] = {}
    for key, t in tests:
        if t.get("replayed", True) and "attainable_p" in t:
            reach[key] = min(reach.get(key, 1.0), float(t["attainable_p"]))
    extra: list[float] = []
    if slots and suggestion is None:
        units = sorted({u for _, u in reach} | {""})
        units = units if n_wells > 1 else [""]
        extra = [reach.get((pr, u), 0.0) for pr in sorted(protocols) for u in units] * slots
        extra += [0.0] * (
            slots * len(protocols) * (1 + (n_wells if n_wells > 1 else 0)) - len(extra)
        )
    p = [float(t.get("p_value", 1.0)) for _, t in tests] + [1.0] * len(extra)
    attainable = [
        float(t["attainable_p"])
        if t.get("replayed", True) and "attainable_p" in t
        else reach.get(key, 0.0)
        for key, t in tests
    ] + extra
    rejected, q, family = live.filtered_bh(p, attainable, live.FDR_Q)
    for i, (_, t) in enumerate(tests):
        t["q_value"] = float(q[i])
        t["rejected"] = bool(rejected[i])
        t["in_family"] = bool(family[i])
    return {
        "procedure": live.PROCEDURE,
        "q": live.FDR_Q,
        "tests": len(p),
        "family": int(family.sum()),
        "rejected": int(rejected.sum()),
    }


def _gain(*tests: dict[str, Any] | None, least: float = MIN_CHANGE) -> bool:
    """Some test (the field's, a well's) finds a lower error beyond chance (BH-rejected), by
    at least ``least`` points (:data:`MIN_CHANGE`)."""
    return any(
        t is not None
        and t.get("rejected")
        and t.get("change") is not None
        and t["change"] <= -least
        for t in tests
    )


def offer(c: CandidateResult, well: str | None) -> tuple[bool, str]:
    """Whether adding ``c`` is offered for ``well`` (None: the field), and why (not).

    Offered when the replay raises neither error (the live change of that well, or of the
    field, and the field's outage change at most 0: never a change that raises the error
    under a reported protocol; a single well's few outage windows are too few to sign its
    own outage change, so the field's is used) and the field's or the well's own test finds
    a lower live or outage error beyond chance (BH over the diagnosis's family), by at least
    :data:`MIN_CHANGE` points. Field-wide
    evidence counts for a well whose own live estimate agrees in sign: physical effects are
    field-wide, and one well's months are weak evidence alone. And only a candidate the
    fit-once evidence names (*material*: the BIC on the reference meter, which charges
    every parameter, and a minimum size), or that is the physics behind a driver the
    evidence found (``via_driver``, :func:`physics_behind_driver`): a flexible candidate can lower a learner's error
    a little by absorbing misfit that is not its physics (on clean fields a tenth of a
    point, significant with years of data); the replay says what adding it does, the
    fit-once evidence what it is. Nor a form of a physics that gives way to another form of
    it (``gives_way``, :func:`weigh_forms`: its parameter sits at a physical bound where the
    other's does not, or the field names the other and this well's evidence does not beat
    it beyond chance)."""
    if not c.replayed:
        return False, "not replayed"
    if c.explained_by is not None:
        return False, rivals.why_explained(c)
    if c.trend_proxy:
        return False, rivals.trend_proxy_text(c)
    first = rivals.second_to(c)
    if first is not None:
        return False, (
            f"the data cannot tell it from {first}, which the evidence ranks first (fitted "
            "together, neither adds beyond the other)"
        )
    if not c.named:
        return False, "not material by the fit-once evidence"
    gives = c.gives_way.get("field" if well is None else well)
    if gives is not None:  # another form of its physics is offered in its place (weigh_forms)
        return False, str(gives["text"])
    lt, ot = c.test("live", well), c.test("outage", well)
    if lt is None or lt.get("change") is None:
        return False, "no replayed measurement"
    if lt["change"] > 0:
        return False, _raises("live", lt)
    of = c.test("outage")
    if of is not None and of.get("change") is not None and of["change"] > 0:
        return False, _raises("outage", of)
    if _gain(c.test("live"), lt if well is not None else None):
        return True, "live"
    if _gain(c.test("outage"), ot if well is not None else None):
        return True, "outage"
    # which test it is, with its change: the note stands beside this well's own figures, and
    # "by less than 0.1 points" beside a well's -0.15 reads as a contradiction when the test
    # that was beyond chance is the field's -0.07
    here = "the field's" if well is None else "this well's"
    named = (
        ("the field's live", c.test("live")),
        (f"{here} live", lt),
        ("the field's outage", c.test("outage")),
        (f"{here} outage", ot),
    )
    for who, t in named:
        if t is not None and _gain(t, least=0.0):
            return False, (
                f"lowers {who} error beyond chance, but by less than {MIN_CHANGE:g} points "
                f"({float(t['change']):+.2f})"
            )
    return False, "within noise"


def _raises(what: str, t: dict[str, Any]) -> str:
    """Why a candidate whose replay raised an error is not offered, with the rise (MAPE
    points) and whether it is beyond chance: a rise of a few thousandths of a point inside
    its 95 % interval is no harm, only no gain, and the words should not read as one."""
    change = float(t["change"])
    size = f"{change:+.3f}" if abs(change) < 0.01 else f"{change:+.2f}"
    low = t.get("low")
    if low is not None and low > 0:
        return f"raises the {what} error ({size} points, beyond chance)"
    return f"raises the {what} error ({size} points, within noise: no gain)"


@dataclass
class VerdictContext:
    """What every verdict of one diagnosis shares: the model as diagnosed (``mm+erosion``),
    the method replayed, the live and outage baselines, the noise floor (MAPE, %) and the
    number of wells diagnosed together."""

    label: str
    method: str
    live: dict[str, Any]
    outage: dict[str, Any]
    floor: float | None
    n_wells: int


def _change_text(t: dict[str, Any] | None, what: str) -> str:
    if t is None or t.get("change") is None:
        return f"{what}: not measured"
    interval = (
        f", 95 % interval {t['low']:+.2f} to {t['high']:+.2f}"
        if t.get("low") is not None and math.isfinite(t["low"])
        else ""
    )
    return f"{what} {t['base_mape']:.2f} -> {t['mape']:.2f} % ({t['change']:+.2f} points{interval})"


def _trial_text(t: dict[str, Any] | None) -> str:
    """``; applied now ...``: the trial forecast in words, or nothing without one."""
    if t is None or t.get("change") is None:
        return ""
    interval = (
        f", 95 % prediction interval {t['low']:+.2f} to {t['high']:+.2f}"
        if t.get("low") is not None
        else ""
    )
    return (
        f"; applied as the service applies a change (fitted on the whole history, then "
        f"learning), over the last {t.get('window_days', live.TRIAL_DAYS):g} days of data its "
        f"trial would have measured {t['base_mape']:.2f} % (shadow) -> {t['mape']:.2f} % "
        f"({t['change']:+.2f} points{interval})"
    )


def _evidence(c: CandidateResult, protocol: str, well: str | None, n_wells: int) -> dict[str, Any]:
    """The field's and the well's test of one protocol, side by side."""
    f, w = c.test(protocol), c.test(protocol, well) if well is not None else None
    out: dict[str, Any] = {"protocol": protocol, "field": brief(f), "wells": n_wells}
    if well is not None and n_wells > 1:
        out["well"] = brief(w)
    return out


def _evidence_text(ev: dict[str, Any]) -> str:
    def one(t: dict[str, Any] | None, who: str) -> str:
        if t is None or not t.get("n_blocks"):
            return f"{who}: no blocks"
        return (
            f"{who} p = {t['p_value']:.2g} (q = {t.get('q_value', float('nan')):.2g}) over "
            f"{t['n_blocks']} blocks of {t['block_days']:g} days"
        )

    text = one(ev["field"], f"the field's {ev['wells']} well(s)" if ev["wells"] > 1 else "the well")
    if "well" in ev:
        text += "; " + one(ev["well"], "this well alone")
    return text


def _verdict_numbers(c: CandidateResult, well: str | None, ctx: VerdictContext) -> dict[str, Any]:
    """A candidate's numbers in a verdict: its live and outage tests (``well``'s, or the
    field's), the evidence of each protocol, and whether it is offered and why (not)."""
    return {
        "live": brief(c.test("live", well)),
        "outage": brief(c.test("outage", well)),
        "trial": brief(c.test("trial", well)),
        "evidence": [_evidence(c, p, well, ctx.n_wells) for p in ("live", "outage")],
        "offer": offer(c, well)[0],
        "reason": offer(c, well)[1],
    }


def live_verdict(
    results: Sequence[CandidateResult],
    suggestion: Suggestion | None,
    well: str | None,
    ctx: VerdictContext,
    fit_once: dict[str, Any],
    prefer: str | None = None,
) -> dict[str, Any]:
    """One verdict (the field's, or ``well``'s) under the live and outage protocols:
    ``effect`` (an offered candidate: ``prefer``, the field's, when offered for the well, else
    the first in BIC order, which names the form; the replay confirms it helps), ``driver``
    (an offered correction), ``carried`` (the fit-once evidence names an effect or a driver,
    but adding it lowers neither error beyond chance, or raises one), or ``noise``. A form
    of a physics that gives way to another form of it here (:func:`weigh_forms`) is not
    offered; the verdict says which and why (``gave_way``)."""
    v = _live_verdict(results, suggestion, well, ctx, fit_once, prefer)
    key = "field" if well is None else well
    gave = [c for c in results if key in c.gives_way]
    v["gave_way"] = [
        {"effect": c.effect, "to": c.gives_way[key]["to"], "rule": c.gives_way[key]["rule"]}
        for c in gave
    ]
    if gave:
        v["text"] += " " + " ".join(
            f"{c.effect} is not offered in its place: {c.gives_way[key]['text']}." for c in gave
        )
    proxies = _trend_proxies(results)
    v["trend_proxies"] = [c.spec or c.effect for c in proxies]
    if proxies and v["kind"] in ("noise", "driver"):
        v["text"] += (
            f" {proxies[0].spec or proxies[0].effect} is not named: "
            f"{rivals.trend_proxy_text(proxies[0])}"
            + (
                f"; nor are {', '.join(c.spec or c.effect for c in proxies[1:])}, for the "
                "same reason"
                if proxies[1:]
                else ""
            )
            + "."
        )
    return v


def _trend_proxies(results: Sequence[CandidateResult]) -> list[CandidateResult]:
    """The material candidates set aside as trend proxies, one per physics (its best form),
    best first."""
    seen: set[str] = set()
    out = []
    for c in results:
        if c.material and c.trend_proxy and c.explained_by is None:
            if rivals.family(c.effect) not in seen:
                seen.add(rivals.family(c.effect))
                out.append(c)
    return out


def _live_verdict(
    results: Sequence[CandidateResult],
    suggestion: Suggestion | None,
    well: str | None,
    ctx: VerdictContext,
    fit_once: dict[str, Any],
    prefer: str | None,
) -> dict[str, Any]:
    offered = [c for c in results if offer(c, well)[0]]
    if offered:
        best = next((c for c in offered if c.effect == prefer), offered[0])
        return _effect_verdict(best, well, ctx)
    if suggestion is not None and offer(suggestion.result, well)[0]:
        return _driver_verdict(suggestion, well, ctx)
    named = [
        c
        for c in results
        if (c.via_driver is not None and rivals.stands_alone(c)) or _fit_once_names(c, well)
    ]
    if named:
        c = next((x for x in named if x.effect == prefer), named[0])
        return _carried_verdict(c, well, ctx)
    carried = _carried_driver(suggestion, well, ctx)
    if carried is not None:
        return carried
    return _noise_verdict(suggestion, well, ctx, fit_once)


def _who(well: str | None) -> str:
    """`` for W01`` in a verdict about one well, empty for the field's."""
    return "" if well is None else f" for {well}"


def _effect_verdict(best: CandidateResult, well: str | None, ctx: VerdictContext) -> dict[str, Any]:
    """The verdict ``effect``: add ``best`` (offered), with its live and outage changes and
    the evidence of the protocol that offers it."""
    out_label = ctx.outage.get("label", "outage")
    num = _verdict_numbers(best, well, ctx)
    why = num["reason"]
    ev = next(e for e in num["evidence"] if e["protocol"] == why)
    text = (
        f"Add {best.spec or best.effect} to {ctx.label}{_who(well)}. Replayed with {ctx.method}, "
        f"{_change_text(num['live'], 'the live MAPE goes')}; "
        f"{_change_text(num['outage'], f'in {out_label} outages')}{_trial_text(num['trial'])}. "
        f"Evidence ({why}): {_evidence_text(ev)}. {best.meaning}"
    )
    if why == "outage":
        text += (
            f" Online, {ctx.method} already follows what it explains (no live gain beyond "
            "noise); it pays off when the meter fails."
        )
    if best.warnings:
        text += " Check its parameters: " + best.warnings[0]
    return _as_named("effect", best, text, num)


def _driver_verdict(
    suggestion: Suggestion, well: str | None, ctx: VerdictContext
) -> dict[str, Any]:
    """The verdict ``driver``: apply the offered correction, with its changes and evidence."""
    out_label = ctx.outage.get("label", "outage")
    num = _verdict_numbers(suggestion.result, well, ctx)
    ev = next(e for e in num["evidence"] if e["protocol"] == num["reason"])
    text = (
        f"No library effect lowers the error{_who(well)}; the residual depends mostly on "
        f"{suggestion.driver}. A correction {suggestion.text}, replayed with {ctx.method}: "
        f"{_change_text(num['live'], 'the live MAPE goes')}; "
        f"{_change_text(num['outage'], f'in {out_label} outages')}{_trial_text(num['trial'])}. "
        "Evidence: "
        f"{_evidence_text(ev)}. Apply it with --effects {suggestion.spec}, or start your "
        "own effect from the code in the report."
    )
    return {"kind": "driver", "effect": None, "driver": suggestion.driver, "text": text, **num}


def _carried_verdict(c: CandidateResult, well: str | None, ctx: VerdictContext) -> dict[str, Any]:
    """The verdict ``carried``: the evidence names ``c``, but the replay with the well's
    method lowers neither error beyond chance (or raises the live one): not offered."""
    out_label = ctx.outage.get("label", "outage")
    num = _verdict_numbers(c, well, ctx)
    if c.replayed:
        lt = num["live"]
        worse = lt is not None and lt.get("change") is not None and lt["change"] > 0
        tail = (
            f"adding it to {ctx.label}{_who(well)} with {ctx.method}: "
            f"{_change_text(lt, 'live MAPE')}; "
            f"{_change_text(num['outage'], f'in {out_label} outages')}"
            f"{_trial_text(num['trial'])}. "
            + (
                "Its live change is above zero (it does not lower the error the operator "
                "sees): not offered."
                if worse
                else _unproven_text(ctx, lt, num["outage"])
                or f"{ctx.method} (and any network) already carries what it explains: "
                f"neither error falls both beyond chance and by {MIN_CHANGE:g} points or more "
                "(chance judged over all the diagnosis's tests at once, Benjamini-Hochberg, "
                "not by each interval alone); adding "
                + _what_adding_gives(ctx)
                + few_blocks_text(lt, well)
            )
        )
    else:
        tail = "it was not replayed under the live protocol."
    text = f"The fit-once evidence names {c.effect} ({_fit_once_text(c, well)}), but " + tail
    return _as_named("carried", c, text, num)


def _unproven_text(
    ctx: VerdictContext,
    live_t: dict[str, Any] | None,
    outage_t: dict[str, Any] | None,
) -> str:
    """For a ``carried`` verdict whose replay lowers an error by :data:`MIN_CHANGE` points
    or more with a 95 % interval below zero (the test alone), though not beyond chance over
    the diagnosis's family: the learner does *not* carry it, the evidence is short of
    proving the gain. Empty otherwise (the learner's change is small, or its interval holds
    zero: "carried" stands). Seen on a Sachdeva valve field (seed 5905, ``mm`` + ``bayes``):
    live -0.99 points (-1.72 to -0.46), outage -1.17, q = 0.08 and 0.16, and the verdict said
    ``bayes`` already carried the valve and adding it would give "not accuracy"."""
    shown = [
        (name, t)
        for name, t in (("live", live_t), ("outage", outage_t))
        if t is not None
        and t.get("change") is not None
        and t["change"] <= -MIN_CHANGE
        and t.get("high") is not None
        and t["high"] < 0
    ]
    if not shown:
        return ""
    parts = [
        f"the {name} error by {-t['change']:.2f} points (p = {t['p_value']:.2g} for this test "
        f"alone, q = {t['q_value']:.2g} over the diagnosis's tests)"
        for name, t in shown
        if t.get("p_value") is not None and t.get("q_value") is not None
    ]
    if not parts:
        return ""
    return (
        f"The replay with {ctx.method} lowers {' and '.join(parts)}: a gain {ctx.method} does "
        "not carry, but not beyond chance once every test of the diagnosis is counted "
        "(Benjamini-Hochberg): not offered on this evidence; a diagnosis over more months "
        "after the split may decide."
    )


def _what_adding_gives(ctx: VerdictContext) -> str:
    """What adding a carried effect gives, in words: a physical parameter to read, on a
    mechanistic model; on a hybrid (:data:`HYBRIDS`) not even that reliably, since its
    network takes up the same misfit while the parameter is learned beside it (a user's
    walk: erosion added to ``ham`` on an eroding well read a wear rate of 0.001 +- 0.005
    against a true 0.04)."""
    if ctx.label.split("+")[0] in HYBRIDS:
        return (
            "it would add a physical parameter, but on a hybrid the network takes up the same "
            "misfit, so that parameter need not read the effect (it may stay near its prior); "
            "not accuracy either."
        )
    return "it would add a physical parameter to read (interpretability), not accuracy."


def untested_text(skipped: Sequence[dict[str, str]]) -> str:
    """A sentence for a ``noise`` verdict naming the candidates the diagnosis did not test,
    with their reasons (``skipped``: ``{"effect", "reason"}`` each): "none lowers the error"
    is then not a verdict on them. Empty when none was skipped. A reason that is a sentence
    of its own loses its full stop inside the brackets ("(... (ham+erosion).)." read as a typo)."""
    if not skipped:
        return ""
    reasons = (f"{x['effect']} ({x['reason'].rstrip().rstrip('.')})" for x in skipped)
    return " Not tested: " + "; ".join(reasons) + "."


def _fit_once_tests(c: CandidateResult, well: str | None) -> list[dict[str, Any]]:
    """``c``'s fit-once tests with a change: the field's, and ``well``'s own if given."""
    tests = [c.test("fit_once")] + ([c.test("fit_once", well)] if well is not None else [])
    return [t for t in tests if t is not None and t.get("change") is not None]


def _each(found: Sequence[dict[str, Any]]) -> str:
    """``real_gas (-0.06 points, q = 0.017), ...``: listed candidates with their change
    (MAPE points) and, where they have them, their p and q."""
    return ", ".join(
        f"{x['effect']} ({x['change']:+.2f} points"
        + "".join(
            f", {name} = {x[key]:.2g}"
            for key, name in (("p_value", "p"), ("q_value", "q"))
            if x.get(key) is not None
        )
        + (f"; also {', '.join(x['variants'])}" if x.get("variants") else "")
        + (
            f"; or {', '.join(x['alternatives'])}, which the data cannot tell from it"
            if x.get("alternatives")
            else ""
        )
        + ")"
        for x in found
    )


def below_minimum(results: Sequence[CandidateResult], well: str | None) -> list[dict[str, Any]]:
    """The candidates that the data support (BIC over every measurement lower by more than
    :data:`MATERIAL_BIC`) and whose fit-once evidence lowers the error beyond chance
    (BH-rejected, the field's test or ``well``'s own) but by less than :data:`MIN_CHANGE`
    points, not material: too little to act on, whether physics at work (real gas that a
    refitted C_D nearly absorbs) or a flexible term taking up meter drift. (Without the BIC
    condition a well's own test lists candidates that change its error by a ten-thousandth
    of a point in every block.)
    ``[{"effect", "change", "q_value"}]``, largest fall first; the change in MAPE points,
    from the test that found it."""
    out = []
    for c in results:
        if c.material or not c.delta_bic_all < -MATERIAL_BIC:
            continue
        found = [
            t
            for t in _fit_once_tests(c, well)
            if t.get("rejected") and -MIN_CHANGE < t["change"] < 0.0
        ]
        if found:
            t = min(found, key=lambda x: x["change"])
            out.append(
                {"effect": c.spec or c.effect, "change": t["change"], "q_value": t.get("q_value")}
            )
    return sorted(out, key=lambda x: x["change"])


def below_minimum_text(found: Sequence[dict[str, Any]]) -> str:
    """A sentence for a ``noise`` verdict naming :func:`below_minimum`'s candidates: the
    effect may be at work, it is not worth adding. Empty when there are none."""
    if not found:
        return ""
    return (
        f" Beyond chance but below the minimum: {_each(found)} lowered the fit-once error by less "
        f"than {MIN_CHANGE:g} points, though the data support it (BIC lower by more than "
        f"{MATERIAL_BIC:g}): too little to act on (physics at work that the fitted "
        "parameters nearly absorb, or a flexible term taking up meter drift)."
    )


#: A fit-once test's own p-value below which a material candidate that the false-discovery
#: control did not reject is reported as suggestive (:func:`suggestive`): the level the
#: control holds the family at, applied to one test alone.
SUGGESTIVE_P = 0.05


def suggestive(results: Sequence[CandidateResult], well: str | None) -> list[dict[str, Any]]:
    """The candidates that the fit-once evidence points at without establishing them:
    material (the data support them, by at least :data:`MIN_CHANGE` points), the fit-once
    test (the field's, or ``well``'s own) lowers the error by :data:`MIN_CHANGE` points or
    more with its own p below :data:`SUGGESTIVE_P`, but Benjamini-Hochberg over the
    diagnosis's tests does not reject it. Nothing is named for them: a ``noise`` verdict
    lists them so that a short span's weak evidence is not read as none (a valve on four
    wells, a year after the split: p = 0.016 alone over 14 blocks, q = 0.13).
    ``[{"effect", "change", "p_value", "q_value", "variants", "alternatives"}]``, largest
    fall first (MAPE points); one entry a physics (:func:`vfm_core.jobs.diagnose_rivals.family`:
    the valve families are one), its best variant, the others that qualified in
    ``variants``. ``alternatives``: the material candidates of other physics that the data
    cannot tell from it (:func:`vfm_core.jobs.diagnose_rivals.second_to`), which are not
    listed on their own; without them the sentence would name one of two equal explanations
    by a few hundredths of a point (a user's walk, an eroding field with ``ham`` + ``bayes``
    8 months after the split: slip -0.31 points, p = 0.0035, listed alone; erosion -0.29,
    p = 0.0033, and a meter bias -0.28 beside it, "indistinguishable")."""
    out: list[dict[str, Any]] = []
    for c in results:
        if not c.material or not rivals.stands_alone(c):
            continue
        found = [
            t
            for t in _fit_once_tests(c, well)
            if not t.get("rejected")
            and t["change"] <= -MIN_CHANGE
            and t.get("p_value") is not None
            and t["p_value"] < SUGGESTIVE_P
        ]
        if found:
            t = min(found, key=lambda x: x["p_value"])
            out.append(
                {
                    "effect": c.spec or c.effect,
                    "change": t["change"],
                    "p_value": t["p_value"],
                    "q_value": t.get("q_value"),
                    "variants": [],
                    "alternatives": [
                        o.spec or o.effect
                        for o in results
                        if o.material
                        and o.explained_by is None
                        and rivals.second_to(o) in (c.effect, c.spec)
                    ],
                }
            )
    best: dict[str, dict[str, Any]] = {}
    for x in sorted(out, key=lambda x: x["change"]):
        kind = rivals.family(x["effect"])
        if kind in best:
            best[kind]["variants"].append(x["effect"])
        else:
            best[kind] = x
    return list(best.values())


def suggestive_text(found: Sequence[dict[str, Any]]) -> str:
    """A sentence for a ``noise`` verdict naming :func:`suggestive`'s candidates, each with
    the alternatives the data cannot tell from it. Empty when there are none."""
    if not found:
        return ""
    return (
        f" Suggestive, not established: the fit-once evidence points at {_each(found)}, beyond "
        f"chance for its own test (p < {SUGGESTIVE_P:g}) but not over all the diagnosis's "
        "tests (q); nothing is named for it. A diagnosis over more months of data may decide."
    )


def _alone_text(t: dict[str, Any] | None) -> str:
    """``: its interval and p = ... are for this test alone ...``: why a 95 % interval that
    excludes 0 can sit beside "not beyond chance" (the false-discovery control over the
    diagnosis's tests). Empty without a p-value."""
    if t is None or t.get("p_value") is None:
        return ""
    q = t.get("q_value")
    return f": its interval and p = {t['p_value']:.2g} are for this test alone" + (
        f"; over all the diagnosis's tests q = {q:.2g}" if q is not None else ""
    )


def few_blocks_text(t: dict[str, Any] | None, well: str | None) -> str:
    """A sentence for a live test that lowered the error by :data:`MIN_CHANGE` or more in
    every one of its blocks, at the smallest p-value its B blocks can give (2^-B), and was
    still not counted beyond chance over the diagnosis's family: its evidence is limited
    by the span replayed, not by the change's size. Empty otherwise."""
    if t is None or t.get("rejected") or t.get("change") is None:
        return ""
    b, p = t.get("n_blocks"), t.get("p_value")
    if not b or p is None or t["change"] > -MIN_CHANGE or p > 1.5 * 2.0 ** -int(b):
        return ""
    q = t.get("q_value")
    who = f"On {well} the" if well is not None else "The"
    return (
        f" {who} live error fell in every one of its {b} blocks of "
        f"{t.get('block_days', 0):g} days (p = {p:.2g}, the smallest {b} blocks can give"
        + (f"; q = {q:.2g} over the diagnosis's tests" if q is not None else "")
        + "): the evidence is limited by the span replayed, not by the size of the change; "
        "a diagnosis with more months of data may decide."
    )


def _fit_once_text(c: CandidateResult, well: str | None) -> str:
    """The fit-once change the naming rests on: the field's (pooled over the wells), and a
    well's own beside it when one well is diagnosed among others (its evidence alone is
    weaker, and may be nil while the field's names the effect)."""
    field = c.test("fit_once")
    own = c.test("fit_once", well) if well is not None else None
    if field is None or own is None or own is field:
        return _change_text(field or own, "fit-once MAPE")
    return (
        f"{_change_text(field, 'fit-once MAPE over all wells')}; "
        f"{_change_text(own, f'on {well} alone')}"
    )


def _correction_how(lt: dict[str, Any] | None) -> str:
    """What a correction that a ``noise`` verdict mentions did to the live error, by its
    live test ``lt``: not beyond chance; beyond chance but by less than :data:`MIN_CHANGE`
    points; or beyond chance and not offered (its candidate line says why)."""
    if lt is None or not lt.get("rejected") or lt.get("change") is None:
        return "does not lower the error the operator sees beyond chance"
    if lt["change"] > -MIN_CHANGE:
        return (
            "lowers the error the operator sees beyond chance, but by less than the "
            f"{MIN_CHANGE:g}-point minimum"
        )
    return "lowers the error the operator sees beyond chance, yet is not offered"


def _noise_verdict(
    suggestion: Suggestion | None,
    well: str | None,
    ctx: VerdictContext,
    fit_once: dict[str, Any],
) -> dict[str, Any]:
    """The verdict ``noise``: no candidate and no correction lowers an error beyond chance."""
    base = (
        ctx.live.get("per_well", {}).get(well, {}).get("mape", float("nan"))
        if well is not None
        else ctx.live.get("mape", float("nan"))
    )
    floor = f"; noise floor about {ctx.floor:.2f} %" if ctx.floor is not None else ""
    text = (
        f"No candidate explains the residual{_who(well)}: none lowers the live or the outage error "
        f"beyond chance (Benjamini-Hochberg at q = {live.FDR_Q:g} over the diagnosis's tests): what is left "
        f"(live MAPE {base:.2f} %{floor}) is measurement noise, meter drift and what "
        f"{ctx.method} follows."
    )
    if fit_once.get("kind") == "driver" or (suggestion is not None and not suggestion.result.offer):
        if suggestion is not None:
            lt = suggestion.result.test("live", well)
            how = _correction_how(lt)
            text += (
                f" A correction in {suggestion.driver} was fitted but {how} "
                f"({_change_text(lt, 'live MAPE')}{_alone_text(lt)})."
            )
    return {
        "kind": "noise",
        "effect": None,
        "driver": None,
        "text": text,
        "live": None,
        "outage": None,
        "trial": None,
        "evidence": [],
        "offer": False,
        "reason": None,
    }


def _fit_once_names(c: CandidateResult, well: str | None) -> bool:
    """The fit-once evidence names ``c``: material, and lower beyond chance (the field's
    test, or the well's)."""
    return (
        c.material
        and rivals.stands_alone(c)  # an alternative is named beside its lead, not alone
        and _gain(c.test("fit_once"), c.test("fit_once", well) if well else None, least=0.0)
    )


def _as_named(kind: str, c: CandidateResult, text: str, num: dict[str, Any]) -> dict[str, Any]:
    """A verdict (``effect``, ``carried``) naming ``c``; with the driver evidence when the
    physics behind a driver named it (``via_driver``: its variable in ``driver``)."""
    v = c.via_driver
    if v is not None and not c.material:
        text += " " + _via_driver_text(c)
    if c.core_fixed:
        text += (
            f" Replayed as identified on the mechanistic core ({c.spec}: its parameters fixed "
            "at the core's values, shared by the wells, the network learning what is left); "
            "learned together with the network, which sees the same variable, it would be "
            "confounded with it."
        )
    rival_text = rivals.rivals_text(c)
    if rival_text:
        text += " " + rival_text
    trend = rivals.trend_text(c)
    if trend:
        text += " " + trend
    driver = None if v is None else v["driver"]
    return {
        "kind": kind,
        "effect": c.effect,
        "driver": driver,
        "text": text,
        **num,
        "via_driver": v,
        "explains": _related(c, "explains"),
        "then": _related(c, "both"),
        "alternatives": _related(c, "indistinguishable"),
    }


def _related(c: CandidateResult, relation: str) -> list[str]:
    """The rivals of ``c`` in ``relation`` to it, not stale
    (:mod:`vfm_core.jobs.diagnose_rivals`)."""
    return rivals.current(c, relation)


def _via_driver_text(c: CandidateResult) -> str:
    """The driver evidence of a candidate named through it, in words."""
    v = c.via_driver or {}
    vs = (v.get("versus_correction") or {}).get("live") or {}
    diff = (
        f" (the correction's live MAPE {vs['change']:+.2f} points against it, 95 % interval "
        f"{vs['low']:+.2f} to {vs['high']:+.2f}, p = {vs['p_value']:.2g})"
        if vs.get("change") is not None and vs.get("low") is not None
        else ""
    )
    return (
        f"The evidence is the driver: the residual depends on {v.get('driver')}, and a generic "
        f"correction {v.get('correction_text', '')} explains it no better than {c.effect}, "
        f"which acts through {v.get('driver')}{diff}: the library's physics is named, the "
        "driver is its evidence."
    )


def _carried_driver(
    suggestion: Suggestion | None,
    well: str | None,
    ctx: VerdictContext,
) -> dict[str, Any] | None:
    """The ``carried`` verdict of a driver outside the library: the fit-once evidence finds
    the correction (material, lower beyond chance), but the model the well runs (a network,
    a filter) already follows it, so the replay shows no gain beyond chance; None otherwise."""
    if not (
        suggestion is not None
        and suggestion.result.replayed
        and suggestion.result.material
        and _gain(
            suggestion.result.test("fit_once"),
            suggestion.result.test("fit_once", well) if well else None,
            least=0.0,
        )
    ):
        return None
    who = "" if well is None else f" for {well}"
    out_label = ctx.outage.get("label", "outage")
    s = suggestion.result
    num = _verdict_numbers(s, well, ctx)
    lt = num["live"]
    worse = lt is not None and lt.get("change") is not None and lt["change"] > 0
    fo = s.test("fit_once", well) or s.test("fit_once")
    text = (
        f"The fit-once evidence finds the residual depending on {suggestion.driver} (a "
        f"correction {suggestion.text}: {_change_text(fo, 'fit-once MAPE')}), but adding "
        f"it to {ctx.label}{who} with {ctx.method}: {_change_text(lt, 'live MAPE')}; "
        f"{_change_text(num['outage'], f'in {out_label} outages')}. "
        + (
            "Its live change is above zero: not offered."
            if worse
            else f"{ctx.method} (and any network) already carries what it explains: "
            "neither error falls beyond chance; the correction would add a parameter to "
            "read, not accuracy."
        )
    )
    return {"kind": "carried", "effect": None, "driver": suggestion.driver, "text": text, **num}


def driver_found(correction: CandidateResult) -> bool:
    """The fit-once evidence finds a driver: its correction is material and lowers the
    fit-once error beyond chance (the field's test, BH-rejected), and it was replayed."""
    return (
        correction.replayed
        and correction.live_run is not None
        and correction.material
        and _gain(correction.test("fit_once"), least=0.0)
    )


def _versus(
    physics: RunResult, correction: RunResult, seed: int, in_outage: bool = False
) -> dict[str, Any]:
    """The paired block test of a correction against a library effect on the same rows
    (live, or inside the outage windows): ``change`` is the correction's MAPE less the
    effect's (points; below 0: the correction is better) and ``p_value`` the one-sided
    p-value of "the correction is better"."""
    a, b = physics.predictions, correction.predictions
    if in_outage:
        keep = a["in_outage"].to_numpy(dtype=bool)
        a, b = a[keep], b[keep]
    return live.paired_test(live.paired_differences(a, b), seed=seed)


def _beats(
    versus: dict[str, Any], correction: dict[str, Any] | None, physics: dict[str, Any] | None
) -> bool:
    """The correction beats the library effect beyond the noise of the replay under one
    protocol: the paired test of the two finds the correction's error lower beyond chance
    (one-sided, :data:`PHYSICS_ALPHA`), and the effect's own gain over the baseline lies
    outside the correction's 95 % interval (above its upper end: a smaller gain than the
    correction's gain can be, given its own uncertainty)."""
    if versus.get("change") is None or versus["change"] >= 0:
        return False
    if versus["p_value"] >= PHYSICS_ALPHA:
        return False
    high = None if correction is None else correction.get("high")
    gain = None if physics is None else physics.get("change")
    if high is None or gain is None or not math.isfinite(high):
        return True
    return bool(gain > high)


def physics_behind_driver(
    kin: Sequence[CandidateResult],
    correction: CandidateResult,
    driver: str,
    correction_text: str,
    seed: int,
) -> list[CandidateResult]:
    """Name the library's physics behind a driver: set ``via_driver`` on each candidate of
    ``kin`` that acts through ``driver`` (:func:`acts_through`), was replayed, and whose
    live error (and outage error, when both have one) the correction in that driver does
    not beat beyond the noise of the replay (:func:`_beats`: lower beyond chance, and by
    more than the correction's own gain is known to); returns those. Nothing when the
    fit-once evidence does not find the driver (:func:`driver_found`).

    Why: a generic correction in a variable (a log-linear factor in the choke opening) fits
    whatever depends on that variable; a library effect that acts through the same variable
    (the valve's area as a function of the opening) is one physical explanation of it, with
    parameters that mean something and that extrapolate as the physics does. When the data
    cannot tell the two apart (the effect's gain lies within what the correction's gain is
    known to, or the correction is not better beyond chance), the physics is named and the
    driver is its evidence; when the correction is better beyond both, something outside
    the library is at work and the driver stays the verdict. A bare significance test alone
    would not do: with years of data a few hundredths of a point are significant, and a
    flexible correction always fits a little of the noise too. Whether the effect is offered is then decided as for any candidate
    (:func:`offer`: a lower error beyond chance, neither error raised)."""
    if not driver_found(correction):
        return []
    assert correction.live_run is not None
    out: list[CandidateResult] = []
    for c in kin:
        if acts_through(c.effect) != driver or not c.replayed or c.live_run is None:
            continue
        tests = {"live": _versus(c.live_run, correction.live_run, seed)}
        if c.outage_run is not None and correction.outage_run is not None:
            tests["outage"] = _versus(c.outage_run, correction.outage_run, seed, in_outage=True)
        better = [p for p, t in tests.items() if _beats(t, correction.test(p), c.test(p))]
        evidence = {
            "driver": driver,
            "correction": correction.spec or correction.effect,
            "correction_text": correction_text,
            "versus_correction": {p: brief(t) for p, t in tests.items()},
            "rule": (
                f"{c.effect} acts through {driver}; the correction in {driver} does not lower "
                "the live or outage error below it beyond the noise of the replay (a "
                f"one-sided paired block test at {PHYSICS_ALPHA:g}, or its gain within the "
                "correction's own 95 % interval)"
            ),
        }
        c.via_driver = None if better else evidence
        if better:
            continue
        out.append(c)
    return out


def bound_wells(c: CandidateResult) -> set[str]:
    """The wells where a fitted parameter of ``c`` sits at a physical bound (``c.at_bound``,
    the same entries its warnings put in words)."""
    return {str(w) for h in c.at_bound for w in h.get("wells", [])}


def at_bound(c: CandidateResult, wells: Sequence[str]) -> bool:
    """``c``'s fitted form is not an estimate for ``wells`` (one well, or the field's): a
    parameter sits at a physical bound in more than half of them. For one well: at a bound
    in it. For the field: in most of its wells; a bound in one well of several is that
    well's own misfit, and the form still describes the others."""
    hit = bound_wells(c)
    return bool(wells) and 2 * sum(w in hit for w in wells) > len(wells)


def _versus_form(
    chosen: CandidateResult, c: CandidateResult, well: str, protocol: str, seed: int
) -> dict[str, Any] | None:
    """The paired block test of form ``c`` against form ``chosen`` of the same physics on
    ``well``'s rows under ``protocol`` (``live`` or ``outage``): ``change`` is ``c``'s MAPE
    less ``chosen``'s (points; below 0: ``c`` is better) and ``p_value`` the one-sided
    p-value of "``c`` is better". None when either was not replayed under it."""
    outage = protocol == "outage"
    a = chosen.outage_run if outage else chosen.live_run
    b = c.outage_run if outage else c.live_run
    if a is None or b is None or len(a.predictions) != len(b.predictions):
        return None
    pa, pb = a.predictions, b.predictions
    if outage:
        keep = pa["in_outage"].to_numpy(dtype=bool)
        pa, pb = pa[keep], pb[keep]
    pairs = live.paired_differences(pa, pb)
    pairs = pairs[pairs["well"] == well]
    own = c.test(protocol, well) or {}
    t = live.paired_test(pairs, own.get("block_days"), seed=seed)
    return None if t.get("change") is None else t


def weigh_forms(
    results: Sequence[CandidateResult],
    wells: Sequence[str],
    well: str | None,
    field_effect: str | None = None,
    seed: int = 0,
) -> None:
    """Which forms of one physics (the valve families; wear with time or throughput:
    :func:`vfm_core.jobs.diagnose_rivals.family`) give way to another form of it, for
    ``well`` (None: the field, ``wells`` its wells): sets ``gives_way["field" or well]`` on
    each candidate that would otherwise be offered there (:func:`offer`), which then is
    not, and says why. Two rules, in this order:

    * **At a bound.** A form whose fitted parameter sits at a physical bound for the wells
      concerned (:func:`at_bound`) gives way to another form of the same physics that the
      evidence names (material, standing alone), that was replayed, and whose parameters
      do not. A parameter at its bound is not an estimate: the data push it past what the
      form allows, so the form does not describe the data; what it lowers of the error it
      takes up as a flexible term would (on a sigmoid valve, the quick-opening curve with
      its weight at -0.5 in four of five wells lowered one well's live error beyond chance,
      and applied, stayed frozen at the bound, a standing alarm). A form that fits within
      its bounds is the physics' description, offered or not on its own evidence.
    * **The field's form.** For one well, when the field's verdict names a form of the
      same physics (``field_effect``) and that form is not at a bound in this well, another
      form is offered in its place only if this well's own replay finds it better than the
      field's form beyond chance (a one-sided paired block test of the two on the well's
      rows under the protocol that offers it, at :data:`PHYSICS_ALPHA`, not adjusted:
      adjusting would make the well's own evidence harder to count). One physics at work
      in a field is one form of it unless a well shows otherwise; a well's months are weak
      evidence alone, and which of two forms' gains on it passes the false-discovery bar
      is otherwise decided by the replay's noise.

    Nothing here is tuned to a field: the bound is the prior's own, the level the one the
    verdict uses for a library effect against a correction (:func:`physics_behind_driver`)."""
    key = "field" if well is None else well
    unit = list(wells) if well is None else [well]
    for c in results:
        c.gives_way.pop(key, None)
    named = [
        c
        for c in results
        if c.named and rivals.stands_alone(c) and c.replayed and not at_bound(c, unit)
    ]
    for c in results:
        if not at_bound(c, unit) or not offer(c, well)[0]:
            continue
        other = next(
            (r for r in named if r is not c and rivals.family(r.effect) == rivals.family(c.effect)),
            None,
        )
        if other is None:
            continue
        params = sorted({h["parameter"] for h in c.at_bound if set(h["wells"]) & set(unit)})
        where = (
            f"on {well}"
            if well is not None
            else (f"in {len(bound_wells(c) & set(unit))} of the field's {len(unit)} wells")
        )
        c.gives_way[key] = {
            "to": other.effect,
            "rule": "at_bound",
            "text": (
                f"{' and '.join(params)} sit{'s' if len(params) == 1 else ''} at a physical "
                f"bound {where}: not an estimate (this form does not describe the data), while "
                f"{other.effect}, a form of the same physics the evidence names, fits within "
                "its bounds"
            ),
        }
    if well is not None and field_effect is not None:
        _field_form(results, well, field_effect, seed)


def _field_form(
    results: Sequence[CandidateResult], well: str, field_effect: str, seed: int
) -> None:
    """:func:`weigh_forms`'s second rule on ``well``: a form other than the field's
    (``field_effect``) gives way to it unless this well's replay finds it better beyond
    chance."""
    key = well
    chosen = next((c for c in results if c.effect == field_effect), None)
    if chosen is None or not chosen.replayed or at_bound(chosen, [well]):
        return
    for c in results:
        if c is chosen or key in c.gives_way:
            continue
        if rivals.family(c.effect) != rivals.family(chosen.effect):
            continue
        ok, protocol = offer(c, well)
        if not ok:
            continue
        t = _versus_form(chosen, c, well, protocol, seed)
        if t is None or (t["change"] < 0 and t["p_value"] < PHYSICS_ALPHA):
            continue
        c.gives_way[key] = {
            "to": chosen.effect,
            "rule": "field_form",
            "versus": brief(t),
            "text": (
                f"the field's verdict names {chosen.effect}, a form of the same physics, and "
                f"on {well} this form does not beat it beyond chance ({protocol} MAPE "
                f"{t['change']:+.2f} points against it, one-sided p = {t['p_value']:.2g})"
            ),
        }


def set_offers(
    candidates: Sequence[CandidateResult], well: str | None, offered: str | None
) -> None:
    """One change offered, the verdict's (``offered``); every other candidate says why not,
    and whether its replay raises the live error."""
    for c in candidates:
        ok, reason = offer(c, well)
        c.offer = ok and c.effect == offered
        c.offer_note = (
            None
            if c.offer
            else (
                f"also lowers the error, but the evidence names {offered}"
                if ok and offered is not None
                # ok with nothing offered: the verdict is a faulty instrument
                else (
                    "lowers the error, but the evidence points to a faulty input" if ok else reason
                )
            )
        )
        lt = c.test("live", well)
        c.raises_error = (
            None if not c.replayed or lt is None or lt["change"] is None else lt["change"] > 0
        )


def outage_info(
    base_out: RunResult, plan: Any, wells: Sequence[str], well: str | None
) -> dict[str, Any]:
    """The outage protocol's baseline and its windows, in numbers and words."""
    info = baseline_info(base_out, wells, well, in_outage=True)
    info.update(
        {
            "label": plan.label,
            "length_days": plan.length / pd.Timedelta(days=1),
            "windows": int(len(plan.windows)),
            "protocol": f"windows of {plan.label} without a measurement (a failed "
            f"meter), {len(plan.windows)} over the wells after the split; scored inside "
            "them, the learner learning from the rest",
        }
    )
    return info


def instrument_check(
    verdicts: dict[str, dict[str, Any]],
    frame: pd.DataFrame,
    results: Sequence[CandidateResult],
    suggestion: Suggestion | None,
    base: RunResult,
    split: pd.Timestamp,
    notes: list[str],
) -> None:
    """Turn the verdicts whose evidence coincides with an input's detected fault into
    ``instrument`` verdicts (:func:`vfm_core.jobs.diagnose_instrument.instrument_verdicts`)."""
    by_name = {c.effect: c for c in results}
    wells = [w for w in verdicts if w != "field"]

    def candidate(v: dict[str, Any]) -> CandidateResult | None:
        if v.get("effect"):
            return by_name.get(v["effect"])
        return suggestion.result if suggestion is not None else None

    def pairs_of(v: dict[str, Any], w: str | None) -> pd.DataFrame | None:
        c = candidate(v)
        if c is None or c.live_run is None:
            return None
        pairs = live.paired_differences(base.predictions, c.live_run.predictions)
        return pairs if w is None else pairs[pairs["well"] == w]

    def gains_of(v: dict[str, Any]) -> dict[str, float]:
        c = candidate(v)
        tests = {w: None if c is None else c.test("live", w) for w in wells}
        return {
            w: float(t["change"]) * float(t.get("n", 0))
            for w, t in tests.items()
            if t is not None and t.get("change") is not None
        }

    faults = inst.input_faults(frame)
    turned = inst.instrument_verdicts(
        verdicts, faults, pairs_of, gains_of, split, frame[TIME].max()
    )
    if turned:
        notes.append(
            f"Instrument faults carry the evidence of {', '.join(turned)}: their verdict is "
            "'instrument' (vfm_core.jobs.diagnose_instrument)."
        )


def baseline_info(
    run: RunResult, wells: Sequence[str], well: str | None, in_outage: bool = False
) -> dict[str, Any]:
    p = run.predictions
    if in_outage:
        p = p[p["in_outage"].to_numpy(dtype=bool)]
    out: dict[str, Any] = {
        "mape": mape(p["predicted"], p["measured"]),
        "n": int(len(p)),
        "per_well": {
            w: {"mape": mape(g["predicted"], g["measured"]), "n": int(len(g))}
            for w, g in p.groupby("well", sort=True)
        },
    }
    if well is not None:
        mine = out["per_well"].get(well, {"mape": float("nan"), "n": 0})
        out["well_mape"], out["well_n"] = mine["mape"], mine["n"]
    return out


def service_error(
    frame: pd.DataFrame,
    targets: str,
    split: pd.Timestamp,
    wells: Sequence[str],
    well: str | None,
) -> dict[str, Any]:
    """The error the service recorded on the same measurements (a store's ``predicted``
    column: the prediction it made before learning each one), beside the replay's."""
    if "predicted" not in frame.columns:
        return {}
    rows = np.flatnonzero(target_mask(frame, targets) & (frame[TIME] >= split).to_numpy())
    scored = frame.iloc[rows]
    pred = pd.to_numeric(scored["predicted"], errors="coerce").to_numpy(dtype=float)
    meas = scored["q_total"].to_numpy(dtype=float)
    w = scored[WELL].astype(str).to_numpy()
    ok = np.isfinite(pred)
    if not ok.any():
        return {}
    out: dict[str, Any] = {"service_mape": mape(pred[ok], meas[ok]), "service_n": int(ok.sum())}
    if well is not None:
        mine = ok & (w == well)
        out["service_well_mape"] = mape(pred[mine], meas[mine]) if mine.any() else None
    return out


def fit_once_verdict(
    base_mape: float,
    candidates: list[CandidateResult],
    top: dict[str, Any] | None,
    drivers: list[dict[str, Any]],
    suggestion: Suggestion | None,
    floor: float | None,
    protocol: str,
    bic_on: str,
    trend_share: float = float("nan"),
) -> tuple[str, str | None, str | None, str]:
    """(kind, effect, driver, sentence): see the module docstring for the rule."""
    material = [c for c in candidates if c.material and rivals.stands_alone(c)]
    if material:
        return _material_verdict(material, base_mape, floor, protocol, bic_on)
    if top is not None and suggestion is not None and suggestion.result.material:
        d = next((x for x in drivers if x["name"] == suggestion.driver), top)
        return _correction_verdict(d, suggestion, base_mape, floor, protocol)
    what = _what_is_left(base_mape, floor, trend_share)
    if top is not None and top["p_value"] is not None and top["p_value"] < stats.ALPHA:
        tail = (
            f"a correction in {suggestion.driver} does not lower the held-out error materially "
            f"({base_mape:.2f} % -> {suggestion.mape:.2f} %, BIC {suggestion.result.delta_bic:+.0f})"
            if suggestion is not None
            else "it is not a variable a correction can use"
        )
        return (
            "noise",
            None,
            None,
            f"No candidate explains the residual. {top['name']} correlates with it beyond chance "
            f"(p = {top['p_value']:.3f}), but {tail}: what is left (MAPE {base_mape:.2f} %) {what}.",
        )
    best_p = (
        ""
        if top is None or top["p_value"] is None
        else f" (best: {top['name']}, p = {top['p_value']:.2f} by circular shifts)"
    )
    return (
        "noise",
        None,
        None,
        "No candidate explains the residual, and no variable explains more of it than chance "
        f"would{best_p}: what is left (MAPE {base_mape:.2f} %"
        + (
            f"{_floor_text(floor)}) looks like measurement noise and meter drift."
            if what.startswith("is treated")
            else f") {what}."
        ),
    )


def _floor_text(floor: float | None) -> str:
    """``; noise floor about 1.23 %``, or nothing without a floor."""
    return f"; noise floor about {floor:.2f} %" if floor is not None else ""


def _what_is_left(base_mape: float, floor: float | None, trend_share: float) -> str:
    """What the error left without an explanation is, in words: a slow drift that follows
    time in each well when it is well above the noise floor, else noise and meter drift."""
    if floor is not None and base_mape > 1.5 * floor:
        return (
            f"is well above the noise floor ({floor:.2f} %) but follows time in each well, not any "
            f"variable (per-well straight lines in time hold {100 * trend_share:.0f} % of its "
            "variance): a slow drift of the wells or meters, which online learning follows"
        )
    return "is treated as measurement noise and meter drift"


def _material_verdict(
    material: list[CandidateResult],
    base_mape: float,
    floor: float | None,
    protocol: str,
    bic_on: str,
) -> tuple[str, str | None, str | None, str]:
    """The fit-once verdict ``effect``: the best material candidate, the others beside it."""
    best = material[0]
    share = (
        f", {100 * best.share_above_floor:.0f} % of the error above the noise floor ({floor:.2f} %)"
        if floor is not None and math.isfinite(best.share_above_floor)
        else ""
    )
    text = (
        f"The missing effect is most likely {best.effect}: {protocol}, the MAPE falls from "
        f"{base_mape:.2f} % to {best.mape:.2f} % with it{share} (BIC {best.delta_bic:+.0f} on the "
        f"{bic_on}). {best.meaning}"
    )
    if len(material) > 1:
        others = ", ".join(f"{c.effect} ({c.mape:.2f} %)" for c in material[1:4])
        text += f" Also material, but weaker: {others}."
    if best.warnings:
        text += " Check its parameters: " + best.warnings[0]
    return "effect", best.effect, None, text


def _correction_verdict(
    d: dict[str, Any],
    suggestion: Suggestion,
    base_mape: float,
    floor: float | None,
    protocol: str,
) -> tuple[str, str | None, str | None, str]:
    """The fit-once verdict ``driver``: the residual depends on driver ``d``, and the
    correction fitted in it is material."""
    s = suggestion.result
    return (
        "driver",
        None,
        d["name"],
        f"No candidate explains the residual; it depends mostly on {d['name']} (it explains "
        f"{100 * d['score']:.0f} % of the residual beyond per-well trends, out of sample; "
        f"p = {d['p_value']:.3f} by circular shifts). A correction {suggestion.text} lowers "
        f"the MAPE from {base_mape:.2f} % to {s.mape:.2f} % ({protocol}{_floor_text(floor)}). "
        f"Apply it with --effects {suggestion.spec}, or start your own effect from the code "
        "in the report.",
    )
