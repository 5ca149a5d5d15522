"""What a diagnosis produces, in memory: :class:`Diagnosis`, :class:`CandidateResult`,
:class:`Suggestion`, and the rule that makes a candidate material.

Their own module, below both the job that makes them (:mod:`vfm_core.jobs.diagnose`) and the
report that draws them (:mod:`vfm_core.reporting.diagnosis`), so neither imports the other
for its types (as :mod:`vfm_core.jobs.results` for the study). ``to_json`` of each is the
public contract of ``diagnosis.json`` (format ``vfm-diagnosis/3``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import pandas as pd

from vfm_core.jobs.diagnose_stats import DRIVER_VARIABLES, acts_through

if TYPE_CHECKING:
    from vfm_core.jobs.study import RunResult

__all__ = [
    "MATERIAL_MAPE_ABS",
    "MATERIAL_MAPE_REL",
    "MATERIAL_BIC",
    "MATERIAL_SHARE",
    "MATERIAL_MAPE_NEAR_FLOOR",
    "is_material",
    "RIVAL_KEYS",
    "BRIEF_KEYS",
    "brief",
    "CandidateResult",
    "Suggestion",
    "Diagnosis",
]

#: A candidate is a *material* improvement only if it lowers the MAPE by at least
#: max(MATERIAL_MAPE_ABS percentage points, MATERIAL_MAPE_REL x the baseline MAPE) and
#: lowers the BIC by more than MATERIAL_BIC. Why: with nothing hidden, extra parameters
#: that follow the MPFM's ordinary slow drift (0.3-1 %/sqrt(yr)) lower a 2-5 % MAPE by
#: up to ~0.1 points; 10 in BIC is "very strong" evidence (Kass & Raftery 1995).
MATERIAL_MAPE_ABS = 0.25
MATERIAL_MAPE_REL = 0.10
MATERIAL_BIC = 10.0
#: Near the noise floor a real effect has little error left to remove (real gas on a field
#: whose refitted C_D absorbs most of Z): it is also material when it removes at least
#: MATERIAL_SHARE of the error above the floor, and at least MATERIAL_MAPE_NEAR_FLOOR points.
#: A share above 1 (the candidate's MAPE below the floor) is no evidence: no model goes below
#: a true floor, so the estimate is then not a floor of these data and the share measures
#: nothing (seed 52 at the default wear: slip, a meter bias and erosion each "removed" 154 to
#: 194 % of the 0.09 points above a floor estimate that all three went under).
MATERIAL_SHARE = 1.0 / 3.0
MATERIAL_MAPE_NEAR_FLOOR = 0.1


#: Hybrid models whose network absorbs what a missing effect would explain: their candidates
#: are identified on the mechanistic core (mm with the same effects), fit once, and replayed
#: on the hybrid itself (what adding the effect does to the model the well runs).
HYBRIDS = ("ham", "hem")


def is_material(
    delta_mape: float, base_mape: float, delta_bic: float, delta_all: float, share: float
) -> bool:
    """The BIC falls by more than :data:`MATERIAL_BIC` on the reference and over every
    measurement, and the MAPE by at least max(:data:`MATERIAL_MAPE_ABS` points,
    :data:`MATERIAL_MAPE_REL` of the baseline), or, near the noise floor, by at least
    :data:`MATERIAL_MAPE_NEAR_FLOOR` points that are :data:`MATERIAL_SHARE` of the error above
    the floor, and at most all of it (``share``; nan without a floor or with a floor that a
    candidate went below: the share is then no evidence)."""
    if not (delta_bic < -MATERIAL_BIC and delta_all < -MATERIAL_BIC):
        return False
    if delta_mape <= -max(MATERIAL_MAPE_ABS, MATERIAL_MAPE_REL * base_mape):
        return True
    return bool(delta_mape <= -MATERIAL_MAPE_NEAR_FLOOR and MATERIAL_SHARE <= share <= 1.0)


#: the verdict's lists of rivals (:mod:`vfm_core.jobs.diagnose_rivals`): those the named
#: candidate explains, those at work beside it (the next step), those the data cannot tell
#: from it
RIVAL_KEYS = ("explains", "then", "alternatives")

#: the fields of a paired test kept in a brief (:func:`brief`): the change of the MAPE
#: (points), its 95 % interval, p and q, the counts and the two MAPEs (%)
BRIEF_KEYS = (
    "change",
    "low",
    "high",
    "p_value",
    "q_value",
    "rejected",
    "n",
    "n_blocks",
    "block_days",
    "base_mape",
    "mape",
    "replayed",
    "window_days",
    "since",
)


def brief(t: dict[str, Any] | None) -> dict[str, Any] | None:
    """A test without its per-well breakdown."""
    if t is None:
        return None
    return {k: t[k] for k in BRIEF_KEYS if k in t}


@dataclass
class CandidateResult:
    """One candidate effect (or set) under the same protocol as the baseline."""

    effect: str
    mape: float
    delta_mape: float
    bic: float
    delta_bic: float
    n_parameters: int
    parameters: dict[str, Any]
    meaning: str
    material: bool
    run: RunResult | None = field(default=None, repr=False)
    #: the change in BIC over every scored measurement (delta_bic may be on well tests only)
    delta_bic_all: float = float("nan")
    #: parameters at a physical bound, in words
    warnings: list[str] = field(default_factory=list)
    #: the candidate this one is a variant of (valve families after ``valve``), if any
    variant_of: str | None = None
    #: the text that adds this effect (``--effects``, ``PUT /wells/{well}/model``)
    spec: str = ""
    #: share of the baseline's error above the noise floor this candidate removes
    share_above_floor: float = float("nan")
    #: the variable the effect acts through (its before/after panel)
    driver: str | None = None
    #: paired block tests against the baseline per protocol (``fit_once``, ``live``,
    #: ``outage``): change, interval, p, q, rejected, per_well (see diagnose_live)
    tests: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: replayed under the well's own learning method (live and outage)
    replayed: bool = False
    #: adding it is offered (it lowers the live or outage error beyond chance, raises neither)
    offer: bool = False
    #: the replay says it raises the live error (point estimate above 0)
    raises_error: bool | None = None
    #: why adding it is not offered, in words (None when offered)
    offer_note: str | None = None
    live_run: RunResult | None = field(default=None, repr=False)
    outage_run: RunResult | None = field(default=None, repr=False)
    #: the trial backtest: fitted on everything before the last
    #: :data:`vfm_core.jobs.diagnose_live.TRIAL_DAYS` days of data, as the service installs a
    #: change, then learning with the well's method (``tests["trial"]``, not in the FDR family)
    trial_run: RunResult | None = field(default=None, repr=False)
    #: the driver evidence that names this candidate where the fit-once evidence alone does
    #: not (:func:`vfm_core.jobs.diagnose_verdicts.physics_behind_driver`): {"driver",
    #: "correction", "test", "rule"}; None otherwise
    via_driver: dict[str, Any] | None = None
    #: replayed on a hybrid as identified on its mechanistic core: its parameters fixed at
    #: the core's values, shared by the wells (``spec`` then names them;
    #: :func:`vfm_core.jobs.diagnose.core_form`)
    core_fixed: bool = False
    #: the candidate of other physics that explains this one: fitted together, this one
    #: adds nothing beyond it (:mod:`vfm_core.jobs.diagnose_rivals`); None otherwise
    explained_by: str | None = None
    #: each rival fitted together with this one: {other: {"relation", "ranked_first", "pair",
    #: "stale", "it_adds", "adds_beyond_it", "shape", "its_shape"}}, or {"relation":
    #: "explained_by", "via_family"} for a weaker form of a physics explained in its best
    #: form (:func:`vfm_core.jobs.diagnose_rivals.relate`)
    rivals: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: its own shape beyond the trend, alone (material candidates fitted once:
    #: :func:`vfm_core.jobs.diagnose_rivals.shape_beyond_trend`): beta, se, blocks, spread,
    #: decisive, rejected, confirmed; None when not tested
    shape: dict[str, Any] | None = None
    #: for a field-wide effect (slip, real gas, the critical ratio), whether its wells'
    #: fitted values agree (:func:`vfm_core.jobs.diagnose_rivals.consistency`): q, df,
    #: p_value, consistent; None for an effect of one well's hardware or meter, or untested
    consistency: dict[str, Any] | None = None
    #: parameters at a physical bound (``warnings`` says them in words): ``[{"parameter",
    #: "side", "bound", "unit", "wells"}]``, the wells where each sits there
    at_bound: list[dict[str, Any]] = field(default_factory=list)
    #: where this form of a physics gives way to another form of it (the valve families:
    #: :func:`vfm_core.jobs.diagnose_verdicts.weigh_forms`), and is not offered there:
    #: ``{"field" or a well: {"to", "rule", "text", ...}}``
    gives_way: dict[str, dict[str, Any]] = field(default_factory=dict)

    #: the variables the residual is examined against, in report order
    driver_variables: ClassVar[tuple[str, ...]] = DRIVER_VARIABLES

    @property
    def named(self) -> bool:
        """The evidence names this candidate: material by the fit-once evidence, or the
        physics behind a driver the correction was fitted in (``via_driver``), and no rival
        of other physics explains it (``explained_by``), and its shape beyond the trend is
        not rejected (``trend_proxy``)."""
        return (
            (self.material or self.via_driver is not None)
            and self.explained_by is None
            and not self.trend_proxy
        )

    @property
    def trend_proxy(self) -> bool:
        """Its own shape beyond the trend was tested decisively and rejected
        (:func:`vfm_core.jobs.diagnose_rivals.shape_beyond_trend` alone: slope below 0.5
        beyond chance, 1 if it were the physics): the residual does not follow what this
        candidate predicts beyond a straight line in time, so what it lowers is a trend it
        stands in for, and it is neither named nor offered (a valve curve on a clean field
        whose flow law the model lacks: the choke opens as the field depletes). Only for a
        library effect that acts through the operating point (the choke, the pressures, the
        gas fraction): wear's physics is a trend in time or throughput, and a meter's drift
        one in time (their correction beyond a straight line is a bend that strong wear's
        residual need not follow: seed 41, wear 30 %/yr, slope 0.02 +/- 0.26); an effect
        of the user's says nothing of what it acts through."""
        s = self.shape
        through = acts_through(self.effect)
        if through is None or through in ("time", "throughput_years"):
            return False
        return bool(s and s.get("decisive") and s.get("rejected"))

    @property
    def material_rule(self) -> dict[str, float]:
        """What makes a candidate material: MAPE drop (points, relative) and BIC drop."""
        return {
            "mape_abs": MATERIAL_MAPE_ABS,
            "mape_rel": MATERIAL_MAPE_REL,
            "bic": MATERIAL_BIC,
            "near_floor": MATERIAL_MAPE_NEAR_FLOOR,
            "share": MATERIAL_SHARE,
        }

    def test(self, protocol: str, well: str | None = None) -> dict[str, Any] | None:
        """The paired test of a protocol, the field's (``well`` None) or one well's."""
        t = self.tests.get(protocol)
        if not t or well is None:
            return t
        return t.get("per_well", {}).get(well, t if not t.get("per_well") else None)

    def to_json(self) -> dict[str, Any]:
        return {
            "replayed": self.replayed,
            "offer": self.offer,
            "raises_error": self.raises_error,
            "offer_note": self.offer_note,
            "live": brief(self.test("live")),
            "outage": brief(self.test("outage")),
            "tests": self.tests,
            "effect": self.effect,
            "spec": self.spec or self.effect,
            "mape": self.mape,
            "delta_mape": self.delta_mape,
            "bic": self.bic,
            "delta_bic": self.delta_bic,
            "delta_bic_all": self.delta_bic_all,
            "n_parameters": self.n_parameters,
            "material": self.material,
            "meaning": self.meaning,
            "parameters": self.parameters,
            "warnings": list(self.warnings),
            "variant_of": self.variant_of,
            "share_above_floor": self.share_above_floor,
            "via_driver": self.via_driver,
            "core_fixed": self.core_fixed,
            "explained_by": self.explained_by,
            "rivals": self.rivals,
            "shape": self.shape,
            "trend_proxy": self.trend_proxy,
            "consistency": self.consistency,
            "at_bound": self.at_bound,
            "gives_way": self.gives_way,
        }


@dataclass
class Suggestion:
    """A generic correction for an effect outside the library, fitted like a candidate."""

    driver: str
    form: str
    shared: bool
    spec: str
    text: str
    parameters: dict[str, Any]
    result: CandidateResult
    #: every form tried: form, shared, n_parameters, mape, delta_bic
    variants: list[dict[str, Any]]
    #: the same correction learned per well (the spec), when the shared one was chosen
    per_well_spec: str
    #: a starting point for one's own Effect class
    code: str

    @property
    def mape(self) -> float:
        return self.result.mape

    def to_json(self) -> dict[str, Any]:
        return {
            "driver": self.driver,
            "form": self.text,
            "shape": self.form,
            "shared": self.shared,
            "parameters": self.parameters,
            "mape": self.result.mape,
            "delta_mape": self.result.delta_mape,
            "delta_bic": self.result.delta_bic,
            "delta_bic_all": self.result.delta_bic_all,
            "material": self.result.material,
            "share_above_floor": self.result.share_above_floor,
            "effects": self.spec,
            "per_well_effects": self.per_well_spec,
            "variants": self.variants,
            "code": self.code,
            "warnings": list(self.result.warnings),
            "replayed": self.result.replayed,
            "offer": self.result.offer,
            "offer_note": self.result.offer_note,
            "raises_error": self.result.raises_error,
            "live": brief(self.result.test("live")),
            "outage": brief(self.result.test("outage")),
            "tests": self.result.tests,
        }


@dataclass
class Diagnosis:
    """Everything ``vfm diagnose`` found; :meth:`to_json` is the public contract."""

    model: str
    method: str
    targets: str
    split: pd.Timestamp
    baseline: RunResult
    baseline_mape: float
    baseline_bic: float
    residuals: pd.DataFrame
    drivers: list[dict[str, Any]]
    regions: dict[str, list[dict[str, Any]]]
    candidates: list[CandidateResult]
    findings: list[str]
    #: the verdict in one sentence (``verdict_kind`` etc. give it as data)
    verdict: str
    extended: CandidateResult | None = None
    runtime_s: float = 0.0
    #: the candidate comparison's protocol and its baseline MAPE (the candidates' reference)
    candidate_method: str = ""
    candidate_baseline_mape: float = float("nan")
    #: what the candidates' BIC was taken on: "well tests" or "all measurements"
    bic_on: str = "all measurements"
    verdict_kind: str = "noise"
    verdict_effect: str | None = None
    verdict_driver: str | None = None
    suggestion: Suggestion | None = None
    #: the noise floor (see vfm_core.jobs.diagnose_stats.noise_floor)
    floor: dict[str, Any] = field(default_factory=dict)
    #: the chance test of the drivers: method, shifts, alpha, best driver and its p-value
    noise_test: dict[str, Any] = field(default_factory=dict)
    #: candidates the data cannot inform: [{"effect", "reason"}]
    skipped: list[dict[str, str]] = field(default_factory=list)
    #: the comparison baseline's residual frame (drivers and panels are drawn from it)
    comparison_residuals: pd.DataFrame | None = None
    #: the protocol in words
    protocol: str = ""
    #: things the user should know (a split chosen for them, ...)
    notes: list[str] = field(default_factory=list)
    #: where the data came from: {"kind": "file" | "store" | "frame", "path", "well"}
    source: dict[str, Any] = field(default_factory=dict)
    #: effects already in the model (their specs): every run has them, the candidates
    #: are what is missing beyond them
    base_effects: list[str] = field(default_factory=list)
    #: the live protocol's baseline: {"protocol", "method", "mape", "n", "service_mape", ...}
    live: dict[str, Any] = field(default_factory=dict)
    #: the outage protocol's baseline: {"label", "windows", "mape", "n", ...} (empty: none)
    outage: dict[str, Any] = field(default_factory=dict)
    #: the false-discovery control: {"procedure", "q", "tests", "rejected"}
    fdr: dict[str, Any] = field(default_factory=dict)
    #: the wells diagnosed together: {"wells", "focus", "note"}
    pool: dict[str, Any] = field(default_factory=dict)
    #: each well's own verdict (what a diagnosis of that well says): {well: {...}}
    well_verdicts: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: the verdict the fit-once evidence alone gives (format 2's rule), as evidence
    fit_once_verdict: dict[str, Any] = field(default_factory=dict)
    #: the model the candidates are identified on (fit once): the model, or mm for a hybrid
    screen_model: str = ""
    #: the verdict's numbers: {"effect", "live", "outage", "evidence"} (None for noise)
    verdict_detail: dict[str, Any] | None = None

    #: the variables the residual is examined against, in report order
    driver_variables: ClassVar[tuple[str, ...]] = DRIVER_VARIABLES

    @property
    def model_label(self) -> str:
        """The model as diagnosed: ``mm``, or ``mm+erosion`` with base effects."""
        return "+".join([self.model, *self.base_effects])

    @property
    def material_rule(self) -> dict[str, float]:
        """What makes a candidate material: MAPE drop (points, relative) and BIC drop."""
        return {
            "mape_abs": MATERIAL_MAPE_ABS,
            "mape_rel": MATERIAL_MAPE_REL,
            "bic": MATERIAL_BIC,
            "near_floor": MATERIAL_MAPE_NEAR_FLOOR,
            "share": MATERIAL_SHARE,
        }

    def residuals_of(self, run: RunResult, base: pd.DataFrame | None = None) -> pd.DataFrame:
        """The residual frame of another run on the same scored rows (``base``: the frame
        whose rows it shares, default the online baseline's)."""
        out = (self.residuals if base is None else base).copy()
        out["predicted"] = run.predictions["predicted"].to_numpy(dtype=float)
        out["r"] = (out["measured"] - out["predicted"]) / out["measured"]
        return out

    @property
    def with_effect(self) -> CandidateResult | None:
        """The "with" of the headline: the verdict's effect, the suggestion, or (noise) the
        best candidate."""
        if self.verdict_kind in ("effect", "carried"):
            return next((c for c in self.candidates if c.effect == self.verdict_effect), None)
        if self.suggestion is not None and self.verdict_kind == "driver":
            return self.suggestion.result
        return self.candidates[0] if self.candidates else None

    @property
    def headline(self) -> dict[str, Any]:
        """One baseline and one "with" figure, both under the live protocol (the well's own
        learning method replayed, what the operator sees) when the diagnosis replayed, else
        under the fit-once comparison; the outage figures beside them."""
        w = self.with_effect
        if not self.live:
            return {
                "protocol": self.protocol,
                "method": self.candidate_method,
                "baseline_mape": self.candidate_baseline_mape,
                "with": None if w is None else (w.spec or w.effect),
                "with_mape": None if w is None else w.mape,
                "floor_mape": self.floor.get("mape"),
                "n": int(len(self.residuals)),
            }
        focus = self.pool.get("focus")
        replayed = w is not None and w.replayed
        lt = None if w is None else w.test("live", focus)
        ot = None if w is None else w.test("outage", focus)
        base = self.live.get("well_mape", self.live["mape"]) if focus else self.live["mape"]
        out_base = (
            self.outage.get("well_mape", self.outage.get("mape"))
            if focus
            else self.outage.get("mape")
        )
        return {
            "protocol": self.live["protocol"],
            "method": self.method,
            "baseline_mape": base,
            "with": None if w is None else (w.spec or w.effect),
            "with_mape": None if lt is None or not replayed else lt["mape"],
            "floor_mape": self.floor.get("mape"),
            "n": int(self.live.get("well_n" if focus else "n", len(self.residuals))),
            "live_change": brief(lt) if replayed else None,
            "outage_baseline_mape": out_base,
            "outage_with_mape": None if ot is None or not replayed else ot.get("mape"),
            "outage_change": brief(ot) if replayed else None,
            "trial_change": brief(w.test("trial", focus)) if w is not None and replayed else None,
            "fit_once_baseline_mape": self.candidate_baseline_mape,
            "fit_once_with_mape": None if w is None else w.mape,
        }

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "format": "vfm-diagnosis/3",
            "model": self.model,
            "base_effects": list(self.base_effects),
            "method": self.method,
            "targets": self.targets,
            "split": self.split.isoformat(),
            "source": self.source,
            "protocol": self.protocol,
            "baseline": {
                "mape": self.baseline_mape,
                "bic": self.baseline_bic,
                "n": int(len(self.residuals)),
                "candidate_method": self.candidate_method,
                "candidate_mape": self.candidate_baseline_mape,
                "bic_on": self.bic_on,
            },
            "verdict": {
                "kind": self.verdict_kind,
                "effect": self.verdict_effect,
                "driver": self.verdict_driver,
                "text": self.verdict,
            },
            "headline": self.headline,
            "floor": self.floor,
            "drivers": self.drivers,
            "drivers_on": f"the residual of {self.model_label} under {self.candidate_method}, "
            "after a straight line in time per well and meter",
            "noise_test": self.noise_test,
            "candidates": [c.to_json() for c in self.candidates],
            "skipped": self.skipped,
            "suggestion": None if self.suggestion is None else self.suggestion.to_json(),
            "regions": self.regions,
            "findings": self.findings,
            "notes": self.notes,
            "runtime_s": self.runtime_s,
            "live": self.live,
            "outage": self.outage,
            "fdr": self.fdr,
            "pool": self.pool,
            "well_verdicts": self.well_verdicts,
            "fit_once": {
                "protocol": self.protocol,
                "method": self.candidate_method,
                "model": self.screen_model or self.model,
                "baseline_mape": self.candidate_baseline_mape,
                "verdict": self.fit_once_verdict,
                "role": "evidence: identifies candidates and drivers; the verdict is taken "
                "under the live and outage protocols",
            },
        }
        out["verdict"].update(self.verdict_detail or {})
        for key in RIVAL_KEYS:  # present on every verdict, empty when nothing is related
            out["verdict"].setdefault(key, [])
        if self.extended is not None:
            out["extended"] = self.extended.to_json()
        return out
