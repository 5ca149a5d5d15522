"""Rival explanations in the fit-once evidence: when it names effects of more than one physics,
does one explain the others, are both at work, or can the data not tell them apart?

Each candidate is scored alone against the baseline (:func:`vfm_core.jobs.diagnose._score`),
and the BIC ranks them. When the truth differs from the model in more than one way (a real
field, or a truth from another simulator: a Bernoulli choke with Simpson's slip under a
Sachdeva model), several candidates of *different physics* lower the error, because each
absorbs part of the same misfit: a valve curve takes up an error that grows with the opening,
slip one that grows with the gas fraction, wear one that grows with time, and on a field
whose gas fraction rises as the reservoir depletes all three can look alike. The one-at-a-time
ranking then names whichever absorbs most, with a confidence the BIC overstates (its
residuals are autocorrelated).

The rule here is an *encompassing* test, as for non-nested models (Mizon and Richard 1986):
the best-ranked material candidate (the *lead*) is fitted together with each of the next
:data:`RIVALS` material candidates of other physics (a *rival*; variants of one physics, the
valve families, are one physics), under the same fit-once protocol. Each is asked whether it
adds beyond the other: the pair against the one alone must be material by the rule every
candidate meets against the baseline (:func:`vfm_core.jobs.diagnose_results.is_material`) and
lower the held-out error beyond chance in the paired block test
(:func:`vfm_core.jobs.diagnose_live.paired_test`, one-sided, :data:`ALPHA`). Then:

* ``explains``: the lead adds beyond the rival, the rival nothing beyond the lead: the rival
  is *explained by* the lead, is not named, and says so;
* ``explained_by``: the other way round: the rival becomes the lead (and is asked about the
  next rival in turn);
* ``both``: each adds beyond the other: both are at work; the lead is named first and the
  rival is the next step (after adding the lead, a second diagnosis names it);
* ``indistinguishable``: neither adds beyond the other: they explain the same misfit. Then
  each one's *shape beyond the trend* is tested (:func:`shape_beyond_trend`): the part of its
  correction that a straight line in time per well and meter does not carry (slip follows the
  gas fraction's ups and downs, a valve curve the choke's moves, wear hardly anything but the
  trend) should be in the residual too, if it is the physics. When one's shape is rejected
  by the residual and the other's is not, the rejected one is explained by the other (a
  trend proxy: ``shape_rejected``); otherwise the data cannot tell them apart, the lead is
  named by its BIC and the rival listed beside it, not offered on its own
  (:func:`second_to`: its evidence is the lead's), nor named alone.

A field-wide effect (:attr:`vfm_core.effects.Effect.field_wide`: slip, the real gas, the
critical ratio: corrections of a flow law or a fluid correlation that is the same at every
well) is also asked whether its wells agree (:func:`consistency`: Cochran's Q over the
wells' fitted values and their Laplace sds). One whose wells disagree beyond chance takes
up, well by well, something each well has in its own measure, and the physics it names
would not; against a rival that belongs to the wells (wear, a valve curve, a meter bias) it
explains nothing: where it would explain the rival or the two could not be told apart, the
rival explains it (``reason`` ``wells_disagree``). Seen on the Bernoulli truth with wear
(seeds 75 and 78): slip alone took up the wear with exponents 1.0-1.9 x Simpson's that
disagree (p 0.0005 and 0.02), and "explained" the wear; on the same seeds' clean fields its
wells agree (p 0.4-0.9).

A lead whose evidence is mostly a trend (wear: its own shape cannot decide) must also beat
the operating-point physics the library has, material or not (:func:`operating_point_rival`:
the best field-wide candidate that lowers the fit-once error and the BIC), and an undecided
shape loses to a field-wide rival whose wells agree and whose shape holds at the physics'
own slope (:func:`_wins`). On the Bernoulli truth without wear (seed 75) erosion had been
named for two of four wells; slip, non-material alone (-0.13 points), agrees across wells
and holds beyond the trend at 0.95 +/- 0.21, and now explains it. A shape whose slope is
above 1 beyond chance is not confirmed (``overshoots``: seed 83's wear at 1.89 +/- 0.25).

The pair is fitted once per rival; a diagnosis makes at most :data:`RIVALS` + 1 more
fit-once runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats as sps

from vfm_core.effects import EFFECTS
from vfm_core.jobs import diagnose_live as live
from vfm_core.jobs import diagnose_stats as dstats
from vfm_core.jobs.diagnose_results import CandidateResult, is_material

__all__ = [
    "RIVALS",
    "ALPHA",
    "family",
    "rivals",
    "mostly_trend",
    "operating_point_rival",
    "adds_beyond",
    "shape_beyond_trend",
    "relate",
    "explain_families",
    "why_explained",
    "prune_stale",
    "current",
    "second_to",
    "stands_alone",
    "rivals_text",
    "own_shapes",
    "trend_text",
    "trend_proxy_text",
    "field_wide",
    "consistency",
    "own_consistency",
]

#: most rival physics fitted together with the lead
RIVALS = 2
#: one-sided level of the paired block test "the pair lowers the error below the one alone"
ALPHA = 0.05


def family(effect: str) -> str:
    """The physics an effect belongs to: its variants are one (every valve family is
    ``valve``, wear with time or throughput is ``erosion``)."""
    for name in ("valve", "erosion"):
        if effect.startswith(name):
            return name
    return effect


def rivals(
    results: Sequence[CandidateResult],
) -> tuple[CandidateResult | None, list[CandidateResult]]:
    """The lead (the best material candidate fitted, ``results`` best first) and its rivals:
    the best material candidate of each other physics, at most :data:`RIVALS`, and for a
    lead whose evidence is mostly a trend its operating-point rival
    (:func:`operating_point_rival`) when no field-wide rival is among them."""
    named = [c for c in results if c.material and c.run is not None and not c.trend_proxy]
    if not named:
        return None, []
    lead, seen, out = named[0], {family(named[0].effect)}, []
    for c in named[1:]:
        if family(c.effect) in seen:
            continue
        seen.add(family(c.effect))
        out.append(c)
        if len(out) == RIVALS:
            break
    extra = operating_point_rival(lead, out, results)
    return lead, out + ([extra] if extra is not None else [])


def mostly_trend(c: CandidateResult) -> bool:
    """``c``'s own shape beyond the trend was tested and cannot decide (nearly all trend, as
    wear's): its evidence is that the residual trends in time."""
    s = c.shape
    return bool(s and s.get("blocks", 0) >= MIN_BLOCKS and not s.get("decisive"))


def operating_point_rival(
    lead: CandidateResult, others: Sequence[CandidateResult], results: Sequence[CandidateResult]
) -> CandidateResult | None:
    """The rival a lead whose evidence is mostly a trend (:func:`mostly_trend`) must beat,
    material or not: the best field-wide candidate (a flow-law or fluid correction, a
    function of the operating point: slip, the critical ratio, the real gas) that lowers
    the fit-once error and the BIC, when no field-wide candidate is among ``others``. On a
    field that depletes, a misfit of the flow law drifts with the operating point and
    trends in time as wear does; being material against the baseline is not the question,
    but whether the trend needs the lead once the flow law may follow the operating point.
    None when the lead's shape decides, or no such candidate was fitted."""
    if not mostly_trend(lead) or any(field_wide(c) for c in others):
        return None
    return next(
        (
            c
            for c in results
            if c is not lead
            and not c.material
            and c.run is not None
            and field_wide(c)
            and c.delta_mape < 0
            and c.delta_bic < 0
        ),
        None,
    )


def adds_beyond(pair: CandidateResult, one: CandidateResult, seed: int) -> dict[str, Any]:
    """Whether the pair adds beyond ``one`` alone (both scored against the same baseline):
    the change of MAPE (points) and BIC, the paired block test's p-value, and ``adds``
    (material by :func:`is_material` and p below :data:`ALPHA`). The rule near the noise
    floor (a small gain that is a large share of the error above it) is left out here: a
    flexible candidate added to a right one picks up a tenth of a point of noise and meter
    drift near the floor (slip beside wear on a Sachdeva field, seed 64), and two rivals
    that neither adds materially beyond are told apart by their shapes instead."""
    assert pair.run is not None and one.run is not None
    delta_mape = pair.mape - one.mape
    delta_bic = pair.delta_bic - one.delta_bic
    delta_all = pair.delta_bic_all - one.delta_bic_all
    test = live.paired_test(
        live.paired_differences(one.run.predictions, pair.run.predictions), seed=seed
    )
    p = float(test.get("p_value", 1.0))
    material = is_material(delta_mape, one.mape, delta_bic, delta_all, float("nan"))
    return {
        "delta_mape": delta_mape,
        "delta_bic": delta_bic,
        "low": test.get("low"),
        "high": test.get("high"),
        "p_value": p,
        "material": material,
        "adds": bool(material and p < ALPHA),
    }


#: block length (days) of the shape test's cluster-robust standard error
SHAPE_BLOCK_DAYS = 30.0
#: fewest blocks for the shape test (a cluster-robust error needs many clusters)
MIN_BLOCKS = 10
#: the slope halfway between a trend proxy (0) and the physics (1): a shape is rejected when
#: its slope lies below it beyond chance
SHAPE_MIDPOINT = 0.5
#: a detrended correction with a smaller sd (%) predicts nothing beyond the trend
_MIN_SPREAD_PCT = 1e-6
#: most one-sided uncertainty (t times the slope's se) of a shape test that decides: a test
#: whose interval reaches past the midpoint from either end cannot tell a trend proxy (0)
#: from the physics (1), and a correction that is nearly all trend (wear: a tenth of a
#: percent beyond the straight line) has a slope that the residual's other misfit, not the
#: candidate, sets; such a shape is neither rejected nor beaten by a confirmed one (but see
#: :func:`_wins` for a field-wide physics at its own slope)
DECISIVE = SHAPE_MIDPOINT
#: the physics' own slope: a fitted correction's errors shrink the slope below it
#: (regression dilution), never above; a slope above it beyond chance is no confirmation
SHAPE_PHYSICS = 1.0


def shape_beyond_trend(
    base: pd.DataFrame, *cands: pd.DataFrame, block_days: float = SHAPE_BLOCK_DAYS
) -> list[dict[str, Any]]:
    """Does the residual follow each candidate's correction beyond the trend?

    ``base`` and ``cands``: prediction frames of the comparison baseline and of one or more
    candidates (fit once, same rows). With r = log(measured / base) the baseline's residual
    and c_i = log(cand_i / base) each candidate's correction, all minus a straight line in
    time per well and meter (:func:`vfm_core.jobs.diagnose_stats.detrend`), r is regressed
    on the c_i together (least squares: two rivals' corrections are judged side by side, so
    that the part of the residual one explains does not count for or against the other).
    Each slope ``beta`` is near 1 when its candidate is the physics (the residual's ups and
    downs beyond the trend are its correction's; a little below, as a fitted correction's
    errors shrink it) and near 0 when it only stands in for the trend. The standard errors
    are cluster-robust over blocks of ``block_days`` per well (the residual is
    autocorrelated), with the small-sample factor G/(G-1) (N-1)/(N-K) and Student's t on
    G - 1 degrees of freedom (G blocks; at least :data:`MIN_BLOCKS`, else nothing is
    decided). Per candidate: ``beta``, ``se``, ``blocks``, ``spread`` (the sd of its
    detrended correction, %: near 0 it predicts nothing beyond the trend, and nothing can be
    rejected or confirmed), ``decisive`` (the one-sided uncertainty t se is under
    :data:`DECISIVE`: the test can tell a trend proxy from the physics), ``rejected`` (beta
    below :data:`SHAPE_MIDPOINT` beyond chance, one-sided at :data:`ALPHA`: closer to a trend
    proxy than to the physics; only when decisive), ``overshoots`` (beta above
    :data:`SHAPE_PHYSICS` beyond chance, one-sided at :data:`ALPHA`: the residual moves
    beyond the trend more than the correction does, so the size its trend calls for is not
    the size its ups and downs call for, which one physics would not give; a fitted
    correction's errors only shrink the slope), ``confirmed`` (beta above 0 beyond chance
    and not overshooting: the residual follows its shape at its size) and ``at_physics``
    (confirmed, and not below :data:`SHAPE_PHYSICS` beyond chance either: 1 inside its
    two-sided interval at 2 x :data:`ALPHA`)."""
    empty = {"beta": None, "se": None, "blocks": 0, "spread": 0.0}
    empty |= {"decisive": False, "rejected": False, "confirmed": False}
    empty |= {"overshoots": False, "at_physics": False}
    m = base["measured"].to_numpy(dtype=float)
    pb = base["predicted"].to_numpy(dtype=float)
    pcs = np.column_stack([c["predicted"].to_numpy(dtype=float) for c in cands])
    ok = np.isfinite(m) & np.isfinite(pb) & (m > 0) & (pb > 0)
    ok &= np.all(np.isfinite(pcs) & (pcs > 0), axis=1)
    if ok.sum() < 10:
        return [dict(empty) for _ in cands]
    rows = pd.DataFrame(
        {
            "time": pd.to_datetime(base["time"], utc=True).to_numpy()[ok],
            "well": base["well"].astype(str).to_numpy()[ok],
            "source": base["source"].astype(str).to_numpy()[ok],
        }
    )
    r = dstats.detrend(rows, np.clip(np.log(m[ok] / pb[ok]), -dstats.CLIP, dstats.CLIP))
    x = np.column_stack(
        [dstats.detrend(rows, np.log(pcs[ok, i] / pb[ok])) for i in range(len(cands))]
    )
    spread = 100.0 * x.std(axis=0)
    _, block = np.unique(live.block_ids(rows, block_days), return_inverse=True)
    groups = int(block.max()) + 1
    out = [{**empty, "spread": float(s_), "blocks": groups} for s_ in spread]
    # a correction with nothing beyond the trend (wear with time) predicts nothing to test
    active = np.flatnonzero(spread > _MIN_SPREAD_PCT)
    xa = x[:, active]
    xtx = xa.T @ xa
    if not len(active) or groups < MIN_BLOCKS or np.linalg.cond(xtx) > 1e12:
        return out
    beta = np.linalg.solve(xtx, xa.T @ r)
    scores = np.zeros((groups, len(active)))
    np.add.at(scores, block, xa * (r - xa @ beta)[:, None])
    bread = np.linalg.inv(xtx)
    n, k = len(r), len(active)
    factor = groups / (groups - 1) * (n - 1) / max(n - k, 1)
    se = np.sqrt(np.clip(factor * np.diag(bread @ (scores.T @ scores) @ bread), 0.0, None))
    for j, i in enumerate(active):
        if se[j] > 0:
            out[i].update(_judge_slope(float(beta[j]), float(se[j]), groups - 1))
    return out


def _judge_slope(beta: float, se: float, df: int) -> dict[str, Any]:
    """A shape's slope ``beta`` (se ``se``, Student's t on ``df``) judged: ``decisive``,
    ``rejected``, ``overshoots``, ``confirmed`` and ``at_physics``
    (:func:`shape_beyond_trend`)."""
    t = sps.t(df=df)
    decisive = bool(t.ppf(1.0 - ALPHA) * se < DECISIVE)
    overshoots = bool(t.sf((beta - SHAPE_PHYSICS) / se) < ALPHA)
    confirmed = bool(t.sf(beta / se) < ALPHA) and not overshoots
    return {
        "beta": beta,
        "se": se,
        "decisive": decisive,
        "rejected": decisive and bool(t.cdf((beta - SHAPE_MIDPOINT) / se) < ALPHA),
        "overshoots": overshoots,
        "confirmed": confirmed,
        "at_physics": confirmed and bool(t.cdf((beta - SHAPE_PHYSICS) / se) >= ALPHA),
    }


_MIRROR = {
    "explains": "explained_by",
    "explained_by": "explains",
    "both": "both",
    "indistinguishable": "indistinguishable",
    "shape_loses": "shape_wins",
    "shape_wins": "shape_loses",
}


def relate(
    lead: CandidateResult,
    rival: CandidateResult,
    pair: CandidateResult,
    seed: int,
    comparison: pd.DataFrame | None = None,
) -> str:
    """The relation of ``lead`` to ``rival`` given their ``pair`` fitted together (one of
    ``explains``, ``explained_by``, ``both``, ``indistinguishable``, and for two that
    neither adds beyond, told apart by their shapes beyond the trend against the
    ``comparison`` baseline's predictions (:func:`_tell_apart`): ``shape_wins`` (the
    lead's shape wins) or ``shape_loses``), recorded on both (``rivals``) and as
    ``explained_by`` on the one explained; returns it."""
    rival_beyond = adds_beyond(pair, lead, seed)
    lead_beyond = adds_beyond(pair, rival, seed)
    shapes: dict[str, Any] = {}
    if lead_beyond["adds"] and rival_beyond["adds"]:
        relation = "both"
    elif lead_beyond["adds"]:
        relation = "explains"
    elif rival_beyond["adds"]:
        relation = "explained_by"
    else:
        relation, shapes = _tell_apart(lead, rival, comparison)
    relation, reason = _wells_disagree(lead, rival, relation)
    if relation in ("explains", "shape_wins"):
        rival.explained_by = lead.effect
    elif relation in ("explained_by", "shape_loses"):
        lead.explained_by = rival.effect
    record = {"pair": pair.spec or pair.effect, "stale": False, "reason": reason}
    lead.rivals[rival.effect] = {
        "relation": relation,
        "ranked_first": True,
        **record,
        "it_adds": rival_beyond,
        "adds_beyond_it": lead_beyond,
        "shape": shapes.get("lead"),
        "its_shape": shapes.get("rival"),
        "its_consistency": rival.consistency,
    }
    rival.rivals[lead.effect] = {
        "relation": _MIRROR[relation],
        "ranked_first": False,
        **record,
        "it_adds": lead_beyond,
        "adds_beyond_it": rival_beyond,
        "shape": shapes.get("rival"),
        "its_shape": shapes.get("lead"),
        "its_consistency": lead.consistency,
    }
    return relation


def _wins(a: dict[str, Any], b: dict[str, Any], a_agrees: bool = False) -> bool:
    """Shape ``a`` wins over shape ``b``: ``b`` is rejected and ``a`` is not, or ``a`` is
    confirmed and ``b``, though its test was decisive, is not (only ``a`` made a prediction
    beyond the trend that could have failed and did not). A shape whose test cannot decide
    (nearly all trend, as wear's) loses to nothing: that the other's shape holds beyond the
    trend says nothing about which of the two carries the trend itself. Except to a
    field-wide physics whose wells agree on one value (``a_agrees``, :func:`_agrees`) and
    whose shape holds at the physics' own slope (``at_physics``): one value for every well
    that carries the trend as well as the other does (neither adds beyond the other) and
    the ups and downs beyond it at their size is the whole misfit; a candidate that
    predicts nothing testable beyond the trend adds nothing to it (its own test, undecided,
    decides nothing, whether it reads "confirmed" or not)."""
    if b["rejected"] and not a["rejected"]:
        return True
    if a_agrees and a.get("at_physics") and not b.get("decisive", True):
        return True  # an undecided test (even "confirmed") decides nothing
    return bool(
        a["confirmed"] and b.get("decisive", True) and not b["confirmed"] and not a["rejected"]
    )


def _agrees(c: CandidateResult) -> bool:
    """``c`` is field-wide and its wells' fitted values agree (:func:`consistency`)."""
    if c.consistency is None:
        c.consistency = consistency(c)
    return bool(c.consistency is not None and c.consistency["consistent"])


def _tell_apart(
    lead: CandidateResult, rival: CandidateResult, comparison: pd.DataFrame | None
) -> tuple[str, dict[str, Any]]:
    """Two rivals neither of which adds beyond the other, by their shapes beyond the trend
    (:func:`shape_beyond_trend`, judged together): the one whose shape loses (rejected
    while the other's is not, or unconfirmed by a decisive test while the other's is
    confirmed: :func:`_wins`) is explained
    by the other (``shape_loses``: the lead's; ``shape_wins``: the rival's), else
    ``indistinguishable``."""
    if comparison is None or lead.run is None or rival.run is None:
        return "indistinguishable", {}
    both = shape_beyond_trend(comparison, lead.run.predictions, rival.run.predictions)
    shapes = {"lead": both[0], "rival": both[1]}
    if _wins(shapes["rival"], shapes["lead"], _agrees(rival)):
        return "shape_loses", shapes
    if _wins(shapes["lead"], shapes["rival"], _agrees(lead)):
        return "shape_wins", shapes
    return "indistinguishable", shapes


def field_wide(c: CandidateResult) -> bool:
    """``c`` is physics of the flow law or the fluid, the same at every well
    (:attr:`vfm_core.effects.Effect.field_wide`)."""
    cls = EFFECTS.get(c.effect)
    return bool(cls is not None and cls.field_wide)


def consistency(c: CandidateResult) -> dict[str, Any] | None:
    """Whether the wells' fitted values of a field-wide effect agree: Cochran's Q, the
    precision-weighted squared deviations of each well's value from their common weighted
    mean (per parameter, summed), against chi-square with (wells - 1) degrees of freedom per
    parameter; the wells with a finite, positive Laplace sd count. ``q``, ``df``,
    ``p_value`` and ``consistent`` (p at least :data:`ALPHA`); None for an effect that is
    not field-wide or with fewer than two wells to compare. The Laplace sds ignore the
    residuals' autocorrelation, so Q errs towards "disagree"; it decides only against a
    rival that belongs to the wells (:func:`_wells_disagree`)."""
    if not field_wide(c):
        return None
    q, df = 0.0, 0
    for entry in c.parameters.values():
        sds = entry.get("per_well_sd") or {}
        pairs = [(v, sds.get(w)) for w, v in (entry.get("per_well") or {}).items()]
        ok = [(v, sd) for v, sd in pairs if sd is not None and np.isfinite(v) and sd > 0]
        if len(ok) < 2:
            continue
        v, sd = np.array(ok, dtype=float).T
        w = 1.0 / sd**2
        mean = float(np.sum(w * v) / np.sum(w))
        q += float(np.sum(w * (v - mean) ** 2))
        df += len(ok) - 1
    if df == 0:
        return None
    p = float(sps.chi2.sf(q, df))
    return {"q": q, "df": df, "p_value": p, "consistent": p >= ALPHA}


def own_consistency(results: Sequence[CandidateResult]) -> None:
    """Each material field-wide candidate's :func:`consistency` (``consistency``)."""
    for c in results:
        if c.material:
            c.consistency = consistency(c)


def _disagrees(a: CandidateResult, b: CandidateResult) -> bool:
    """``a`` is field-wide with wells that disagree, ``b`` belongs to the wells."""
    if a.consistency is None:
        a.consistency = consistency(a)
    ca = a.consistency
    return ca is not None and not ca["consistent"] and not field_wide(b)


def _wells_disagree(
    lead: CandidateResult, rival: CandidateResult, relation: str
) -> tuple[str, str | None]:
    """The relation after the wells' agreement is weighed (see the module docstring): a
    field-wide candidate whose wells disagree does not explain a rival that belongs to the
    wells, nor is it told apart from it: the rival explains it. Returns the relation and
    its reason (``wells_disagree``, or None when the relation stands)."""
    if relation in ("explains", "indistinguishable", "shape_wins") and _disagrees(lead, rival):
        return "explained_by", "wells_disagree"
    if relation in ("explained_by", "indistinguishable", "shape_loses") and _disagrees(rival, lead):
        return "explains", "wells_disagree"
    return relation, None


def explain_families(results: Sequence[CandidateResult]) -> None:
    """A physics explained in its best form is explained in every form: the other
    candidates of an explained candidate's family (its weaker variants) get the same
    ``explained_by``, with the form that was weighed (``via_family``)."""
    by_family = {
        family(c.effect): (c.explained_by, c.effect)
        for c in results
        if c.explained_by and "via_family" not in c.rivals.get(c.explained_by, {})
    }
    for c in results:
        if c.explained_by is None and family(c.effect) in by_family:
            other, form = by_family[family(c.effect)]
            c.explained_by = other
            c.rivals.setdefault(
                other, {"relation": "explained_by", "ranked_first": False, "via_family": form}
            )


def prune_stale(results: Sequence[CandidateResult]) -> None:
    """A relation with a candidate that ended up explained by a third says nothing about
    what is named: it is marked ``stale`` (not listed under ``then`` or ``alternatives``,
    and no longer holding a candidate second)."""
    explained = {c.effect for c in results if c.explained_by is not None}
    for c in results:
        for other, r in c.rivals.items():
            if other in explained and r["relation"] in ("both", "indistinguishable"):
                r["stale"] = True


def current(c: CandidateResult, relation: str) -> list[str]:
    """The rivals of ``c`` in ``relation`` to it, not stale."""
    return [o for o, r in c.rivals.items() if r["relation"] == relation and not r.get("stale")]


def second_to(c: CandidateResult) -> str | None:
    """The rival ranked before ``c`` that the data cannot tell it from (``indistinguishable``,
    ``c`` not ranked first, not stale), or None. Such a candidate is neither offered nor
    named on its own: its evidence is the other's, and naming it where the other is not
    offered would pick one of two equal explanations by the replay's noise."""
    return next(
        (
            other
            for other, r in c.rivals.items()
            if r["relation"] == "indistinguishable"
            and not r.get("ranked_first", True)
            and not r.get("stale")
        ),
        None,
    )


def stands_alone(c: CandidateResult) -> bool:
    """``c`` may be named or offered on its own: no rival explains it, and it is not an
    alternative to a better-ranked one (:func:`second_to`)."""
    return c.explained_by is None and second_to(c) is None and not c.trend_proxy


def why_explained(c: CandidateResult) -> str:
    """Why an explained candidate is neither named nor offered, in one clause."""
    other = c.explained_by
    r = c.rivals.get(other or "", {})
    if "via_family" in r:
        return f"explained by {other}, as its stronger form {r['via_family']} is"
    if r.get("reason") == "wells_disagree" and c.consistency is not None:
        k = c.consistency
        return (
            f"explained by {other}: {c.effect} is the same physics at every well, but fitted "
            f"alone its wells' values disagree (Cochran's Q {k['q']:.1f} on {k['df']} df, "
            f"p = {k['p_value']:.2g}): it takes up, well by well, what {other} describes"
        )
    if r.get("relation") == "shape_loses":
        own = r.get("shape") or {}
        how = (
            "does not fit the residual"
            if own.get("rejected")
            else (
                "is not borne out by the residual, while the other's is"
                if own.get("decisive", True)
                else "predicts too little to test, while the other's, one value at every "
                "well, holds at the physics' own slope"
                f" ({_shape_text(r.get('its_shape'))})"
            )
        )
        return (
            f"explained by {other}: the two explain the same misfit, and beyond the trend "
            f"this one's shape {how} ({_shape_text(r.get('shape'))})"
        )
    return f"explained by {other}: fitted together, it adds nothing material beyond it"


def _shape_text(t: dict[str, Any] | None) -> str:
    if not t or t.get("beta") is None:
        return "no shape beyond the trend to test"
    text = f"slope {t['beta']:.2f} +/- {t['se']:.2f} on its correction, 1 if it were the physics"
    if t.get("overshoots"):
        text += " (above 1 beyond chance: no confirmation)"
    return text


def _beyond_text(t: dict[str, Any] | None) -> str:
    if not t:
        return "not fitted together"
    return f"fit-once MAPE {t['delta_mape']:+.2f} points, BIC {t['delta_bic']:+.0f}, p = {t['p_value']:.2g}"


def rivals_text(c: CandidateResult) -> str:
    """What the rivalry says of a named candidate, in words (empty without rivals)."""
    parts = []
    for other, r in c.rivals.items():
        rel, it = r["relation"], r.get("it_adds")
        if r.get("stale") or "via_family" in r:
            continue
        if rel == "explains" and r.get("reason") == "wells_disagree":
            k = r.get("its_consistency") or {}
            parts.append(
                f"It explains {other} too: {other} is the same physics at every well, but "
                f"fitted alone its wells' values disagree (Cochran's Q {k.get('q', float('nan')):.1f} "
                f"on {k.get('df', 0)} df, p = {k.get('p_value', float('nan')):.2g}): it takes up, "
                f"well by well, what {c.effect} describes."
            )
        elif rel == "explains":
            parts.append(
                f"It explains {other} too: fitted together, {other} adds nothing material beyond it "
                f"({_beyond_text(it)})."
            )
        elif rel == "both":
            parts.append(
                f"{other} may be at work too: fitted together, it still lowers the error "
                f"beyond {c.effect} ({_beyond_text(it)}); once {c.effect} is in the model, "
                f"diagnose again."
            )
        elif rel == "indistinguishable":
            parts.append(
                f"{other} explains the same misfit about as well: neither adds beyond the other "
                f"({other} beyond it: {_beyond_text(it)}), nor do their shapes beyond the trend "
                f"tell them apart ({c.effect}: {_shape_text(r.get('shape'))}; {other}: "
                f"{_shape_text(r.get('its_shape'))}): the data cannot tell them apart; "
                f"{c.effect} ranks first by the evidence."
            )
        elif rel == "shape_wins":
            parts.append(
                f"{other} explains the same misfit about as well (neither adds beyond the other), "
                f"but beyond a straight line in time per well its shape "
                f"({_shape_text(r.get('its_shape'))}) fits the residual less than "
                f"{c.effect}'s ({_shape_text(r.get('shape'))})."
            )
        elif rel in ("explained_by", "shape_loses"):
            parts.append(why_explained(c).replace("explained by", "It is explained by", 1) + ".")
    return " ".join(parts)


def own_shapes(results: Sequence[CandidateResult], comparison: pd.DataFrame) -> None:
    """Each material candidate's own shape beyond the trend, alone (``shape``): what the
    verdict says of a candidate whose evidence is only a trend (:func:`trend_text`)."""
    for c in results:
        if c.material and c.run is not None:
            c.shape = shape_beyond_trend(comparison, c.run.predictions)[0]


def trend_proxy_text(c: CandidateResult) -> str:
    """Why a trend proxy (:attr:`CandidateResult.trend_proxy`) is neither named nor offered,
    in one clause."""
    return (
        f"the residual does not follow its correction beyond a straight line in time per well "
        f"({_shape_text(c.shape)}, below 0.5 beyond chance): what it lowers "
        f"({c.delta_mape:+.2f} points fit once) is a trend it stands in for, not its physics"
    )


def trend_text(c: CandidateResult) -> str:
    """What a named candidate's own shape says when its test cannot decide (nearly all
    trend, as wear's), in words; empty otherwise. Its evidence is then that the residual
    trends in time, and any misfit that drifts with the operating point looks the same."""
    s = c.shape
    if not s or s.get("decisive") or s.get("blocks", 0) < MIN_BLOCKS:
        return ""
    return (
        f"Its evidence is mostly a trend in time: beyond a straight line per well its "
        f"correction varies by {s['spread']:.2f} % (sd), too little to test its shape "
        f"({_shape_text(s)}). Wear is the library's physics for such a trend, but a misfit "
        "of the model that drifts with the operating point as the field depletes looks the "
        "same; its physical parameter is worth reading with that in mind."
    )
