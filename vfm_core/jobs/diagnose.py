"""Diagnose a choke model: where it fails, which physical effect is missing, and what adding it gives.

``vfm diagnose DATA --model mm --method ol --out DIR`` (or ``--store PATH`` for a running
service's data) answers with one verdict, of four kinds:

* ``effect``: adding a library effect (:mod:`vfm_core.effects`) lowers the error the
  operator sees (live) or the error while the meter is out (outage) beyond chance, and
  raises neither; it is named with both changes and their intervals, the evidence, and
  its fitted parameters with their uncertainty;
* ``driver``: no library effect does, but a variable explains the residual beyond time,
  well and chance, and a generic correction in it (fitted, offered as an effect
  ``--effects suggest:driver=...`` and as code to start one's own) passes the same test;
* ``carried``: the fit-once evidence names an effect, but adding it to the model the well
  runs lowers neither error beyond chance (the learner, or a hybrid's network, already
  carries it), or raises one: not offered;
* ``noise``: none of these;
* ``instrument``: the evidence for a well's effect, driver or carried verdict coincides with
  a fault :mod:`vfm_core.sensor_faults` detects in one of its inputs (its gain concentrated
  in the fault's interval, or its driver the faulty input's variable): the sensor, the
  fault's kind and interval instead of physics (:mod:`vfm_core.jobs.diagnose_instrument`);
  the field's verdict too when most of its gain comes from such wells.

An ``effect`` may also be named through a driver: when the correction fitted for a driver
is not better, beyond the replay's noise, than a library effect that acts through that
variable (a valve family through the choke opening), the effect is named with the driver
as its evidence (``via_driver``;
:func:`vfm_core.jobs.diagnose_verdicts.physics_behind_driver`).

**The verdict's protocols** (format ``vfm-diagnosis/3``): the well's own learning method
(``method``) is replayed over the history (:func:`vfm_core.jobs.study.run_prequential`:
every measurement after the split predicted before it is learned, as the service runs it),
so that the baseline is the live error the service shows (**live**), and again with
:data:`OUTAGE` windows without a measurement (**outage**), scored inside them. The baseline
and the best :data:`REPLAY_TOP` candidates by the fit-once evidence (plus a suggested
correction) are replayed; each is compared with the baseline by paired block tests of the
per-measurement differences of absolute percentage error, for the field and for each well,
all tests of a diagnosis in one Benjamini-Hochberg family (:mod:`vfm_core.jobs.diagnose_live`,
which states each rule and its reason). A candidate is *offered* (the page's "apply") only
when neither error rises and a test finds a lower one beyond chance
(:func:`vfm_core.jobs.diagnose_verdicts.offer`).
``well`` diagnoses one well beside its pool (the other wells of the data, which a store
narrows to those running the same model and method): the field's evidence and the well's,
side by side (``well_verdicts`` holds each well's). Hybrids (:data:`HYBRIDS`) are
identified on their mechanistic core (``mm`` with the same effects) and replayed as they
are; a candidate acting through an input their network sees (a valve family through the
choke opening) is replayed as identified on the core, its parameters fixed (:func:`core_form`:
learned with the network it would be confounded with it). The fit-once protocol below is kept as **evidence**: it names and ranks the
candidates, finds the drivers and fits the correction; ``fit_once.verdict`` in the JSON is
the verdict it alone would give (format 2's rule); ``replay_top=0`` gives only that.

How the fit-once evidence is taken:

1. **One protocol for every comparison** (``--candidate-method``, default
   :data:`CANDIDATE_METHOD`): the model is fitted once on the measurements before the split
   (the mechanistic model to convergence: its priors are its regulariser, and early
   stopping on the latest slice of a drifting history stops before a trend such as wear is
   learned) and scored on every measurement after it, held out. The baseline, each
   candidate, its variants and the suggested correction all go through it; the headline
   gives one baseline and one "with" figure under it. Online learning (``--method``, default
   ``ol``) is run once more for *where the model fails* as it would in operation, not to
   compare: it follows, and so hides, what a missing effect does.
2. **Where it fails**: the relative residual r = (measured - predicted)/measured of the
   online run by well, quarter, choke opening, flow regime and meter.
3. **Which effect is missing**: each candidate the data can inform (a meter bias needs well
   tests *and* MPFM readings, a valve curve a choke that moves, ...; the others are listed
   as skipped, with the reason) is added and ranked by the change in BIC of the relative
   residuals (n log(mean r^2) + k log n, k = effect parameters over all wells), taken on
   the **well tests** (the reference meter) when at least :data:`MIN_WELL_TESTS` are
   scored, else on every measurement with one noise level per meter: MPFM readings drift
   slowly, and their many correlated rows would otherwise reward whichever candidate's
   trend follows the meter. A candidate is *material* when it lowers the MAPE by at least
   max(:data:`MATERIAL_MAPE_ABS` points, :data:`MATERIAL_MAPE_REL` of the baseline) and the
   BIC by more than :data:`MATERIAL_BIC`, on the reference and over every measurement. The
   best material candidate's variants (the valve families after the learned valve curve,
   wear with time after wear with throughput) are then tried too: one learned form rarely
   fits every field. Fitted parameters come with a posterior sd (a Gauss-Newton Laplace
   approximation on the training data, see :func:`_laplace_sd`) and a warning where one
   sits at a physical bound.
4. **Drivers** (:mod:`vfm_core.jobs.diagnose_stats`): what each variable (the inputs, the
   pressure ratio, water cut, throughput, the day of the year) explains of the comparison
   baseline's residual *beyond a straight line in time per well and meter*, out of sample,
   and whether the best of them beats chance (circular shifts, family-wise p-value).
5. **A suggested correction**: with no material candidate and a driver that beats chance,
   a multiplicative correction of the rate in that driver (linear, then log-linear; shared
   by all wells or per well; chosen by BIC) is fitted under the same protocol. It makes the
   verdict ``driver`` only if it also lowers the held-out error and BIC materially (a second,
   held-out test); else the verdict is ``noise``.
6. **Rivals** (:mod:`vfm_core.jobs.diagnose_rivals`): when the evidence names more than one
   physics, the best candidate is fitted together with the next two of other physics, and
   each is asked whether it adds beyond the other, then (when neither does) whether its
   shape beyond the trend fits the residual; one explained by another is neither named nor
   offered, one at work beside the verdict's is its next step (``then``), one the data
   cannot tell from it is listed (``alternatives``).
7. **The noise floor**: the meters' white noise, estimated from consecutive readings
   (:func:`vfm_core.jobs.diagnose_stats.noise_floor`), so that "how much of the error above
   the floor the effect removes" can be read.

Outputs (written atomically): ``DIR/diagnosis.json`` (format ``vfm-diagnosis/3``; every field
of format 2 kept, the headline now under the live protocol with the fit-once figures beside
it, plus ``live``, ``outage``, ``fdr``, ``pool``, ``well_verdicts``, ``fit_once`` and per
candidate ``replayed``, ``offer``, ``raises_error``, ``live``, ``outage``, ``tests``;
format 2's fields: ``model``,
``baseline``, ``drivers``, ``candidates`` as before, plus ``verdict`` ``{"kind", "effect",
"driver", "text"}``, ``headline``, ``suggestion`` ``{"driver", "form", "parameters", "mape",
...}``, ``floor``, ``noise_test``, ``skipped``, ``notes``) and ``DIR/report.html``.

Where the parts live (all exported from here as before): the result types and the rule that
makes a candidate material in :mod:`vfm_core.jobs.diagnose_results` (below both this job
and the report, :mod:`vfm_core.reporting.diagnosis`); the data sources (a service's store,
a well's pool, the history in front) in :mod:`vfm_core.jobs.diagnose_sources`; the files
written and the printed summary in :mod:`vfm_core.jobs.diagnose_output`; the drivers and
the noise floor in :mod:`vfm_core.jobs.diagnose_stats`; the replay's paired tests in
:mod:`vfm_core.jobs.diagnose_live`; the tests of each candidate, the false-discovery
control, the offers and the verdicts in :mod:`vfm_core.jobs.diagnose_verdicts`; the
instrument check in :mod:`vfm_core.jobs.diagnose_instrument`. Here: the protocol
(:func:`run_diagnosis`, its steps in :class:`_DiagnosisRun`), what the data can inform,
the candidates' scores and uncertainty, the suggested correction and the command line.
"""

from __future__ import annotations

import argparse
import math
import textwrap
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from vfm_core.data import Batch, make_batch, target_mask
from vfm_core.effects import (
    DEFAULT_CANDIDATES,
    EFFECTS,
    SUGGEST_DRIVERS,
    CriticalRatio,
    Effect,
    MeterBias,
    RealGas,
    Slip,
    Valve,
    ValveFamily,
    add_features,
    effect_spec,
    fixed_effect,
    resolve_effect,
    resolve_effects,
)
from vfm_core.errors import ConfigError, DataError
from vfm_core.features import STANDARD_FEATURES, standard_features
from vfm_core.jobs import diagnose_live as live
from vfm_core.jobs import diagnose_rivals as rivals
from vfm_core.jobs import diagnose_stats as stats
from vfm_core.jobs import diagnose_verdicts as verdicts
from vfm_core.jobs.diagnose_output import format_summary, json_safe, write_diagnosis
from vfm_core.jobs.diagnose_results import (
    HYBRIDS,
    MATERIAL_BIC,
    MATERIAL_MAPE_ABS,
    MATERIAL_MAPE_REL,
    RIVAL_KEYS,
    CandidateResult,
    Diagnosis,
    Suggestion,
    is_material,
)
from vfm_core.jobs.diagnose_sources import (
    load_source,
    pool_frame,
    store_model,
    stored_method,
    with_history,
)
from vfm_core.jobs.diagnose_stats import DRIVER_VARIABLES, acts_through, rank_drivers
from vfm_core.jobs.diagnose_verdicts import PHYSICS_ALPHA, REPLAY_TOP
from vfm_core.jobs.study import RunResult, mape, plan_outages, resolve_split, run_prequential
from vfm_core.learning import DEFAULT_TRAIN, OnlineSettings, TrainSettings
from vfm_core.models import EFFECT_MODELS, ChokeModel
from vfm_core.schema import INPUT_COLUMNS, MPFM, SOURCE, TIME, WELL, WELL_TEST

__all__ = [
    "DRIVER_VARIABLES",
    "MATERIAL_MAPE_ABS",
    "MATERIAL_MAPE_REL",
    "MATERIAL_BIC",
    "MIN_WELL_TESTS",
    "CANDIDATE_METHOD",
    "REPLAY_TOP",
    "OUTAGE",
    "HYBRIDS",
    "NETWORK_INPUTS",
    "core_form",
    "VARIANTS",
    "PHYSICS_ALPHA",
    "acts_through",
    "reference_bic",
    "CandidateResult",
    "Suggestion",
    "Diagnosis",
    "residual_frame",
    "rank_drivers",
    "bic",
    "DiagnosisSettings",
    "run_diagnosis",
    "write_diagnosis",
    "format_summary",
    "load_source",
    "pool_frame",
    "with_history",
    "stored_method",
    "json_safe",
    "register",
]

# The rule that makes a candidate material (MATERIAL_*) lives with the result types, in
# vfm_core.jobs.diagnose_results, and is exported from here as before.
#: the comparison protocol: fit once before the split, never update (100-year period)
CANDIDATE_METHOD = "pbl:36500d"
#: The outage protocol's window: a month without a measurement (a failed MPFM's repair).
OUTAGE = "30d"
#: The variables a hybrid's network sees: its six inputs and what is computed from them alone.
#: A candidate acting through one of them (:func:`acts_through`: a valve family through the
#: choke opening, slip through the gas fraction, ...) is replayed on a hybrid as identified
#: on the core (:func:`core_form`).
NETWORK_INPUTS = ("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil", "p_ratio", "water_cut")
#: fewest scored well tests for the BIC to be taken on them (else: on every measurement)
MIN_WELL_TESTS = 20
#: Library variants tried after a material candidate: other forms of the same physics.
VARIANTS: dict[str, tuple[str, ...]] = {
    "valve": (
        "valve_equal_percentage",
        "valve_quick_opening",
        "valve_convex",
        "valve_sigmoid",
    ),
}
#: Most drivers (those that beat chance, best first) a correction is fitted for.
SUGGEST_TOP = 2
#: Fewest measurements per source (before the split) for a meter-bias candidate.
_MIN_PER_SOURCE = 5
#: A valve curve is offered when some well's choke spans at least this (P5..P95) in training.
_MIN_CHOKE_SPAN = 0.05
_CLIP = stats.CLIP

ProgressFn = Callable[[float, str], None]


# --- residuals ------------------------------------------------------------------------------
def residual_frame(
    frame: pd.DataFrame,
    predictions: pd.DataFrame,
    *,
    targets: str,
    split: pd.Timestamp,
    p_cr: dict[str, float] | None = None,
) -> pd.DataFrame:
    """The scored rows with inputs, derived variables and the relative residual ``r``.

    ``predictions`` come from :func:`vfm_core.jobs.study.run_prequential` on the same frame,
    whose rows are the target rows on or after ``split`` in frame order. ``p_cr`` (per
    well) sets the critical-flow boundary (default 0.55).
    """
    rows = np.flatnonzero(target_mask(frame, targets) & (frame[TIME] >= split).to_numpy())
    if len(rows) != len(predictions):
        raise ValueError("The predictions do not belong to this frame, target case and split.")
    scored = frame.iloc[rows]
    feats = standard_features(frame).iloc[rows]
    out = pd.DataFrame(
        {
            "time": pd.to_datetime(scored[TIME], utc=True).to_numpy(),
            "well": scored[WELL].astype(str).to_numpy(),
            "source": scored[SOURCE].astype(str).to_numpy(),
        }
    )
    for col in INPUT_COLUMNS:
        out[col] = scored[col].to_numpy(dtype=float)
    out["p_ratio"] = out["p_down"] / out["p_up"]
    out["water_cut"] = feats["water_cut"].to_numpy()
    out["throughput_years"] = feats["throughput_years"].to_numpy()
    out["years_on"] = feats["years_on"].to_numpy()
    limits = out["well"].map(p_cr or {}).astype(float).fillna(0.55).to_numpy()
    out["flow_regime"] = np.where(out["p_ratio"].to_numpy() < limits, "critical", "subcritical")
    out["predicted"] = predictions["predicted"].to_numpy(dtype=float)
    out["measured"] = predictions["measured"].to_numpy(dtype=float)
    out["r"] = (out["measured"] - out["predicted"]) / out["measured"]
    out["time"] = pd.to_datetime(out["time"], utc=True)
    out["day_of_year"] = stats.driver_values(out, "day_of_year")
    return out


def bic(residuals: np.ndarray, k: int, groups: np.ndarray | None = None) -> float:
    """BIC of relative residuals under Gaussian errors with one variance per group.

    sum over groups g of n_g log(mean r_g^2) + k log n. The groups are the measurement
    sources: MPFM readings (2-5 % noise) and well tests (about 1 %) carry different
    noise, so a term that fits only the many MPFM rows and not the precise well tests
    gains less than one that fits both.
    """
    r = np.asarray(residuals, dtype=float)
    g = np.zeros(len(r), dtype=int) if groups is None else pd.factorize(np.asarray(groups))[0]
    ok = np.isfinite(r)
    r, g = np.clip(r[ok], -_CLIP, _CLIP), g[ok]
    n = len(r)
    if n == 0:
        return float("nan")
    total = 0.0
    for code in np.unique(g):
        rg = r[g == code]
        total += len(rg) * math.log(max(float(np.mean(rg**2)), 1e-300))
    return float(total + k * math.log(n))


def reference_bic(predictions: pd.DataFrame, k: int) -> tuple[float, str]:
    """BIC of a run's relative residuals on the reference meter, and what it was taken on.

    On the scored well tests when there are at least :data:`MIN_WELL_TESTS` of them,
    otherwise on every scored measurement (one variance per source); see the module
    docstring for why.
    """
    p = predictions
    r = ((p["measured"] - p["predicted"]) / p["measured"]).to_numpy(dtype=float)
    src = p["source"].to_numpy()
    wt = (src == WELL_TEST) & np.isfinite(r)
    if int(wt.sum()) >= MIN_WELL_TESTS:
        return bic(r[wt], k), "well tests"
    return bic(r, k, src), "all measurements"


def _regions(res: pd.DataFrame) -> dict[str, list[dict[str, Any]]]:
    def summary(groups: Any) -> list[dict[str, Any]]:
        rows = []
        for key, g in groups:
            key = key[0] if isinstance(key, tuple) else key
            rows.append(
                {
                    "region": str(key),
                    "n": int(len(g)),
                    "mape": mape(g["predicted"], g["measured"]),
                    "median_residual": float(np.nanmedian(g["r"])) if len(g) else float("nan"),
                }
            )
        return sorted(rows, key=lambda d: -(d["mape"] if math.isfinite(d["mape"]) else -1))

    choke_bin = pd.cut(
        res["choke"],
        [0, 0.2, 0.4, 0.6, 0.8, 1.0001],
        right=False,
        labels=["0-0.2", "0.2-0.4", "0.4-0.6", "0.6-0.8", "0.8-1"],
    )
    quarter = res["time"].dt.tz_convert(None).dt.to_period("Q").astype(str)
    return {
        "well": summary(res.groupby("well", sort=False)),
        "period": summary(res.groupby(quarter.to_numpy(), sort=True)),
        "choke": summary(res.groupby(choke_bin.to_numpy(), sort=True, observed=True)),
        "flow_regime": summary(res.groupby("flow_regime")),
        "source": summary(res.groupby("source")),
    }


def _findings(
    res: pd.DataFrame, regions: dict[str, list[dict[str, Any]]], overall: float
) -> list[str]:
    words = {
        "well": "well",
        "period": "quarter",
        "choke": "choke opening",
        "flow_regime": "flow regime",
        "source": "measurement source",
    }
    out = []
    for key, rows in regions.items():
        rows = [r for r in rows if r["n"] >= 10 and math.isfinite(r["mape"])]
        if len(rows) < 2:
            continue
        top = rows[0]
        sign = "under-predicts" if top["median_residual"] > 0 else "over-predicts"
        out.append(
            f"By {words[key]}: the largest error is in {top['region']} (MAPE {top['mape']:.1f} % vs "
            f"{overall:.1f} % overall, n = {top['n']}); there the model {sign} by a median "
            f"{100 * abs(top['median_residual']):.1f} %."
        )
    return out


# --- what the data can inform -----------------------------------------------------------------
def _offer_reason(
    cls: type[Effect], train: pd.DataFrame, min_choke_span: float = _MIN_CHOKE_SPAN
) -> str | None:
    """Why the training rows (measured, before the split) cannot inform ``cls``; None if they
    can. ``min_choke_span``: the span a valve curve needs (0 once a correction in the
    choke opening fitted on the same rows showed that their span informs a curve in it)."""
    if train.empty:
        return "there are no measurements before the split"
    src = train[SOURCE].to_numpy()
    if issubclass(cls, MeterBias) or cls.uses_source:
        n_wt, n_mpfm = int((src == WELL_TEST).sum()), int((src == MPFM).sum())
        if n_wt < _MIN_PER_SOURCE or n_mpfm < _MIN_PER_SOURCE:
            return (
                f"a meter bias against well tests needs both before the split: {n_wt} well "
                f"test(s) and {n_mpfm} MPFM reading(s) (at least {_MIN_PER_SOURCE} of each)"
            )
    if issubclass(cls, Valve | ValveFamily):
        span = train.groupby(WELL)["choke"].quantile(0.95) - train.groupby(WELL)["choke"].quantile(
            0.05
        )
        if float(span.max()) < min_choke_span:
            return (
                f"the choke hardly moves (largest P5-P95 span {float(span.max()):.3f} in one well), "
                "so a valve curve cannot be told from C_D"
            )
    gas = train["eta_gas"].to_numpy(dtype=float)
    if issubclass(cls, RealGas | Slip | CriticalRatio) and float(np.nanmax(gas)) < 1e-3:
        return "there is no gas in the mixture"
    if issubclass(cls, Slip) and float(np.nanmin(gas)) > 0.999:
        return "there is no liquid in the mixture"
    if issubclass(cls, CriticalRatio):
        ratio = (train["p_down"] / train["p_up"]).to_numpy(dtype=float)
        if float(np.mean(ratio < 0.65)) < 0.02:
            return (
                "the flow never comes near critical (p_down/p_up below 0.65 in under 2 % of rows)"
            )
    return None


def _training_rows(frame: pd.DataFrame, targets: str, split: pd.Timestamp) -> np.ndarray:
    return np.flatnonzero(target_mask(frame, targets) & (frame[TIME] < split).to_numpy())


# --- uncertainty --------------------------------------------------------------------------------
def _laplace_sd(model: ChokeModel, batch: Batch) -> dict[str, np.ndarray]:
    """Posterior sd per well (SI units) of the physical and effect parameters, keyed like
    ``model.physical_parameters()``: a Gauss-Newton Laplace approximation at the fit.

    The Jacobian of the log rate with respect to the standardised parameters z (theta =
    mu + sigma z) is taken by central differences; the noise variance of the log residual
    per well and meter from the fit's residuals; the prior is z ~ N(0, 1). The data's
    precision is divided by (1 + rho)/(1 - rho), rho the lag-1 autocorrelation of each
    well's residual (an AR(1) effective sample size: MPFM errors drift). Network weights of
    hybrid models are held at their values (the sd is conditional on them).
    """
    blocks: list[tuple[str, Any]] = []
    if getattr(model, "phys", None) is not None:
        blocks.append(("", model.phys))
    for name, block in getattr(model, "effect_params", {}).items():
        blocks.append((f"{name}.", block))
    cols = [(prefix + n, block, i) for prefix, block in blocks for i, n in enumerate(block.names)]
    if not cols or int(batch.count().sum()) == 0:
        return {}
    step = 1e-4
    with torch.no_grad():
        q0 = model.forward_batch(batch)
        ok = batch.mask & torch.isfinite(q0) & (q0 > 0) & (batch.y > 0)
        r = torch.where(ok, torch.log(batch.y.clamp(min=1e-12) / q0.clamp(min=1e-12)), 0.0)
        jac = torch.zeros(*q0.shape, len(cols), dtype=q0.dtype)
        for j, (_, block, i) in enumerate(cols):
            z = block.z.data
            old = z[:, i].clone()
            z[:, i] = old + step
            up = torch.log(model.forward_batch(batch).clamp(min=1e-12))
            z[:, i] = old - step
            down = torch.log(model.forward_batch(batch).clamp(min=1e-12))
            z[:, i] = old
            jac[..., j] = (up - down) / (2 * step)
        jac = torch.where(ok.unsqueeze(-1) & torch.isfinite(jac), jac, torch.zeros_like(jac))
        assert batch.well_test is not None
        weight = torch.zeros_like(r)
        for meter in (batch.well_test, ~batch.well_test):
            m = ok & meter
            var = (r**2 * m).sum(1) / m.sum(1).clamp(min=1)
            weight = torch.where(m, 1.0 / var.clamp(min=1e-8).unsqueeze(1), weight)
        # lag-1 autocorrelation per well, over consecutive valid samples (time order)
        pair = ok[:, 1:] & ok[:, :-1]
        num = (r[:, 1:] * r[:, :-1] * pair).sum(1)
        den = (r**2 * ok).sum(1).clamp(min=1e-30)
        rho = (num / den).clamp(0.0, 0.95)
        inflate = (1.0 + rho) / (1.0 - rho)
        hess = torch.einsum("wnp,wnq->wpq", jac * weight.unsqueeze(-1), jac)
        hess = hess / inflate.view(-1, 1, 1) + torch.eye(len(cols), dtype=hess.dtype)
        sd_z = torch.sqrt(torch.diagonal(torch.linalg.inv(hess), dim1=1, dim2=2).clamp(min=0.0))
    return {key: (block.sigma[i] * sd_z[:, j]).numpy() for j, (key, block, i) in enumerate(cols)}


def _bounds_hit(model: ChokeModel, ready: np.ndarray) -> list[dict[str, Any]]:
    """Parameters that sit at a physical bound (other than their 'no effect' prior mean):
    ``[{"parameter", "side", "bound", "unit", "wells"}]``, one entry a parameter and side,
    with the (ready) wells where it sits there. Such a value is not an estimate: the data
    push it past what physics allows (:func:`_bound_text` says so in words; the verdict
    prefers a form of the same physics that fits within its bounds,
    :func:`vfm_core.jobs.diagnose_verdicts.weigh_forms`)."""
    priors_of = getattr(model, "physical_priors", None)  # a physics model's own
    priors = priors_of() if priors_of is not None else {}
    params = model.physical_parameters()
    out: list[dict[str, Any]] = []
    for key, prior in priors.items():
        if key not in params:
            continue
        values = params[key].numpy()
        span = prior.high - prior.low
        for side, bound in (("lower", prior.low), ("upper", prior.high)):
            if abs(bound - prior.mean) < 1e-12 * max(1.0, abs(bound)):
                continue  # the bound is "no effect" (a wear rate of 0): a legitimate answer
            hit = ready & (np.abs(values - bound) <= 1e-3 * span)
            if hit.any():
                out.append(
                    {
                        "parameter": key,
                        "side": side,
                        "bound": float(bound),
                        "unit": prior.unit,
                        "wells": [w for w, h in zip(model.wells, hit, strict=True) if h],
                    }
                )
    return out


def _bound_text(hits: Sequence[dict[str, Any]]) -> list[str]:
    """:func:`_bounds_hit`'s entries in words, one warning each."""
    out = []
    for h in hits:
        wells = h["wells"]
        shown = ", ".join(wells[:5]) + (f" and {len(wells) - 5} more" if len(wells) > 5 else "")
        out.append(
            f"{h['parameter']} sits at its {h['side']} bound {h['bound']:g} {h['unit']} in "
            f"{shown}: the data push it past what physics allows; read it as a sign of another "
            "effect or of bad data, not as a value."
        )
    return out


def _bound_warnings(model: ChokeModel, ready: np.ndarray) -> list[str]:
    """Parameters that sit at a physical bound, in words (:func:`_bounds_hit`)."""
    return _bound_text(_bounds_hit(model, ready))


# --- candidates -----------------------------------------------------------------------------
def _parameter_summary(
    run: RunResult, effects: Sequence[type[Effect]], train_batch: Batch | None
) -> tuple[dict[str, Any], str, int, list[dict[str, Any]]]:
    model = run.final_model
    assert model is not None
    params = model.physical_parameters()
    ready = model.ready.numpy()
    sds = _laplace_sd(model, train_batch) if train_batch is not None else {}
    out: dict[str, Any] = {}
    medians: dict[str, dict[str, float]] = {}
    k = 0
    for cls in effects:
        for pname, prior in cls.parameters.items():
            key = f"{cls.name}.{pname}"
            values = params[key].numpy()
            med = float(np.median(values[ready])) if ready.any() else float("nan")
            sd = sds.get(key)
            medians.setdefault(cls.name, {})[pname] = med
            out[key] = {
                "value": med,
                "sd": float(np.median(sd[ready])) if sd is not None and ready.any() else None,
                "unit": prior.unit,
                "meaning": prior.meaning,
                "prior_mean": prior.mean,
                "prior_std": prior.std,
                "low": prior.low,
                "high": prior.high,
                "per_well": {w: float(v) for w, v in zip(model.wells, values, strict=True)},
                "per_well_sd": (
                    {w: float(v) for w, v in zip(model.wells, sd, strict=True)}
                    if sd is not None
                    else {}
                ),
            }
            k += int(ready.sum())
    meaning = " ".join(cls().describe(medians.get(cls.name, {})) for cls in effects)
    return out, meaning, k, _bounds_hit(model, ready)


def _score(
    name: str,
    run: RunResult,
    effects: Sequence[type[Effect]],
    base_mape: float,
    base: RunResult,
    train_batch: Batch | None,
    *,
    k_override: int | None = None,
) -> CandidateResult:
    p = run.predictions
    r = ((p["measured"] - p["predicted"]) / p["measured"]).to_numpy(dtype=float)
    params, meaning, k, hits = _parameter_summary(run, effects, train_batch)
    if k_override is not None:
        k = k_override
    m = mape(p["predicted"], p["measured"])
    b, on = reference_bic(p, k)
    b0, on0 = reference_bic(base.predictions, 0)
    bp = base.predictions
    r0 = ((bp["measured"] - bp["predicted"]) / bp["measured"]).to_numpy(dtype=float)
    delta_all = bic(r, k, p["source"].to_numpy()) - bic(r0, 0, bp["source"].to_numpy())
    delta_mape = m - base_mape
    delta_bic = b - b0 if on == on0 else delta_all
    material = is_material(delta_mape, base_mape, delta_bic, delta_all, float("nan"))
    driver = acts_through(name)
    return CandidateResult(
        name,
        m,
        delta_mape,
        b,
        delta_bic,
        k,
        params,
        meaning,
        material,
        run,
        delta_all,
        _bound_text(hits),
        spec="+".join(effect_spec(c) for c in effects),
        driver=driver,
        at_bound=hits,
    )


# --- the suggested correction ---------------------------------------------------------------------
def _shared_value(values: np.ndarray, sds: np.ndarray) -> tuple[float, float]:
    """A coefficient shared by all wells from per-well estimates: the precision-weighted
    mean, with the larger of its sd and the wells' spread over sqrt(wells)."""
    ok = np.isfinite(values) & np.isfinite(sds) & (sds > 0)
    if not ok.any():
        return float(np.nanmedian(values)), float("nan")
    w = 1.0 / sds[ok] ** 2
    mean = float(np.sum(w * values[ok]) / np.sum(w))
    sd = 1.0 / math.sqrt(float(np.sum(w)))
    if ok.sum() > 1:
        sd = max(sd, float(np.std(values[ok], ddof=1)) / math.sqrt(int(ok.sum())))
    return mean, sd


def _x0(values: np.ndarray, scale: float) -> float:
    """A round reference value near the median (a multiple of half the scale step)."""
    med = float(np.nanmedian(values)) if len(values) else 0.0
    unit = scale / 2.0
    return float(round(med / unit) * unit) if math.isfinite(med) else 0.0


def _form_text(cls: type[Effect], values: dict[str, tuple[float, float]], shared: bool) -> str:
    """The correction in words, with the fitted values and their sd."""
    driver = SUGGEST_DRIVERS[cls.driver]  # type: ignore[attr-defined]
    who = "the same for every well" if shared else "median over wells, learned per well"

    def pm(key: str) -> str:
        v, s = values[key]
        return (
            ("+ " if v >= 0 else "- ")
            + f"{abs(v):.3g}"
            + (f" ± {s:.2g}" if math.isfinite(s) else "")
        )

    if cls.form == "season":  # type: ignore[attr-defined]
        return (
            f"C_D x (1 {pm('k_sin')} sin(2 pi d) {pm('k_cos')} cos(2 pi d)), d = fraction of the "
            f"year since 1 January ({who})"
        )
    x0 = f"{cls.x0:g} {driver.unit}".rstrip()  # type: ignore[attr-defined]
    step = cls.step  # type: ignore[attr-defined]
    if cls.form == "log":  # type: ignore[attr-defined]
        return f"C_D x exp({pm('k').replace(' ', '', 1)} per {step} of {cls.driver} above {x0}) ({who})"  # type: ignore[attr-defined]
    return f"C_D x (1 {pm('k')} per {step} of {cls.driver} above {x0}) ({who})"  # type: ignore[attr-defined]


_SNIPPET_X = {
    "choke": ("inputs.u", "fraction"),
    "p_up": ("inputs.p_up / 1e5", "bar"),
    "p_down": ("inputs.p_down / 1e5", "bar"),
    "p_ratio": ("inputs.p_down / inputs.p_up", "-"),
    "t_up": ("inputs.t_up - 273.15", "degC"),
    "eta_gas": ("inputs.eta_gas", "-"),
    "eta_oil": ("inputs.eta_oil", "-"),
    "water_cut": ("inputs.water_cut", "-"),
    "years_on": ('inputs.feature("years_on")', "yr"),
    "throughput_years": ('inputs.feature("throughput_years")', "yr-eq"),
}


def _snippet(cls: type[Effect], values: dict[str, tuple[float, float]]) -> str:
    """A starting point for one's own Effect class: the suggestion written out."""
    driver = cls.driver  # type: ignore[attr-defined]
    title = "".join(part.capitalize() for part in driver.split("_")) + "Correction"
    if cls.form == "season":  # type: ignore[attr-defined]
        s, c = values["k_sin"][0], values["k_cos"][0]
        return textwrap.dedent(
            f'''\
            import math

            import torch

            from vfm_core.effects import Effect, EffectInputs, Prior


            class SeasonCorrection(Effect):
                """The rate times 1 + a sin(2 pi d) + b cos(2 pi d), d = fraction of the year."""

                name = "season_correction"
                parameters = {{
                    "a": Prior({s:.3g}, 0.05, -0.5, 0.5, "-", "amplitude of sin(2 pi d)"),
                    "b": Prior({c:.3g}, 0.05, -0.5, 0.5, "-", "amplitude of cos(2 pi d)"),
                }}

                def output_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
                    assert inputs.time_ns is not None
                    d = torch.remainder(inputs.time_ns.double() / 86400e9, 365.2425) / 365.2425
                    phase = 2 * math.pi * d
                    return 1.0 + p["a"] * torch.sin(phase) + p["b"] * torch.cos(phase)
            '''
        )
    expr, unit = _SNIPPET_X[driver]
    k, k_sd = values["k"]
    prior_sd = max(0.1, 3 * k_sd) if math.isfinite(k_sd) else 0.1
    x0, scale, step = cls.x0, cls.scale, cls.step  # type: ignore[attr-defined]
    extra = (
        f'\n    extra_columns = ("{driver}",)' if driver in ("years_on", "throughput_years") else ""
    )
    factor = (
        f'torch.exp(p["k"] * (x - {x0:g}) / {scale:g})'
        if cls.form == "log"  # type: ignore[attr-defined]
        else f'1.0 + p["k"] * (x - {x0:g}) / {scale:g}'
    )
    return textwrap.dedent(
        f'''\
        import torch

        from vfm_core.effects import Effect, EffectInputs, Prior


        class {title}(Effect):
            """The rate (C_D) times a factor of {driver}: fitted by vfm diagnose as a start."""

            name = "{driver}_correction"
            parameters = {{
                "k": Prior({k:.3g}, {prior_sd:.2g}, -1.0, 1.0, "1/({step})", "rate change per {step}"),
            }}{extra}

            def output_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
                x = {expr}  # {unit}
                return {factor}
        '''
    )


# --- running the protocol ----------------------------------------------------------------------
class _Progress:
    """Progress of the runs: a tqdm bar, or a callback ``(fraction done, short text)``."""

    def __init__(self, progress: bool | ProgressFn, total: int) -> None:
        self.callback = progress if callable(progress) else None
        self.bar = tqdm(total=total, desc="diagnose", unit="run", disable=progress is not True)
        self.total = total
        self.done = 0
        self.fraction = 0.0

    def add(self, n: int) -> None:
        self.total += n
        self.bar.total = self.total
        self.bar.refresh()

    def start(self, text: str) -> None:
        self.bar.set_postfix_str(text)
        if self.callback is not None:
            self.callback(self.fraction, text)

    def step(self) -> None:
        self.done += 1
        self.bar.update(1)
        self.fraction = max(self.fraction, min(self.done / max(self.total, 1), 0.99))

    def finish(self, text: str) -> None:
        self.bar.close()
        if self.callback is not None:
            self.callback(1.0, text)


def _comparison_train(model: str, train: TrainSettings | None) -> TrainSettings:
    """The comparison's batch fit: the mechanistic model to convergence (its priors are its
    regulariser; early stopping on the latest slice of a drifting history stops before a
    trend such as wear is learned), the hybrids with early stopping."""
    if train is not None:
        return train
    base = DEFAULT_TRAIN.get(model, TrainSettings())
    return replace(base, early_stopping=False) if model == "mm" else base


def _choose_split(
    frame: pd.DataFrame, targets: str, split: str | pd.Timestamp | None
) -> tuple[pd.Timestamp, str | None]:
    """The split, and a note when the default one did not suit the data and another was chosen.

    A given split is kept. The target case's default is kept when it leaves at least 20 %
    of the measurements on either side; otherwise (a service's store of a few months, say)
    the split falls where 60 % of the measurements lie before it.
    """
    ts = resolve_split(targets, split)
    if split is not None:
        return ts, None
    times = frame.loc[target_mask(frame, targets), TIME]
    if times.empty:
        return ts, None
    before = float((times < ts).mean())
    if 0.2 <= before <= 0.8:
        return ts, None
    chosen = pd.Timestamp(times.quantile(0.6)).floor("D")
    chosen = chosen.tz_localize("UTC") if chosen.tzinfo is None else chosen.tz_convert("UTC")
    if not (times.min() < chosen <= times.max()):
        return ts, None
    return chosen, (
        f"The default split {ts.date()} leaves {100 * before:.0f} % of the measurements before it; "
        f"the diagnosis splits at {chosen.date()} instead (60 % before). Give --split to choose."
    )


def _screen_split(
    frame: pd.DataFrame,
    targets: str,
    screen_split: str | pd.Timestamp | None,
    split_ts: pd.Timestamp,
) -> pd.Timestamp:
    """The fit-once evidence's split: ``split_ts`` (None), the time before which 60 % of the
    measurements lie (``"auto"``), or the time given."""
    if screen_split is None:
        return split_ts
    if isinstance(screen_split, str) and screen_split == "auto":
        times = frame.loc[target_mask(frame, targets), TIME]
        if times.empty:
            return split_ts
        ts = pd.Timestamp(times.quantile(0.6)).floor("D")
    else:
        ts = pd.Timestamp(screen_split)
    return ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")


def _with_features(frame: pd.DataFrame, classes: Sequence[type[Effect]]) -> pd.DataFrame:
    """The frame with the standard features and every column the effects need."""
    out = add_features(frame, classes)
    missing = [c for c in STANDARD_FEATURES if c not in out.columns]
    if missing:
        feats = standard_features(out)
        for c in missing:
            out[c] = feats[c].to_numpy()
    return out


@dataclass(frozen=True)
class DiagnosisSettings:
    """The keywords of :func:`run_diagnosis`, one field each, as given."""

    model: str
    #: the well's learning method: the online residuals of *where it fails*, and the method
    #: replayed for the verdict (live, and with :data:`OUTAGE` windows without a measurement)
    method: str
    #: the comparison protocol, run for the baseline, every candidate and the suggestion alike
    candidate_method: str | None
    targets: str
    split: str | pd.Timestamp | None
    #: tried one at a time (those the data cannot inform are skipped)
    candidates: Sequence[str | type[Effect]]
    #: one extended model compared side by side with the base (optional)
    effects: Sequence[str | type[Effect]]
    train: TrainSettings | None
    online: OnlineSettings | None
    seed: int
    #: True for a progress bar, or a callback ``(fraction, text)`` called as each run starts
    #: and once at the end with 1.0 (for a service's background job)
    progress: bool | ProgressFn
    #: fit a correction for a driver outside the library
    suggest: bool
    #: circular shifts of the drivers' chance test (0: none)
    shifts: int
    source: dict[str, Any] | None
    #: effects the model already has (found by an earlier diagnosis and added): every run
    #: has them, so the verdict is about what is missing beyond them; a candidate among them
    #: is skipped
    base_effects: Sequence[str | type[Effect]]
    #: the best candidates by the fit-once evidence replayed under ``method`` (0: none, the
    #: fit-once verdict of format 2 only)
    replay_top: int
    #: the outage protocol's window (None: left out)
    outage: str | None
    #: the well the diagnosis is for; the other wells of the frame are its pool (the
    #: field's evidence beside the well's)
    well: str | None
    #: the model the candidates are identified on, fit once (default: ``model``, or mm for
    #: the hybrids in :data:`HYBRIDS`)
    screen_model: str | None
    #: the split of the fit-once evidence (default: ``split``; ``"auto"``: where 60 % of the
    #: measurements lie before it). A service's store joined to its history is replayed from
    #: the service's start (``split``), but identified where both sides hold enough of the
    #: operating range: a valve curve cannot be told from C_D on a history whose choke
    #: hardly moved.
    screen_split: str | pd.Timestamp | None
    #: a well whose verdict's evidence coincides with a fault that
    #: :mod:`vfm_core.sensor_faults` detects in one of its inputs gets the verdict
    #: ``instrument`` instead (:mod:`vfm_core.jobs.diagnose_instrument`)
    instrument: bool


def run_diagnosis(
    frame: pd.DataFrame,
    model: str = "mm",
    *,
    method: str = "ol",
    candidate_method: str | None = CANDIDATE_METHOD,
    targets: str = "all",
    split: str | pd.Timestamp | None = None,
    candidates: Sequence[str | type[Effect]] = DEFAULT_CANDIDATES,
    effects: Sequence[str | type[Effect]] = (),
    train: TrainSettings | None = None,
    online: OnlineSettings | None = None,
    seed: int = 0,
    progress: bool | ProgressFn = False,
    suggest: bool = True,
    shifts: int = stats.SHIFTS,
    source: dict[str, Any] | None = None,
    base_effects: Sequence[str | type[Effect]] = (),
    replay_top: int = REPLAY_TOP,
    outage: str | None = OUTAGE,
    well: str | None = None,
    screen_model: str | None = None,
    screen_split: str | pd.Timestamp | None = None,
    instrument: bool = True,
) -> Diagnosis:
    """Diagnose ``model`` (mm, hem or ham) on an observation frame; see the module docstring.

    Each keyword is described on :class:`DiagnosisSettings`. Same split, settings and seed
    everywhere. The fit-once evidence names and ranks the candidates, finds the drivers and
    fits the correction; the verdict is taken under the well's own learning method
    (``method``) replayed over the history (live) and with :data:`OUTAGE` windows without a
    measurement (outage): the baseline and the best ``replay_top`` candidates, each compared
    with paired block tests under one Benjamini-Hochberg family
    (:mod:`vfm_core.jobs.diagnose_live`).
    """
    started = time.perf_counter()
    settings = DiagnosisSettings(
        model,
        method=method,
        candidate_method=candidate_method,
        targets=targets,
        split=split,
        candidates=candidates,
        effects=effects,
        train=train,
        online=online,
        seed=seed,
        progress=progress,
        suggest=suggest,
        shifts=shifts,
        source=source,
        base_effects=base_effects,
        replay_top=replay_top,
        outage=outage,
        well=well,
        screen_model=screen_model,
        screen_split=screen_split,
        instrument=instrument,
    )
    job = _DiagnosisRun(frame, settings)
    job.fit_baselines()
    job.score_candidates()
    job.try_variants()
    job.rank_drivers()
    job.weigh_rivals()
    job.replay_shortlist()
    job.suggest_correction()
    job.fit_once_verdict()
    job.live_verdicts()
    return job.diagnosis(started)


#: one of the first runs: (key, effects beyond the base, method, train settings, model, split)
_Job = tuple[str, list[type[Effect]], str, TrainSettings | None, str, pd.Timestamp]


class _DiagnosisRun:
    """One diagnosis in progress: its settings, the frame (with the features the effects
    tried so far need), the runs made and what they found. :func:`run_diagnosis` calls its
    steps in order; each reads what the ones before it set."""

    def __init__(self, frame: pd.DataFrame, settings: DiagnosisSettings) -> None:
        s = self.s = settings
        self.cand_classes = [resolve_effect(c) for c in s.candidates]
        self.ext_classes = resolve_effects(list(s.effects)) if s.effects else []
        self.base_classes = resolve_effects(list(s.base_effects)) if s.base_effects else []
        self.in_model = {c.name for c in self.base_classes}
        self.label = "+".join([s.model, *(c.name for c in self.base_classes)])
        twice = [c.name for c in self.ext_classes if c.name in self.in_model]
        if twice:
            raise ConfigError(
                f"The effect(s) {', '.join(twice)} are in the base effects already "
                f"({self.label}); give the effects to compare beyond them."
            )
        self.frame = frame
        self._choose_splits()
        self._choose_pool_and_screen()
        self._choose_candidates()
        self.suggestion: Suggestion | None = None
        self.live_info: dict[str, Any] = {}
        self.outage_info: dict[str, Any] = {}
        self.well_verdicts: dict[str, dict[str, Any]] = {}
        self.detail: dict[str, Any] | None = None

    def _choose_splits(self) -> None:
        """The replay's split and the fit-once evidence's, with a note for each one chosen."""
        s = self.s
        self.split_ts, split_note = _choose_split(self.frame, s.targets, s.split)
        self.notes = [split_note] if split_note else []
        self.screen_ts = _screen_split(self.frame, s.targets, s.screen_split, self.split_ts)
        if self.screen_ts != self.split_ts:
            self.notes.append(
                f"The fit-once evidence is fitted before {self.screen_ts.date()} and scored "
                f"after it (60 % of the measurements before); the replay starts at "
                f"{self.split_ts.date()}."
            )
        if s.source and s.source.get("note"):
            self.notes.append(str(s.source["note"]))

    def _choose_pool_and_screen(self) -> None:
        """The wells diagnosed together (the focus well must be among them) and the model
        the candidates are identified on."""
        s, frame = self.s, self.frame
        self.pool_wells = sorted(set(frame.loc[target_mask(frame, s.targets), WELL].astype(str)))
        if s.well is not None and s.well not in self.pool_wells:
            raise DataError(
                f"The data hold no measurement of well {s.well} (they hold "
                f"{', '.join(self.pool_wells[:20])})."
            )
        self.screen = s.screen_model or ("mm" if s.model in HYBRIDS else s.model)
        if self.screen not in EFFECT_MODELS:
            raise ConfigError(f"The screen model must be one of {', '.join(EFFECT_MODELS)}.")
        if self.screen != s.model:
            self.notes.append(
                f"The candidates are identified on {self.screen}, the mechanistic core of "
                f"{s.model}, fit once (its network would absorb what a missing effect "
                f"explains); what adding one does is measured on {s.model} itself, replayed "
                f"with {s.method}."
            )

    def _choose_candidates(self) -> None:
        """The candidates the training data can inform (the others skipped, with the
        reason), the frame with every feature the runs need, and the comparison protocol."""
        s = self.s
        self.train_rows = _training_rows(self.frame, s.targets, self.screen_ts)
        self.train_frame = self.frame.iloc[self.train_rows]
        self.offered: list[type[Effect]] = []
        self.skipped: list[dict[str, str]] = []
        for cls in self.cand_classes:
            reason = (
                f"{cls.name} is already in the model ({self.label})."
                if cls.name in self.in_model
                else _offer_reason(cls, self.train_frame)
            )
            if reason is None:
                self.offered.append(cls)
            else:
                self.skipped.append({"effect": cls.name, "reason": reason})
        classes = [*self.base_classes, *self.offered, *self.ext_classes]
        self.frame = _with_features(self.frame, classes)
        self.cand_method = s.candidate_method or CANDIDATE_METHOD
        self.cand_train = _comparison_train(self.screen, s.train)

    def run(
        self,
        key: str,
        classes: list[type[Effect]],
        how: str,
        settings: TrainSettings | None,
        name: str | None = None,
        plan: Any = None,
        at: pd.Timestamp | None = None,
    ) -> RunResult:
        """One run of :func:`run_prequential` on the diagnosis's frame with the base effects
        and ``classes``: ``name`` (default the screen model) from ``at`` (default the fit-once
        split), with outages ``plan`` (if any), counted on the progress bar."""
        s = self.s
        self.bar.start(f"fitting {key.strip('_')}")
        out = run_prequential(
            self.frame,
            self.screen if name is None else name,
            how,
            effects=[*self.base_classes, *classes],
            train=settings,
            outage=plan,
            split=self.screen_ts if at is None else at,
            targets=s.targets,
            online=s.online,
            seed=s.seed,
        )
        self.bar.step()
        return out

    def _first_jobs(self) -> list[_Job]:
        """The baseline (the well's method), the comparison baseline (fit once), each
        offered candidate (fit once) and the extended model, if any."""
        s, cm, ct, screen, at = (
            self.s,
            self.cand_method,
            self.cand_train,
            self.screen,
            self.screen_ts,
        )
        jobs: list[_Job] = [("baseline", [], s.method, s.train, s.model, self.split_ts)]
        jobs.append(("__comparison__", [], cm, ct, screen, at))
        jobs += [(c.name, [c], cm, ct, screen, at) for c in self.offered]
        if self.ext_classes:
            jobs.append(
                ("__extended__", self.ext_classes, s.method, s.train, s.model, self.split_ts)
            )
        return jobs

    def fit_baselines(self) -> None:
        """Make the first runs; the baseline's residuals, BIC, regions and findings, and the
        comparison baseline's."""
        s, frame = self.s, self.frame
        jobs = self._first_jobs()
        # the replays (live and outage, baseline and the shortlist) are the slow runs: count
        # them from the start so that the progress does not jump back
        self.n_replays = (3 * max(s.replay_top, 0) + 1) if s.replay_top > 0 else 0
        self.bar = _Progress(s.progress, len(jobs) + 1 + self.n_replays)
        self.runs: dict[str, RunResult] = {}
        for key, classes, how, settings, name, at in jobs:
            self.runs[key] = self.run(key, classes, how, settings, name, at=at)
        self.classes_of: dict[str, list[type[Effect]]] = {c.name: [c] for c in self.offered}
        base = self.base = self.runs["baseline"]
        base_p = base.predictions
        self.base_mape = mape(base_p["predicted"], base_p["measured"])
        self.res = residual_frame(
            frame, base_p, targets=s.targets, split=self.split_ts, p_cr=_p_cr(base)
        )
        self.base_bic = bic(self.res["r"].to_numpy(), 0, self.res["source"].to_numpy())
        self.regions = _regions(self.res)
        self.findings = _findings(self.res, self.regions, self.base_mape)
        comp = self.comp = self.runs["__comparison__"]
        self.comp_mape = mape(comp.predictions["predicted"], comp.predictions["measured"])
        self.comp_res = residual_frame(
            frame, comp.predictions, targets=s.targets, split=self.screen_ts, p_cr=_p_cr(comp)
        )
        self.batches: dict[tuple[str, ...], Batch] = {}

    def train_batch(self, run_: RunResult) -> Batch | None:
        """The training rows of a run's fitted model as a batch (None without a model; one
        per set of extra columns), for the Laplace sds."""
        m = run_.final_model
        if m is None:
            return None
        cols = tuple(m.extra_columns)
        if cols not in self.batches:
            rows = self.train_rows
            rows = rows[self.frame.iloc[rows][WELL].astype(str).isin(m.wells).to_numpy()]
            self.batches[cols] = make_batch(self.frame, m.wells, rows=rows, extra_columns=cols)
        return self.batches[cols]

    def _rank(self) -> None:
        """Order the candidates by the change in BIC, best (lowest) first."""
        self.results.sort(key=lambda c: c.delta_bic if math.isfinite(c.delta_bic) else math.inf)

    def score_candidates(self) -> None:
        """Score each offered candidate against the comparison baseline, take the noise floor
        on the best fit (model error only adds to the differences it is taken from), and
        judge each candidate against it."""
        comp_mape, comp, comp_res = self.comp_mape, self.comp, self.comp_res
        self.results = [
            _score(
                c.name, self.runs[c.name], [c], comp_mape, comp, self.train_batch(self.runs[c.name])
            )
            for c in self.offered
        ]
        self._rank()
        fits = [comp_res]
        best_fit = min(
            (c for c in self.results if c.run is not None), key=lambda c: c.mape, default=None
        )
        if best_fit is not None and best_fit.mape < comp_mape:
            assert best_fit.run is not None
            fits.append(_residuals_like(comp_res, best_fit.run))
        floors = [stats.noise_floor(f) for f in fits]
        floor = min(floors, key=lambda f: math.inf if f["mape"] is None else f["mape"])
        floor["on"] = (
            "the comparison baseline"
            if floor is floors[0] or best_fit is None
            else "+".join(
                [self.s.model, *(effect_spec(c) for c in self.base_classes), best_fit.effect]
            )
        )
        self.floor = floor
        _trust_floor(floor, self.results)
        for c in self.results:
            _judge(c, comp_mape, floor)
        self._rank()

    def fit_once_more(self, more: Sequence[tuple[type[Effect], str | None]]) -> None:
        """Fit more candidates once (``(class, variant_of)``), judged and ranked in. The runs
        see the frame as it was; the features the new candidates need are added after."""
        frame = _with_features(self.frame, [cls for cls, _ in more])
        self.bar.add(len(more))
        for cls, of in more:
            self.classes_of[cls.name] = [cls]
            r_ = self.run(cls.name, [cls], self.cand_method, self.cand_train)
            self.results.append(
                _score(cls.name, r_, [cls], self.comp_mape, self.comp, self.train_batch(r_))
            )
            self.results[-1].variant_of = of
            _judge(self.results[-1], self.comp_mape, self.floor)
        if self.floor.get("trusted", True) and not _trust_floor(self.floor, self.results):
            for c in self.results:  # a new candidate went below the floor: judge all again
                _judge(c, self.comp_mape, self.floor)
        self._rank()
        names = {c.name for c, _ in more}
        self.skipped[:] = [x for x in self.skipped if x["effect"] not in names]
        self.frame = frame
        rivals.explain_families(self.results)  # a new form of a physics already explained

    def try_variants(self) -> None:
        """Other forms of the same physics: the variants of the best material candidate, or
        of a flexible candidate that shows the effect everywhere but on the reference's BIC."""
        best = _variant_source(self.results, self.comp_mape)
        if best is None:
            return
        tried = {c.effect for c in self.results} | {s["effect"] for s in self.skipped}
        tried |= self.in_model
        extra = []
        for name in VARIANTS[best.effect]:
            if name in tried or name not in EFFECTS:
                continue
            cls = resolve_effect(name)
            if _offer_reason(cls, self.train_frame) is None:
                extra.append(cls)
        self.fit_once_more([(cls, best.effect) for cls in extra])

    def rank_drivers(self) -> None:
        """What the comparison baseline's residual depends on beyond time and well, the
        chance test of the best driver, and (when it beats chance) the library effects that
        act through it, fitted once."""
        s, comp_res = self.s, self.comp_res
        self.bar.start("ranking drivers")
        self.drivers = rank_drivers(comp_res, shifts=s.shifts, seed=s.seed)
        self.eligible = [d for d in self.drivers if d["role"] == "driver"]
        top = self.top = self.eligible[0] if self.eligible else None
        r_raw = np.clip(comp_res["r"].to_numpy(dtype=float), -_CLIP, _CLIP)
        ok_r = np.isfinite(r_raw)
        r_det = stats.detrend(comp_res[ok_r])
        self.trend_share = 1.0 - float(np.var(r_det)) / max(float(np.var(r_raw[ok_r])), 1e-300)
        self.noise_test = {
            "trend_share": self.trend_share,
            "method": "circular shifts of the detrended residual within each well and meter; "
            "p-value of the best driver against the best score any eligible driver reaches by "
            "chance",
            "shifts": s.shifts,
            "alpha": stats.ALPHA,
            "driver": None if top is None else top["name"],
            "score": None if top is None else top["score"],
            "p_value": None if top is None else top["p_value"],
        }
        if top is not None and (top["p_value"] or 1.0) < stats.ALPHA and top["score"] > 0:
            self.fit_once_more(self._kin(top["name"]))

    def weigh_rivals(self) -> None:
        """When the fit-once evidence names more than one physics, fit the lead together with
        each rival (:func:`vfm_core.jobs.diagnose_rivals.rivals`) and record which explains
        which; a rival that explains the lead becomes the lead, and is then weighed against
        the earlier rivals it has not met. A physics explained in its best form is explained
        in every form; relations with an explained candidate go stale."""
        rivals.own_shapes(self.results, self.comp.predictions)
        rivals.own_consistency(self.results)
        lead, others = rivals.rivals(self.results)
        self.lead = lead
        if lead is None or not others:
            return
        first = lead
        self.bar.add(len(others))
        for r in others:
            self._weigh(lead, r)
            if lead.explained_by is not None:
                lead = r
        if lead is not first:
            late = [
                r
                for r in others
                if r is not lead and r.explained_by is None and lead.effect not in r.rivals
            ]
            self.bar.add(len(late))
            for r in late:
                self._weigh(lead, r)
        rivals.explain_families(self.results)
        rivals.prune_stale(self.results)
        self.lead = next((c for c in (lead, *others) if c.explained_by is None), None)

    def _weigh(self, lead: CandidateResult, rival: CandidateResult) -> None:
        """Fit ``lead`` and ``rival`` together once and relate them
        (:func:`vfm_core.jobs.diagnose_rivals.relate`)."""
        classes = [*self.classes_of[lead.effect], *self.classes_of[rival.effect]]
        key = f"{lead.effect}+{rival.effect}"
        run_ = self.run(key, classes, self.cand_method, self.cand_train)
        pair = _score(key, run_, classes, self.comp_mape, self.comp, self.train_batch(run_))
        rivals.relate(lead, rival, pair, self.s.seed, self.comp.predictions)

    def _kin(self, driver: str) -> list[tuple[type[Effect], str | None]]:
        """The library effects acting through ``driver`` not tried yet (:func:`_kin_classes`)."""
        return _kin_classes(
            self.cand_classes, self.results, self.in_model, driver, self.train_frame
        )

    def _replay_runs(self) -> int:
        """Runs a candidate's replay takes: live, with outages when the protocol is on, and
        its trial backtest when the replay is long enough (:meth:`_trial_since`)."""
        return (2 if self.plan is not None else 1) + (self._trial_since() is not None)

    def _trial_since(self) -> pd.Timestamp | None:
        """Start of the trial backtest: :data:`vfm_core.jobs.diagnose_live.TRIAL_DAYS` days
        before the latest measurement (the trial's default length), when that leaves at
        least as long again of replay after the split; else None (no backtest)."""
        frame, s = self.frame, self.s
        last = frame.loc[target_mask(frame, s.targets), TIME].max()
        since = last - pd.Timedelta(days=live.TRIAL_DAYS)
        return since if since - self.split_ts >= pd.Timedelta(days=live.TRIAL_DAYS) else None

    def replay(self, c: CandidateResult, classes: list[type[Effect]]) -> None:
        """Replay the model with ``classes`` under the well's method, live and with outages."""
        s, label = self.s, c.effect
        core = [core_form(k, c, s.model) for k in classes]
        if core != classes:  # a hybrid: the effect as identified on its core
            classes = core
            c.spec = "+".join(effect_spec(k) for k in core)
            c.core_fixed = True
        c.live_run = self.run(
            f"{label} with {s.method}", classes, s.method, s.train, s.model, at=self.split_ts
        )
        if self.plan is not None:
            c.outage_run = self.run(
                f"{label} with outages",
                classes,
                s.method,
                s.train,
                s.model,
                self.plan,
                at=self.split_ts,
            )
        since = self._trial_since()
        if since is not None:  # as the service installs a change: fitted on all before it
            c.trial_run = self.run(
                f"{label} fitted {live.TRIAL_DAYS} days before the end",
                classes,
                s.method,
                s.train,
                s.model,
                at=since,
            )
        c.replayed = True

    def test_all(self) -> None:
        """Each candidate's paired tests against the baselines (``verdicts.test_candidate``)."""
        for c in self.results:
            self.test(c)

    def test(self, c: CandidateResult) -> None:
        """One candidate's paired tests against the baselines (``verdicts.test_candidate``)."""
        verdicts.test_candidate(
            c,
            self.comp,
            self.base,
            self.base_out,
            self.pool_wells,
            self.s.seed,
            replay_top=self.s.replay_top,
            trial_since=self._trial_since(),
        )

    def _plan_outages(self) -> None:
        """The outage windows after the split (None, with a note, when no well has any), and
        the baseline replayed with them."""
        s = self.s
        self.plan = None
        if s.replay_top > 0 and s.outage:
            self.plan = plan_outages(
                self.frame, s.outage, targets=s.targets, split=self.split_ts, seed=s.seed
            )
            if self.plan.windows.empty:
                self.notes.append(
                    f"No well has {s.outage} outage windows after the split (a well needs three "
                    "times the window's length of measurements): the outage protocol is left out."
                )
                self.plan = None
        self.base_out = None
        if s.replay_top > 0 and self.plan is None:
            self.bar.add(-1)
        if s.replay_top > 0 and self.plan is not None:
            self.base_out = self.run(
                f"baseline with {s.outage} outages",
                [],
                s.method,
                s.train,
                s.model,
                self.plan,
                at=self.split_ts,
            )

    def replay_shortlist(self) -> None:
        """The replay: the baseline with outages, the best ``replay_top`` candidates that
        lowered the fit-once error live and with outages, every test and the false-discovery
        control; whether any candidate is offered."""
        s = self.s
        self._plan_outages()
        top_n = max(s.replay_top, 0)
        # in BIC order, but the lead of the rivals first, and a candidate a rival of other
        # physics explains, or that the data cannot tell from a better one, after the rest
        fitted = [c for c in self.results if c.run is not None and c.delta_mape < 0]
        shortlist = sorted(
            fitted,
            key=lambda c: (
                c is not self.lead,
                c.explained_by is not None or rivals.second_to(c) is not None,
            ),
        )[:top_n]
        if self.n_replays:  # the runs counted at the start, made exact now
            self.bar.add(len(shortlist) * self._replay_runs() - 3 * top_n)
        if s.replay_top > 0:
            for c in shortlist:
                self.replay(c, self.classes_of[c.effect])
            self.test_all()
        self.suggest_slots = 1 if s.suggest and s.replay_top > 0 else 0
        if s.replay_top > 0:
            self.fdr = self._control_fdr(None)
            self.offered_any = any(verdicts.offer(c, None)[0] for c in self.results) or any(
                verdicts.offer(c, w)[0] for c in self.results for w in self.pool_wells
            )
        else:
            self.fdr = {}
            self.offered_any = any(c.material for c in self.results)

    def _control_fdr(self, suggestion: CandidateResult | None) -> dict[str, Any]:
        """Benjamini-Hochberg over every test so far (``verdicts.fdr``)."""
        return verdicts.fdr(self.results, suggestion, self.suggest_slots, len(self.pool_wells))

    def _drivers_to_correct(self) -> list[str]:
        """The drivers a correction is fitted for: with no candidate offered, those that beat
        chance and a correction can use, best first (at most :data:`SUGGEST_TOP`); none when
        the best driver does not."""
        top = self.top
        significant = (
            top is not None
            and top["p_value"] is not None
            and top["p_value"] < stats.ALPHA
            and top["score"] > 0
        )
        if not self.s.suggest or self.offered_any or not significant or top is None:
            return []
        if top["name"] not in SUGGEST_DRIVERS:
            return []
        return [
            d["name"]
            for d in self.eligible
            if d["p_value"] is not None
            and d["p_value"] < stats.ALPHA
            and d["score"] > 0
            and d["name"] in SUGGEST_DRIVERS
        ][:SUGGEST_TOP]

    def suggest_correction(self) -> None:
        """Fit a generic correction in the drivers that beat chance (when no candidate is
        offered), judge it, replay and test it; when it finds the driver, the library's
        physics behind that driver (:meth:`_physics_behind`)."""
        s = self.s
        chosen = self._drivers_to_correct()
        if chosen:
            rows = _derived(self.frame.iloc[self.train_rows])
            self.suggestion = _fit_suggestion(
                chosen,
                {d: np.asarray(stats.driver_values(rows, d), dtype=float) for d in chosen},
                self.run,
                _Comparison(self.cand_method, self.cand_train, self.comp_mape, self.comp),
                self.train_batch,
                self.bar,
            )
        suggestion = self.suggestion
        if suggestion is not None:
            _judge(suggestion.result, self.comp_mape, self.floor)
            if s.replay_top > 0:
                s_cls = [resolve_effect(suggestion.spec)]
                self.frame = _with_features(self.frame, s_cls)
                self.bar.add(self._replay_runs())
                self.replay(suggestion.result, s_cls)
                self.test(suggestion.result)
                self.fdr = self._control_fdr(suggestion.result)
        if suggestion is not None and s.replay_top > 0 and verdicts.driver_found(suggestion.result):
            self._physics_behind(suggestion)
        self.noise_test["confirmed"] = None if suggestion is None else suggestion.result.material

    def _physics_behind(self, suggestion: Suggestion) -> None:
        """The library effects acting through the correction's driver: fitted once, replayed,
        tested, and weighed against the correction (``verdicts.physics_behind_driver``)."""
        self.fit_once_more(self._kin(suggestion.driver))
        kin = _kin_shortlist(self.results, suggestion.driver, self.s.replay_top)
        self.bar.add(sum(not c.replayed for c in kin) * self._replay_runs())
        for c in [c for c in kin if not c.replayed]:
            self.replay(c, self.classes_of[c.effect])
        self.test_all()  # the new ones, and the new replays' live and outage tests
        verdicts.physics_behind_driver(
            kin, suggestion.result, suggestion.driver, suggestion.text, self.s.seed
        )
        self.fdr = self._control_fdr(suggestion.result)

    def fit_once_verdict(self) -> None:
        """The extended model's score, the protocol in words, and the verdict the fit-once
        evidence alone gives (format 2's rule)."""
        self.extended = None
        if self.ext_classes:
            ext = self.runs["__extended__"]
            self.extended = _score(
                "+".join(c.name for c in self.ext_classes),
                ext,
                self.ext_classes,
                self.base_mape,
                self.base,
                self.train_batch(ext),
            )
        self.scored_on = reference_bic(self.comp.predictions, 0)[1]
        n, day = len(self.comp_res), self.screen_ts.date()
        self.protocol = (
            f"fitted once on the measurements before {day} and scored on the "
            f"{n:,} measurements after it, never updated ({self.cand_method})"
            if self.cand_method == CANDIDATE_METHOD
            else f"learned with {self.cand_method} from {day} on, scored on the "
            f"{n:,} measurements after the split (each predicted before it is learned)"
        )
        self.verdict = verdicts.fit_once_verdict(
            self.comp_mape,
            self.results,
            self.top,
            self.drivers,
            self.suggestion,
            self.floor.get("mape"),
            self.protocol,
            self.scored_on,
            self.trend_share,
        )
        self.fit_once = dict(zip(("kind", "effect", "driver", "text"), self.verdict, strict=True))

    def _baseline_infos(self) -> None:
        """The live baseline (with the service's own recorded error) and the outage one."""
        s = self.s
        live_info = self.live_info = verdicts.baseline_info(self.base, self.pool_wells, s.well)
        live_info["protocol"] = (
            f"{verdicts.model_label(s.model, self.base_classes)} learning with {s.method} from "
            f"{self.split_ts.date()}, as the service runs it: every measurement after the "
            f"split predicted before it is learned ({live_info['n']:,} measurements)"
        )
        live_info["method"] = str(s.method)
        live_info.update(
            verdicts.service_error(self.frame, s.targets, self.split_ts, self.pool_wells, s.well)
        )
        if self.base_out is not None and self.plan is not None:
            self.outage_info = verdicts.outage_info(
                self.base_out, self.plan, self.pool_wells, s.well
            )

    def _each_well_verdict(self) -> None:
        """The field's verdict and each well's under the live and outage protocols, then
        the instrument check."""
        s, pool = self.s, self.pool_wells
        ctx = verdicts.VerdictContext(
            verdicts.model_label(s.model, self.base_classes),
            str(s.method),
            self.live_info,
            self.outage_info,
            self.floor.get("mape"),
            len(pool),
        )
        by_well = self.well_verdicts
        for w in [None, *pool] if len(pool) > 1 else [None]:
            prefer = None if w is None else by_well["field"]["effect"]
            # which form of a physics is offered: one within its bounds, the field's
            verdicts.weigh_forms(self.results, pool, w, prefer, seed=s.seed)
            by_well["field" if w is None else w] = verdicts.live_verdict(
                self.results, self.suggestion, w, ctx, self.fit_once, prefer
            )
        for key, v in by_well.items():  # "none lowers the error" is no verdict on the untested
            if v["kind"] == "noise":
                who = None if key == "field" else key
                found = verdicts.below_minimum(self.results, who)
                v["below_minimum"] = found
                v["text"] += verdicts.below_minimum_text(found)
                hint = verdicts.suggestive(self.results, who)
                v["suggestive"] = hint
                v["text"] += verdicts.suggestive_text(hint)
                v["text"] += verdicts.untested_text(self.skipped)
        if len(pool) == 1:
            by_well[pool[0]] = by_well["field"]
        if s.instrument:
            self.bar.start("instrument faults")
            verdicts.instrument_check(
                by_well,
                self.frame,
                self.results,
                self.suggestion,
                self.base,
                self.split_ts,
                self.notes,
            )
        for v in by_well.values():  # present on every verdict, empty when nothing is related
            for key in (*RIVAL_KEYS, "below_minimum", "suggestive", "gave_way"):
                v.setdefault(key, [])

    def live_verdicts(self) -> None:
        """With a replay: the verdict under the live and outage protocols (the focus well's,
        or the field's), its numbers, and the one change offered."""
        s = self.s
        if s.replay_top <= 0:
            return
        self._baseline_infos()
        self._each_well_verdict()
        picked = self.well_verdicts[s.well if s.well is not None else "field"]
        kind, effect_name, driver_name, text = (
            picked[k] for k in ("kind", "effect", "driver", "text")
        )
        self.detail = {
            k: v for k, v in picked.items() if k not in ("kind", "effect", "driver", "text")
        }
        # one change is offered: the verdict's (the fit-once evidence names the physics; a
        # flexible candidate that lets the learner follow the same misfit also lowers the
        # replayed error, and is shown, not offered)
        suggestion = self.suggestion
        offered_effect = (
            effect_name
            if kind == "effect"
            else (suggestion.result.effect if kind == "driver" and suggestion is not None else None)
        )
        verdicts.set_offers(
            [*self.results, *([suggestion.result] if suggestion else [])], s.well, offered_effect
        )
        pool = self.pool_wells
        if s.well is not None and len(pool) > 1:
            field_v = self.well_verdicts["field"]
            if field_v["kind"] != kind or field_v["effect"] != effect_name:
                text += f" The field's verdict over its {len(pool)} wells: {field_v['text']}"
        self.verdict = (kind, effect_name, driver_name, text)

    def _pool(self) -> dict[str, Any]:
        """The wells diagnosed together, the focus, and a note when there is a pool."""
        well, pool = self.s.well, self.pool_wells
        return {
            "wells": pool,
            "focus": well,
            "note": (
                f"the diagnosis of {well} takes the {len(pool) - 1} other well(s) of the "
                "data with the same model as its pool: the field's evidence beside the well's"
                if well is not None and len(pool) > 1
                else None
            ),
        }

    def diagnosis(self, started: float) -> Diagnosis:
        """Close the progress and gather what was found (``started``: perf_counter at the
        start, for the runtime)."""
        s = self.s
        kind, effect_name, driver_name, text = self.verdict
        self.bar.finish(f"verdict: {kind}")
        return Diagnosis(
            s.model,
            str(s.method),
            s.targets,
            self.split_ts,
            self.base,
            self.base_mape,
            self.base_bic,
            self.res,
            self.drivers,
            self.regions,
            self.results,
            self.findings,
            text,
            self.extended,
            time.perf_counter() - started,
            self.cand_method,
            self.comp_mape,
            self.scored_on,
            kind,
            effect_name,
            driver_name,
            self.suggestion,
            self.floor,
            self.noise_test,
            self.skipped,
            self.comp_res,
            self.protocol,
            self.notes,
            s.source or {"kind": "frame"},
            [effect_spec(c) for c in self.base_classes],
            self.live_info,
            self.outage_info,
            self.fdr,
            self._pool(),
            self.well_verdicts,
            self.fit_once,
            self.screen,
            self.detail,
        )


def core_form(cls: type[Effect], c: CandidateResult, model: str) -> type[Effect]:
    """The form of candidate ``c`` (class ``cls``) replayed on ``model``: on a hybrid
    (:data:`HYBRIDS`), an effect acting through a variable its network sees
    (:data:`NETWORK_INPUTS`) is fixed at its values identified on the mechanistic core (each
    parameter's precision-weighted mean over the wells, shared by every well:
    :func:`vfm_core.effects.fixed_effect`), the network learning what is left; otherwise, or
    without per-well values, ``cls`` itself (learned with the model).

    Why: learned together with the network, such an effect is confounded with it (the
    network is a function of the same variable), so its replay measures what the network
    already carries, not what the physics adds; the generic correction it is weighed
    against is replayed with its coefficient fixed the same way (:func:`_fit_shared`).
    Replaying both as identified on the core compares like with like (a valve field,
    Sachdeva seed 66, ``ham`` + ``ol``: the equal-percentage valve learned with the network
    -0.02 points live, fixed at the core's weight -0.34; the choke correction learned per
    well -0.02, fixed -0.32)."""
    if model not in HYBRIDS or acts_through(cls.name) not in NETWORK_INPUTS or not cls.parameters:
        return cls
    values: dict[str, float] = {}
    for pname, prior in cls.parameters.items():
        entry = c.parameters.get(f"{cls.name}.{pname}") or {}
        per_well = entry.get("per_well")
        if not per_well:
            return cls
        wells = sorted(per_well)
        sds = entry.get("per_well_sd") or {}
        v = np.array([per_well[w] for w in wells], dtype=float)
        sd = np.array([sds.get(w, np.nan) for w in wells], dtype=float)
        mean = _shared_value(v, np.where(np.isfinite(sd), sd, np.nan))[0]
        if not math.isfinite(mean):
            return cls
        values[pname] = float(np.clip(mean, prior.low, prior.high))
    return fixed_effect(cls, values)


def _derived(frame: pd.DataFrame) -> pd.DataFrame:
    """Observation rows with the pressure ratio (the features are already columns)."""
    return frame.assign(p_ratio=frame["p_down"] / frame["p_up"])


def _p_cr(run: RunResult) -> dict[str, float] | None:
    m = run.final_model
    if m is None:
        return None
    phys = m.physical_parameters()
    if "p_cr" not in phys:
        return None
    return {w: float(v) for w, v in zip(m.wells, phys["p_cr"], strict=True)}


def _residuals_like(res: pd.DataFrame, run: RunResult) -> pd.DataFrame:
    out = res.copy()
    out["predicted"] = run.predictions["predicted"].to_numpy(dtype=float)
    out["r"] = (out["measured"] - out["predicted"]) / out["measured"]
    return out


def _judge(c: CandidateResult, base_mape: float, floor: dict[str, Any]) -> None:
    """Set a candidate's share of the error above the floor (``floor``: the noise floor's
    record, MAPE in %), and whether it is material; the share is no evidence when the floor
    is not ``trusted`` (:func:`_trust_floor`)."""
    c.share_above_floor = _share(base_mape, c.mape, floor.get("mape"))
    share = c.share_above_floor if floor.get("trusted", True) else float("nan")
    c.material = is_material(c.delta_mape, base_mape, c.delta_bic, c.delta_bic_all, share)


def _trust_floor(floor: dict[str, Any], results: Sequence[CandidateResult]) -> bool:
    """Whether the noise floor's estimate is a floor of these data: no candidate's fit-once
    MAPE (%) went below it. No model goes below a true floor; when one does, the estimate
    (meter noise from consecutive readings, itself uncertain) is not one here, and the error
    above it is no measure of what is left to explain, for any candidate. Sets
    ``floor["trusted"]`` and ``floor["below"]`` (the candidates under it) and returns the
    first."""
    mape = floor.get("mape")
    below = (
        []
        if mape is None
        else [c.effect for c in results if math.isfinite(c.mape) and c.mape < mape]
    )
    floor["below"] = below
    floor["trusted"] = not below
    return not below


def _variant_source(results: Sequence[CandidateResult], base_mape: float) -> CandidateResult | None:
    """The candidate whose :data:`VARIANTS` are tried (``results`` best first): the best
    one with variants that is material, or that lowers the MAPE by a material amount and
    the BIC over every measurement by more than :data:`MATERIAL_BIC`, failing only the BIC
    on the reference. That is a flexible form (a learned curve per well: the valve's 6
    slopes a well) paying for its parameters on few well tests; a few-parameter form of the
    same physics is then judged on its own."""
    for c in results:
        if c.effect in VARIANTS and (
            c.material
            or (
                c.delta_bic_all < -MATERIAL_BIC
                and c.delta_mape <= -max(MATERIAL_MAPE_ABS, MATERIAL_MAPE_REL * base_mape)
            )
        ):
            return c
    return None


def _share(base: float, with_: float, floor: float | None) -> float:
    """Share of the error above the floor that ``with_`` removes (nan without a floor)."""
    if floor is None or not math.isfinite(floor) or base - floor <= 1e-9:
        return float("nan")
    return (base - with_) / (base - floor)


# --- the suggested correction: fitting it ---------------------------------------------------
def _kin_classes(
    classes: Sequence[type[Effect]],
    results: Sequence[CandidateResult],
    in_model: set[str],
    driver: str,
    train: pd.DataFrame,
) -> list[tuple[type[Effect], str | None]]:
    """The library effects not yet fitted that act through ``driver``, with their other
    forms (:data:`VARIANTS`), as ``(class, variant_of)``; a valve curve skipped because the
    choke hardly moved is in (a material correction in the opening fitted on the same rows
    shows that their span informs a curve in it); other reasons still skip."""
    out: list[tuple[type[Effect], str | None]] = []
    tried = {c.effect for c in results} | in_model
    for cls in classes:
        if cls.name in in_model or acts_through(cls.name) != driver:
            continue
        for name in [cls.name, *VARIANTS.get(cls.name, ())]:
            if name in tried or name not in EFFECTS:
                continue
            k_cls = resolve_effect(name)
            if _offer_reason(k_cls, train, min_choke_span=0.0) is None:
                out.append((k_cls, None if name == cls.name else cls.name))
                tried = tried | {name}
    return out


def _kin_shortlist(
    results: Sequence[CandidateResult], driver: str, n: int
) -> list[CandidateResult]:
    """The best ``n`` candidates by the fit-once BIC (``results`` are in that order) that act
    through ``driver`` and lowered the fit-once error: the ones replayed beside its
    correction."""
    kin = [c for c in results if acts_through(c.effect) == driver and c.run is not None]
    return [c for c in kin if c.delta_mape < 0][: max(n, 0)]


def _per_well_values(
    cand: CandidateResult, cls: type[Effect], model: ChokeModel
) -> tuple[dict[str, tuple[float, float]], dict[str, tuple[float, float]]]:
    """Per parameter: (field median, median sd) and the shared estimate (mean, sd)."""
    ready = model.ready.numpy()
    median: dict[str, tuple[float, float]] = {}
    shared: dict[str, tuple[float, float]] = {}
    for pname in cls.parameters:
        entry = cand.parameters[f"suggest.{pname}"]
        v = np.array([entry["per_well"][w] for w in model.wells])[ready]
        s = np.array([entry["per_well_sd"].get(w, np.nan) for w in model.wells])[ready]
        shared[pname] = _shared_value(v, s)
        sd = entry["sd"]
        median[pname] = (float(entry["value"]), float(sd) if sd is not None else float("nan"))
    return median, shared


@dataclass(frozen=True)
class _Comparison:
    """The fit-once comparison a correction is fitted under: its method and train settings,
    and the baseline it is scored against (its run and MAPE, %)."""

    how: str
    settings: TrainSettings
    base_mape: float
    base: RunResult


#: one correction tried: (its result, shared by every well, its class, its values per
#: parameter (value, sd), the per-well spec it came from)
_Tried = tuple[CandidateResult, bool, type[Effect], dict[str, tuple[float, float]], str]


def _correction_heads(driver: str, x: np.ndarray) -> dict[str, str]:
    """The per-well correction specs tried for ``driver`` by form: the season for the day of
    the year, else linear and log-linear around the training values ``x``."""
    spec = SUGGEST_DRIVERS[driver]
    if driver == "day_of_year":
        return {"season": f"suggest:driver={driver}:form=season"}
    x0 = _x0(x, spec.scale)
    return {
        f: f"suggest:driver={driver}:form={f}:x0={x0:g}:scale={spec.scale:g}"
        for f in ("linear", "log")
    }


def _fit_per_well(
    driver: str,
    heads: dict[str, str],
    run: Callable[..., RunResult],
    comp: _Comparison,
    train_batch: Callable[[RunResult], Batch | None],
) -> list[tuple[_Tried, dict[str, tuple[float, float]]]]:
    """Fit each form of the correction per well: each as tried (with each parameter's
    field median), and each parameter's shared (precision-weighted) estimate."""
    fits: list[tuple[_Tried, dict[str, tuple[float, float]]]] = []
    for form, head in heads.items():
        cls = resolve_effect(head)
        r_ = run(f"suggest {driver} {form} per well", [cls], comp.how, comp.settings)
        cand = _score(f"suggest:{driver}", r_, [cls], comp.base_mape, comp.base, train_batch(r_))
        cand.driver = driver
        assert r_.final_model is not None
        median, shared = _per_well_values(cand, cls, r_.final_model)
        fits.append(((cand, False, cls, median, head), shared))
    return fits


def _fit_shared(
    driver: str,
    per_well: _Tried,
    shared: dict[str, tuple[float, float]],
    run: Callable[..., RunResult],
    comp: _Comparison,
) -> _Tried:
    """A per-well form with each coefficient fixed at its ``shared`` estimate (one value for
    every well), fitted and scored like a candidate."""
    cls, head = per_well[2], per_well[4]
    fixed_spec = head + "".join(f":{k}={v:.6g}" for k, (v, _) in shared.items())
    fixed_cls = resolve_effect(fixed_spec)
    r_s = run(f"suggest {driver} {cls.form} shared", [fixed_cls], comp.how, comp.settings)  # type: ignore[attr-defined]
    one = _score(
        f"suggest:{driver}",
        r_s,
        [fixed_cls],
        comp.base_mape,
        comp.base,
        None,
        k_override=len(shared),
    )
    one.driver = driver
    one.parameters = {
        f"suggest.{pname}": {
            "value": mean,
            "sd": sd,
            "unit": cls.parameters[pname].unit,
            "meaning": cls.parameters[pname].meaning,
            "shared": True,
        }
        for pname, (mean, sd) in shared.items()
    }
    one.meaning = fixed_cls().describe({})
    return (one, True, fixed_cls, shared, head)


def _variant_rows(tried: Sequence[_Tried]) -> list[dict[str, Any]]:
    """Every correction tried, one row each (the suggestion's ``variants``)."""
    return [
        {
            "driver": c_cls.driver,  # type: ignore[attr-defined]
            "form": c_cls.form,  # type: ignore[attr-defined]
            "shared": is_shared,
            "n_parameters": cand.n_parameters,
            "mape": cand.mape,
            "delta_bic": cand.delta_bic,
            "delta_bic_all": cand.delta_bic_all,
            "effects": cand.spec,
        }
        for cand, is_shared, c_cls, _, _ in tried
    ]


def _fit_suggestion(
    drivers: Sequence[str],
    x_train: dict[str, np.ndarray],
    run: Callable[..., RunResult],
    comp: _Comparison,
    train_batch: Callable[[RunResult], Batch | None],
    bar: _Progress,
) -> Suggestion:
    """Fit the generic correction for each driver under the comparison protocol and keep the
    one with the lowest BIC: per well, linear and log-linear (the season for the day of the
    year); then the better form with one coefficient shared by every well (the
    precision-weighted mean of the wells' values, fixed)."""
    tried: list[_Tried] = []
    for driver in drivers:
        heads = _correction_heads(driver, x_train[driver])
        bar.add(len(heads) + 1)
        fits = _fit_per_well(driver, heads, run, comp, train_batch)
        tried += [one for one, _ in fits]
        best, shared = min(fits, key=lambda f: _order(f[0][0].delta_bic))
        tried.append(_fit_shared(driver, best, shared, run, comp))
    chosen, is_shared, cls, values, head = min(tried, key=lambda t: _order(t[0].delta_bic))
    params = {key.split(".", 1)[1]: dict(entry) for key, entry in chosen.parameters.items()}
    return Suggestion(
        driver=cls.driver,  # type: ignore[attr-defined]
        form=cls.form,  # type: ignore[attr-defined]
        shared=is_shared,
        spec=chosen.spec,
        text=_form_text(cls, values, is_shared),
        parameters=params,
        result=chosen,
        variants=_variant_rows(tried),
        per_well_spec=head,
        code=_snippet(cls, values),
    )


def _order(value: float) -> float:
    return value if math.isfinite(value) else math.inf


# --- command line ---------------------------------------------------------------------------
def _split_list(values: Sequence[str] | None) -> list[str]:
    """Comma-separated values of a repeatable option, as one list."""
    return [x.strip() for v in values or [] for x in v.split(",") if x.strip()]


@dataclass
class _Inputs:
    """What ``vfm diagnose`` diagnoses beside the observations, from its arguments (and a
    store's records): the model, its effects and method, the candidates and the splits."""

    model: str
    method: str | None
    candidates: list[str]
    effects: list[str]
    base_effects: list[str]
    split: str | pd.Timestamp | None
    screen_split: str | None = None


def _cmd_diagnose(args: argparse.Namespace) -> int:
    if (args.data is None) == (args.store is None):
        raise ConfigError(
            "Give either an observation file (DATA) or --store PATH, not both or neither."
        )
    candidates = _split_list(args.candidates) or list(DEFAULT_CANDIDATES)
    if candidates == ["none"]:
        candidates = []
    effects = _split_list(args.effects)
    given_base = _split_list(args.base_effects) if args.base_effects is not None else None
    base_effects = [] if given_base == ["none"] else list(given_base or [])
    # resolve names before loading data, so a typo fails at once
    resolve_effects(effects)
    resolve_effects(base_effects)
    for c in candidates:
        resolve_effect(c)
    got = _Inputs(args.model or "mm", args.method, candidates, effects, base_effects, args.split)
    if args.store is not None:
        frame, source = _read_store(args, got, given_base)
    elif args.history is not None:
        raise ConfigError("--history goes with --store (the history a service was fitted on).")
    else:
        frame, source = _read_file(args)
    if got.method is None:
        got.method = "ol"
        print("Replaying with ol (give --method for the well's own learning method).")
    diag = run_diagnosis(
        frame,
        got.model,
        method=got.method,
        candidate_method=args.candidate_method,
        targets=args.targets,
        split=got.split,
        screen_split=got.screen_split,
        candidates=got.candidates,
        effects=got.effects,
        seed=args.seed,
        progress=not args.quiet,
        source=source,
        base_effects=got.base_effects,
        replay_top=args.replay_top,
        outage=None if args.outage == "none" else args.outage,
        well=args.well,
        screen_model=args.screen_model,
    )
    written = write_diagnosis(diag, args.out, report=not args.no_report)
    print(format_summary(diag))
    print(f"Diagnosis took {diag.runtime_s:.1f} s. Wrote {', '.join(str(p) for p in written)}.")
    return 0


def _read_store(
    args: argparse.Namespace, got: _Inputs, given_base: list[str] | None
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """``--store``: a service's stored observations (the well's pool, or the well alone) and
    where they came from; into ``got`` the model and method the service runs, and with
    ``--history`` (the history in front) the splits."""
    from vfm_core.observations import load_observations

    frame = load_source("store", args.store, None if args.no_pool else args.well)
    source = {"kind": "store", "path": str(args.store), "well": args.well}
    if args.well is not None and not args.no_pool:
        frame, note = pool_frame(frame, args.well)
        print(note)
    print(f"{args.store}: {len(frame):,} rows from the service's store.")
    got.model, got.base_effects = store_model(frame, args.model, given_base, got.base_effects)
    if got.method is None:
        got.method = stored_method(frame, args.well)
    if args.history is not None:
        if args.history_until is None:
            raise ConfigError(
                "--history needs --history-until: the time the service's fit ended "
                "(its model.history_until)."
            )
        frame, history_split, note = with_history(
            frame, load_observations(args.history).frame, args.history_until
        )
        print(note)
        got.split = args.split or history_split
        got.screen_split = "auto"
        source.update(history=str(args.history), history_until=str(history_split), note=note)
    return frame, source


def _read_file(args: argparse.Namespace) -> tuple[pd.DataFrame, dict[str, Any]]:
    """An observation file (every well, or with ``--well --no-pool`` that well's rows
    alone) and where it came from."""
    from vfm_core.observations import load_observations

    loaded = load_observations(args.data)
    print(loaded.summary())
    frame = loaded.frame
    source = {"kind": "file", "path": str(args.data), "well": args.well}
    if args.well is not None:
        if not (frame[WELL].astype(str) == args.well).any():
            raise DataError(f"The file {args.data} has no rows of well {args.well}.")
        if args.no_pool:
            frame = frame[frame[WELL].astype(str) == args.well].reset_index(drop=True)
    return frame, source


def register(subparsers: Any) -> None:
    """Add ``vfm diagnose`` to the CLI (called from ``vfm_core.cli``)."""
    p = subparsers.add_parser(
        "diagnose",
        help="find where a model fails and which physical effect is missing",
        description="Fit the model once before the split and score it after (the evidence); try "
        "each candidate effect under the same protocol; rank what the residual depends on beyond "
        "time and well; suggest a correction for an effect outside the library; replay the "
        "well's learning method with the best candidates (live and with outages) and test them "
        "with false-discovery control; give one verdict.",
    )
    _source_arguments(p)
    _protocol_arguments(p)
    _candidate_arguments(p)
    p.set_defaults(handler=_cmd_diagnose)


def _source_arguments(p: argparse.ArgumentParser) -> None:
    """The data (a file, or a service's store with its history), the well and the output."""
    p.add_argument("data", nargs="?", default=None, help="observation file (.parquet or .csv)")
    p.add_argument(
        "--store",
        default=None,
        metavar="PATH",
        help="a service's SQLite store instead of a file (read through the vfm.sources entry point)",
    )
    p.add_argument(
        "--history",
        default=None,
        metavar="FILE",
        help="with --store: the observation file the service was fitted on (its model.history); "
        "joined in front of the store so that the replay starts where the service started",
    )
    p.add_argument(
        "--history-until",
        default=None,
        metavar="DATE",
        help="with --history: the end of the service's fit (its model.history_until); the split",
    )
    p.add_argument("--well", default=None, help="diagnose this well only")
    p.add_argument("--out", required=True, help="output folder (diagnosis.json, report.html)")


def _protocol_arguments(p: argparse.ArgumentParser) -> None:
    """The model and method replayed, the replay's size, the outage window, the pool, and
    the model and protocol of the fit-once evidence."""
    p.add_argument(
        "--model",
        default=None,
        choices=list(EFFECT_MODELS),
        help="base model (default mm; with --store, the model the service runs when it is "
        "one of these)",
    )
    p.add_argument(
        "--method",
        default=None,
        help="the well's learning method, replayed for the live and outage errors and where "
        "it fails: ol, pbl:<period>, bayes, ... (default: with --store the method the service "
        "runs for the well, else ol)",
    )
    p.add_argument(
        "--replay-top",
        type=int,
        default=REPLAY_TOP,
        help=f"candidates replayed under --method, live and with outages (default {REPLAY_TOP}; "
        "0: the fit-once verdict only, as format 2)",
    )
    p.add_argument(
        "--outage",
        default=OUTAGE,
        help=f"the outage protocol's window (default {OUTAGE}; 'none' to leave it out)",
    )
    p.add_argument(
        "--no-pool",
        action="store_true",
        help="with --well: diagnose that well's data alone (default: beside the other wells "
        "that run the same model, the field's evidence beside the well's)",
    )
    p.add_argument(
        "--screen-model",
        default=None,
        choices=list(EFFECT_MODELS),
        help="the model the candidates are identified on, fit once (default: --model, or mm "
        "for ham and hem, whose network absorbs a missing effect)",
    )
    p.add_argument(
        "--candidate-method",
        default=CANDIDATE_METHOD,
        help=f"protocol of every comparison (default {CANDIDATE_METHOD}: fit once "
        "before the split, score the rest; online learning would hide a missing effect)",
    )


def _candidate_arguments(p: argparse.ArgumentParser) -> None:
    """The target case, the split, the candidates and effects, the seed and the outputs."""
    p.add_argument(
        "--targets", default="all", choices=["all", "well_test"], help="target case (default all)"
    )
    p.add_argument(
        "--split",
        default=None,
        help="first day scored (default as vfm evaluate, or where 60 %% of the data lie before "
        "it when that leaves too little on one side)",
    )
    p.add_argument(
        "--candidates",
        action="append",
        help="comma-separated candidate effects (default: "
        + ",".join(DEFAULT_CANDIDATES)
        + "; 'none' for none); registry names or module:Class",
    )
    p.add_argument(
        "--effects",
        action="append",
        help="effects to add to the model and compare side by side, e.g. erosion,real_gas, "
        "suggest:driver=t_up or mypkg.effects:Scale",
    )
    p.add_argument(
        "--base-effects",
        action="append",
        help="effects the model already has (e.g. the one an earlier diagnosis found and you "
        "added): every run has them, and the diagnosis looks for what is missing beyond them; "
        "with --store, default the effects the service's model has ('none' for none)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-report", action="store_true", help="skip report.html")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


if __name__ == "__main__":  # pragma: no cover - ``python -m vfm_core.jobs.diagnose``
    import sys

    from vfm_core.errors import VFMError

    _parser = argparse.ArgumentParser(prog="python -m vfm_core.jobs.diagnose")
    _sub = _parser.add_subparsers(dest="command", required=True)
    register(_sub)
    _args = _parser.parse_args(["diagnose", *sys.argv[1:]])
    try:
        sys.exit(_args.handler(_args))
    except VFMError as _exc:
        print(f"vfm diagnose: error: {_exc}", file=sys.stderr)
        sys.exit(2)
