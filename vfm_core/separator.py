"""Learning from a separator's total, and allocating it back to the wells.

A separator reading y (Sm3/h) at time t measures the sum of the rates of the wells flowing
into it (see :mod:`vfm_core.separator_format` for which sample of each well counts, and
shut-in wells). For the ``bayes`` method (:mod:`vfm_core.learning.bayes`) it is one
measurement of that sum, in log space like the single-well filter:

    log y = log sum_i h_i(x_i; theta_i) + e,   e ~ N(0, R),

linearised at the current parameters: the row G = (w_1 H_1, ..., w_M H_M) stacks the wells'
sensitivities H_i = d log h_i / d theta_i side by side, weighted by their shares
w_i = h_i / sum h. One extended Kalman step over the stacked state (innovation variance
S = G C G^T + R, gain K = C G^T / S, C the joint covariance) moves every member well at once
and correlates them: after it, the wells' errors are negatively correlated (the sum is known
better than any part).

* **Cross-covariances** (``cross=True``, the default) are kept: :class:`SeparatorLearner`
  holds each separator's joint covariance; its diagonal blocks are the single-well filter's
  P (grown by each well's drift), its off-diagonal blocks are kept here. A well test still
  updates its well through the single-well filter (with its Huber weight, gate and noise
  adaptation); the learner then carries that update to the other wells through the kept
  cross-covariances (the exact Gaussian conditioning: with P and P' the well's covariance
  before and after, theta_j += C_ji P^-1 dtheta, C_ij <- P' P^-1 C_ij,
  C_jk -= C_ji P^-1 (P - P') P^-1 C_ik). ``cross=False`` drops the cross-covariances after
  every update (a block-diagonal approximation: each well's marginal is right after the
  update, what the wells' correlation would carry later is lost); its cost in accuracy is
  measured by ``benchmarks/bench_separator.py``.
* **Noise.** R = s^2 + sum_i w_i^2 tau_i^2: the separator meter's relative noise s (given,
  default 1.5 %) and each well's misfit, tau_i = the well test noise the filter estimated for
  the well (the scatter of its tests about its model), since the sum carries every member's
  model error. An innovation beyond ``huber`` sd is down-weighted, beyond ``gate`` refused
  (counted), as in the single-well filter.
* **Cost.** The update is rank one: with cross-covariances O((M D)^2) for M wells of D
  parameters; block-diagonal O(M D^2).

**Allocation** (:class:`Allocation`), for each reading: the wells' true log rates have the
prior Gaussian N(l, Sigma); conditioned on the reading (linearised as above) their posterior
mean gives rates that are then scaled by a common factor to sum to the measured total
exactly (the booked allocation); the 90 % interval of each is its rate times
exp(+-1.645 sd), sd the booked rate's sd in log space. A shut-in well is allocated 0.
Sigma and sd are calibrated from what the allocator sees (:func:`calibrated_prior`):

* **The wells' variance factor.** H_i C_ii H_i^T + tau_i^2 is the variance the filter states
  for the log error of well i's next well test, and the filter learns how far off that is:
  c_i^2, the scale of the posterior InvGamma((nu0 + n) / 2, (nu0 + sum z^2) / 2) of the
  factor on it from the standardised errors z of its forecasts of the well's past well
  tests (``BayesianFilter._learn_calibration``, prior nu0 = ``cal_prior`` = 2 errors at
  z^2 = 1), c_i^2 = (nu0 + sum z^2) / (nu0 + n), read from the filter's statistics, not
  learned again. Each well's prior is pooled over the separator's other members (the
  empirical Bayes prior of ``cal_pool``, :func:`~vfm_core.learning.bayes.pooled_factor`):
  they share a model and a drift allowance, and a well's own 8-15 well tests a year leave
  its factor near the stated prior, c^2 = 1, which is far off when the filter's tau_i is
  (e.g. a fit that could not follow a fast drift booked it as test noise: tau_i 3-6 %
  where the tests scatter by 1 %). The wells' parameter covariance is scaled by it:
  H_i C_ij H_j^T c_i c_j.
* **A well test is not the truth.** The calibrated c_i^2 (H_i C_ii H_i^T + tau_i^2) is the
  variance of a well test's error; the true rate has no test meter noise in it, so each
  well's misfit (beyond its parameters) is what is left of c_i^2 tau_i^2 after the test
  meter's own variance: m_i = max(c_i^2 tau_i^2 - s_t^2, 0), s_t the filter's fixed
  well-test noise if it was given one, else :data:`NOISE_DEFAULTS` (1 %, a test separator's
  usual noise). So Sigma_ij = c_i c_j H_i C_ij H_j^T + m_i [i = j].
* **The booking.** The booked rates are scaled to the measured total, so each carries part
  of the separator meter's error: for the linearised model (log rates l ~ N(mu, Sigma),
  reading y = w . l + e, e ~ N(0, s^2), S = w Sigma w^T + s^2), the booked log rate is
  mu + (Sigma w^T + s^2 1) (y - w . mu) / S, whose error has the variance
  Sigma_ii - (Sigma w^T)_i^2 / S + s^4 / S: the posterior variance plus s^4 / S.

The learning step is not changed by the calibration (it uses tau_i, as above).

``ol`` and ``pbl`` ignore separator readings (see :func:`check_method`): their fits are
per-well objectives, solved for all wells at once but independently (the vectorised
training and the service's one-method-per-well design rest on it); a shared objective term
would couple every member's fit and is not implemented.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
import torch

from vfm_core.data import DTYPE, Batch, make_batch, target_mask
from vfm_core.errors import ConfigError, DataError
from vfm_core.learning import DEFAULT_TRAIN, TrainSettings, parse_method
from vfm_core.learning.bayes import NOISE_DEFAULTS, Z90, BayesianFilter, pooled_factor
from vfm_core.learning.memory import FrameMemory
from vfm_core.learning.method import NEVER
from vfm_core.models import make_model
from vfm_core.schema import INPUT_COLUMNS, TARGET, TIME, WELL, WELL_TEST
from vfm_core.separator_format import (
    SAMPLE_WINDOW,
    SEPARATOR_COLUMN,
    SeparatorData,
    member_samples,
)

__all__ = [
    "SEPARATOR_NOISE",
    "ALLOCATION_COLUMNS",
    "sum_update",
    "calibrated_prior",
    "booked_allocation",
    "well_test_factor",
    "Allocation",
    "SeparatorLearner",
    "WellFilters",
    "WellTestMark",
    "SeparatorRun",
    "check_method",
    "run_separator",
]

#: relative noise (sd) of a separator's total when none is given: a separator meter's 1-2 %
SEPARATOR_NOISE = 0.015
#: the columns of ``allocation.parquet`` (rates in Sm3/h)
ALLOCATION_COLUMNS = (
    "time",
    "separator",
    "well",
    "q_alloc",
    "lo90",
    "hi90",
    "q_pred",
    "residual",
)


def sum_update(
    mean: torch.Tensor, cov: torch.Tensor, g: torch.Tensor, innovation: float, noise_var: float
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """One Kalman step for a scalar measurement z = g . x + e, e ~ N(0, ``noise_var``),
    given x ~ N(``mean`` [n], ``cov`` [n, n]) and the innovation z - g . mean.

    Returns the posterior mean, covariance (symmetric; C - S K K^T, which equals the Joseph
    form for this gain) and the innovation variance S = g C g + R. Rank one: O(n^2)."""
    c = cov @ g
    s = float(g @ c) + noise_var
    k = c / s
    new_cov = cov - s * torch.outer(k, k)
    return mean + k * innovation, 0.5 * (new_cov + new_cov.T), s


def well_test_factor(
    filt: BayesianFilter | WellFilters, wells: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each well's well-test variance factor c^2 [W] as the ``bayes`` filter learned it (the
    scale (nu0 + sum z^2) / (nu0 + n) of its InvGamma posterior; 1 with no error yet, or with
    ``cal_prior`` = 0) and the well-test meter's relative noise s_t [W] (the filter's fixed
    ``noise_well_test`` if given, else :data:`NOISE_DEFAULTS`).

    ``wells`` (indices [M] of one separator's members): their factors [M], each with its
    prior pooled over the other members' errors (:func:`pooled_factor`: the factor a filter
    over the members alone would learn with ``cal_pool``), and their s_t [M]. The members
    share a model and a drift allowance, so their factors are alike, and a well's own
    handful of well tests leaves its factor near the stated prior (c^2 = 1). Left as the
    filter learned them when it pools already (``cal_pool``: over the field), learns no
    factor (``cal_prior`` = 0), the members' filters differ in ``cal_prior``, or there is
    one member."""
    factor, meter = _own_factor(filt)
    if wells is None:
        return factor, meter
    factor, meter = factor[wells], meter[wells]
    filters = filt.filters if isinstance(filt, WellFilters) else [filt]
    nu0 = {float(f.cal_prior) for f in filters}
    if len(wells) < 2 or len(nu0) != 1 or min(nu0) <= 0 or any(f.cal_pool for f in filters):
        return factor, meter
    errors = torch.cat([f.well_test_errors() for f in filters])[wells]
    return torch.from_numpy(pooled_factor(errors.numpy(), nu0.pop())).to(DTYPE), meter


def _own_factor(filt: BayesianFilter | WellFilters) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`well_test_factor` of every well of ``filt``, each its filter's own."""
    if isinstance(filt, WellFilters):
        parts = [_own_factor(f) for f in filt.filters]
        return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    n = len(filt.model.wells)
    meter = filt.noise[1] if filt.noise[1] is not None else NOISE_DEFAULTS[1]
    noise = torch.full((n,), float(meter), dtype=DTYPE)
    return filt.well_test_factor(), noise


def booked_allocation(
    log_rate: torch.Tensor,
    flowing: torch.Tensor,
    sigma: torch.Tensor,
    s2: float,
    measured: float,
    *,
    booking: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The booked allocation of a reading ``measured`` (Sm3/h, relative noise variance
    ``s2``) to wells whose log rates (of Sm3/h) have the prior N(``log_rate`` [M], ``sigma``
    [M, M]) (``flowing`` [M]: the others get 0): the posterior mean given the reading
    (linearised at the prior mean, shares w), scaled to sum to the reading exactly, and the
    sd [M] of each booked log rate's error: the posterior variance plus s2^2 / S, with
    S = w sigma w^T + s2 (the meter's error the booking puts into every rate; ``booking``
    False: the posterior variance alone, as before the calibration)."""
    q = torch.where(flowing, log_rate.exp(), torch.zeros_like(log_rate))
    share = q / float(q.sum())
    r = math.log(measured) - math.log(float(q.sum()))
    s_alloc = float(share @ sigma @ share) + s2
    post_mean = torch.where(flowing, log_rate + (sigma @ share) * r / s_alloc, log_rate)
    post_var = torch.diagonal(sigma - torch.outer(sigma @ share, sigma @ share) / s_alloc)
    rates = torch.where(flowing, post_mean.exp(), torch.zeros_like(log_rate))
    booked = rates * (measured / float(rates.sum()))
    if booking:
        post_var = post_var + s2**2 / s_alloc
    return booked, post_var.clamp(min=0).sqrt()


def calibrated_prior(
    sigma_params: torch.Tensor,
    tau2: torch.Tensor,
    factor: torch.Tensor,
    meter: torch.Tensor,
) -> torch.Tensor:
    """The wells' prior covariance of their true log rates [M, M] for an allocation (see the
    module docstring): ``sigma_params`` [M, M] = H_i C_ij H_j^T (the parameters' part),
    ``tau2`` [M] the wells' well-test noise variance (0 for a shut-in well), ``factor`` [M]
    their well-test variance factor c^2, ``meter`` [M] the well-test meter's relative noise.
    c_i c_j H_i C_ij H_j^T + max(c_i^2 tau_i^2 - s_t^2, 0) [i = j]."""
    c = factor.clamp(min=0).sqrt()
    misfit = (factor * tau2 - meter**2).clamp(min=0)
    misfit = torch.where(tau2 > 0, misfit, torch.zeros_like(misfit))
    return sigma_params * torch.outer(c, c) + torch.diag(misfit)


@dataclass
class Allocation:
    """One reading split to its wells: ``wells`` (names), ``q_alloc`` (Sm3/h, summing to
    ``measured``), ``lo90``/``hi90`` (Sm3/h), ``q_pred`` (the wells' predictions before the
    reading, Sm3/h, 0 for a shut-in well) and the reading's ``residual`` (measured total
    minus the sum of the predictions, Sm3/h)."""

    time: pd.Timestamp
    separator: str
    wells: list[str]
    q_alloc: np.ndarray
    lo90: np.ndarray
    hi90: np.ndarray
    q_pred: np.ndarray
    measured: float
    residual: float
    learned: bool = False

    def rows(self) -> list[dict[str, Any]]:
        return [
            {
                "time": self.time,
                "separator": self.separator,
                "well": w,
                "q_alloc": float(self.q_alloc[k]),
                "lo90": float(self.lo90[k]),
                "hi90": float(self.hi90[k]),
                "q_pred": float(self.q_pred[k]),
                "residual": self.residual,
            }
            for k, w in enumerate(self.wells)
        ]


@dataclass
class WellTestMark:
    """The wells about to learn a measurement (``live`` [W]) with their parameters
    ``theta`` [W, D], covariance grown to the measurement ``before`` [W, D, D] and reset
    counts ``resets`` [W], taken by :meth:`SeparatorLearner.before_well_tests`."""

    live: torch.Tensor
    theta: torch.Tensor
    before: torch.Tensor
    resets: torch.Tensor


class _Wells:
    """What :class:`SeparatorLearner` reads of a filter's model: the wells' names and
    whether each is ready (has a model)."""

    def __init__(self, wells: list[str], ready: torch.Tensor) -> None:
        self.wells = wells
        self.ready = ready


class WellFilters:
    """One-well ``bayes`` filters (each well its own model, as the service holds them) seen
    as the one filter over their wells that :class:`SeparatorLearner` reads and writes:
    each call goes to every well's filter with its row of the arguments, and the answers are
    stacked by well. A well's model and filter state do not depend on the other wells', so
    the numbers are those of one filter over all of them. All filters must filter as many
    parameters (models of one specification)."""

    def __init__(self, wells: Sequence[str], filters: Sequence[Any]) -> None:
        plain = [f for f in filters if isinstance(f, BayesianFilter)]
        if len(plain) != len(filters) or not filters:
            raise ConfigError(
                "A separator's wells learn from its total together only when every one of "
                "them learns with bayes."
            )
        if len({int(f.filter_state()[1].shape[-1]) for f in plain}) > 1:
            raise ConfigError(
                "A separator's wells learn from its total together only with models of one "
                "specification (as many filtered parameters each)."
            )
        self.filters = plain
        self.model = _Wells(list(wells), torch.cat([f.model.ready.reshape(1) for f in plain]))

    def filter_state(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`BayesianFilter.filter_state` of every well, stacked by well."""
        parts = [f.filter_state() for f in self.filters]
        return tuple(torch.cat([p[k] for p in parts]) for k in range(4))  # type: ignore[return-value]

    def grown_covariance(self, now_ns: torch.Tensor) -> torch.Tensor:
        """:meth:`BayesianFilter.grown_covariance`, well by well."""
        return torch.cat(
            [f.grown_covariance(now_ns[i : i + 1]) for i, f in enumerate(self.filters)]
        )

    def log_rate_and_gradient(
        self, one: Batch, live: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`BayesianFilter.log_rate_and_gradient`, each well on its row of ``one``."""
        parts = [
            f.log_rate_and_gradient(_well_row(one, i), live[i : i + 1])
            for i, f in enumerate(self.filters)
        ]
        return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])

    def stats(self) -> dict[str, torch.Tensor]:
        """:meth:`BayesianFilter.stats` of every well, stacked by well."""
        parts = [f.stats() for f in self.filters]
        return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}

    def on_measurement(self, batch: Batch) -> torch.Tensor:
        """Each well's filter learns from its row of ``batch`` (one measurement per well,
        masked where none); the wells whose model changed."""
        return torch.cat(
            [
                f.on_measurement(_well_row(batch, i))
                if bool(batch.mask[i].any())
                else torch.zeros(1, dtype=torch.bool)
                for i, f in enumerate(self.filters)
            ]
        )

    def set_filter_state(
        self, theta: torch.Tensor, P: torch.Tensor, now_ns: torch.Tensor, wells: torch.Tensor
    ) -> None:
        """:meth:`BayesianFilter.set_filter_state` of the wells marked in ``wells``."""
        for i, f in enumerate(self.filters):
            if bool(wells[i]):
                sl = slice(i, i + 1)
                f.set_filter_state(theta[sl], P[sl], now_ns[sl], wells[sl])


def _well_row(batch: Batch, i: int) -> Batch:
    """Well ``i`` of ``batch`` as a one-well batch."""
    sl = slice(i, i + 1)
    assert batch.well_test is not None and batch.extra is not None
    return Batch(
        batch.wells[sl],
        batch.x[sl],
        batch.y[sl],
        batch.mask[sl],
        batch.time_ns[sl],
        batch.row[sl],
        batch.well_test[sl],
        batch.extra[sl],
        batch.extra_names,
    )


class SeparatorLearner:
    """Separator readings for a :class:`BayesianFilter` bound to a field's model: joint
    updates over each separator's wells, well tests through the single-well filter with
    their effect carried over the kept cross-covariances (see the module docstring).

    ``members``: separator -> its wells (names of the model's wells); ``noise``: the
    separators' relative noise (sd), one for all or per separator; ``cross``: keep the
    cross-covariances; ``huber``/``gate``: down-weight / refuse beyond so many sd;
    ``calibrate``: calibrate the allocation's intervals (see the module docstring; False:
    the posterior variance of H C H^T + tau^2, as before the calibration, for comparison)."""

    def __init__(
        self,
        filt: BayesianFilter | WellFilters,
        members: Mapping[str, Sequence[str]],
        *,
        noise: float | Mapping[str, float] = SEPARATOR_NOISE,
        cross: bool = True,
        huber: float = 3.0,
        gate: float = 6.0,
        calibrate: bool = True,
    ) -> None:
        if not isinstance(filt, BayesianFilter | WellFilters):
            raise ConfigError(check_method(str(filt)) or "Separator learning needs bayes.")
        self.filt = filt
        wells = list(filt.model.wells)
        self.index = {
            sep: torch.tensor([wells.index(w) for w in ws], dtype=torch.int64)
            for sep, ws in members.items()
        }
        self.members = {sep: list(ws) for sep, ws in members.items()}
        self.noise = dict(noise) if isinstance(noise, Mapping) else {s: noise for s in members}
        self.cross = cross
        self.calibrate = calibrate
        self.huber = huber
        self.gate = gate
        self._d = filt.filter_state()[1].shape[-1]
        #: each separator's joint covariance (its diagonal blocks are re-read from the filter)
        self._joint: dict[str, torch.Tensor] = {
            sep: torch.zeros(len(ix) * self._d, len(ix) * self._d, dtype=DTYPE)
            for sep, ix in self.index.items()
        }
        self._separator_of = {int(i): sep for sep, ix in self.index.items() for i in ix.tolist()}
        self.counts = {"taken": 0, "downweighted": 0, "refused": 0, "incomplete": 0}

    # -- well tests ------------------------------------------------------------------------
    def learn_well_tests(self, batch: Batch) -> torch.Tensor:
        """Learn from one measurement per well (others masked) through the single-well
        filter, then carry each update to the well's separator partners (``cross``)."""
        live = batch.mask[:, 0] & self.filt.model.ready
        mark = self.before_well_tests(live, batch.time_ns[:, 0])
        changed = self.filt.on_measurement(batch)
        self.carry_well_tests(mark)
        return changed

    def before_well_tests(self, live: torch.Tensor, time_ns: torch.Tensor) -> WellTestMark | None:
        """What :meth:`carry_well_tests` needs of the wells ``live`` [W] (ready, measured at
        ``time_ns`` [W], epoch ns) before the single-well filter learns their measurements:
        their parameters, covariance grown to the measurement and reset counts. None
        without ``cross`` (nothing is carried)."""
        if not self.cross:
            return None
        filt = self.filt
        now = torch.where(live, time_ns, torch.full_like(time_ns, NEVER))
        theta0 = filt.filter_state()[0]
        return WellTestMark(live, theta0, filt.grown_covariance(now), filt.stats()["resets"])

    def carry_well_tests(self, mark: WellTestMark | None) -> list[str]:
        """After the single-well filter learned the measurements of ``mark``'s wells: carry
        each well's update to its separator partners over the kept cross-covariances (a
        well the filter reset forgets them). The separators whose joint state changed."""
        if mark is None:
            return []
        filt = self.filt
        theta1, after, _, _ = filt.filter_state()
        resets = filt.stats()["resets"] - mark.resets
        touched: list[str] = []
        for i in torch.nonzero(mark.live).flatten().tolist():
            sep = self._separator_of.get(i)
            if sep is None or len(self.index[sep]) < 2:
                continue
            if int(resets[i]):  # the well changed: what it shared with the others is gone
                self._forget(sep, i)
                touched.append(sep)
                continue
            if self._carry(sep, i, mark.before[i], after[i], theta1[i] - mark.theta[i]):
                touched.append(sep)
        return touched

    def joint(self, sep: str) -> torch.Tensor:
        """A copy of ``sep``'s joint covariance [M D, M D] (its diagonal blocks as of the
        last joint step; the filter's P holds the current ones)."""
        return self._joint[sep].clone()

    def set_joint(self, sep: str, cov: torch.Tensor) -> None:
        """Put back ``sep``'s joint covariance (as :meth:`joint` gave it, e.g. after a
        restart, or kept between readings by a caller that builds a learner per reading)."""
        if cov.shape != self._joint[sep].shape:
            raise ConfigError(
                f"The joint covariance of {sep} has the shape {tuple(cov.shape)}; its "
                f"{len(self.index[sep])} wells need {tuple(self._joint[sep].shape)}."
            )
        self._joint[sep] = cov.to(DTYPE).clone()

    def _carry(
        self, sep: str, well: int, p0: torch.Tensor, p1: torch.Tensor, step: torch.Tensor
    ) -> bool:
        """Condition the separator's other wells on well ``well``'s update (see the module
        docstring): its covariance went from p0 to p1 and its parameters moved by ``step``.
        False when there was nothing to carry (no correlation yet)."""
        ix, d = self.index[sep], self._d
        k = int((ix == well).nonzero()[0, 0])
        joint = self._joint[sep]
        own = torch.arange(k * d, (k + 1) * d)
        others = torch.nonzero(torch.arange(len(ix) * d) // d != k).flatten()
        c_oi = joint[others][:, own]  # [(M-1) D, D]
        if not bool(c_oi.abs().gt(0).any()):
            return False  # no correlation yet: nothing to carry
        p0_inv = torch.linalg.pinv(p0, hermitian=True)
        gain = c_oi @ p0_inv
        shrink = gain @ (p0 - p1) @ gain.T
        a = p1 @ p0_inv
        new = joint.clone()
        c_oo = joint[others][:, others] - shrink
        new[others.unsqueeze(1), others.unsqueeze(0)] = 0.5 * (c_oo + c_oo.T)
        new[others.unsqueeze(1), own.unsqueeze(0)] = c_oi @ a.T
        new[own.unsqueeze(1), others.unsqueeze(0)] = a @ c_oi.T
        self._joint[sep] = new
        # the partners' parameters move, and their own blocks shrink (at their own times)
        theta, P, last, _ = self.filt.filter_state()
        partners = ix[torch.arange(len(ix)) != k]
        theta[partners] += (gain @ step).reshape(len(partners), d)
        for j, w in enumerate(partners.tolist()):
            P[w] = P[w] - shrink[j * d : (j + 1) * d, j * d : (j + 1) * d]
        mask = torch.zeros(len(self.filt.model.wells), dtype=torch.bool)
        # a partner without a model yet is left unstarted (it shares nothing yet): its
        # first measurement starts it (at its start variance), as in a joint update
        mask[partners] = self.filt.model.ready[partners]
        self.filt.set_filter_state(theta, P, last, mask)
        return True

    def separator_of(self, well: int) -> str | None:
        """The separator well ``well`` (its index in the model) flows into (None: none)."""
        return self._separator_of.get(well)

    def forget(self, sep: str | None, well: int) -> None:
        """Drop well ``well``'s cross-covariances on its separator ``sep`` (a refit started
        its filter again: what it shared with its partners is gone); None: on no separator."""
        if sep is not None and sep in self.index:
            self._forget(sep, well)

    def _forget(self, sep: str, well: int) -> None:
        """Drop well ``well``'s cross-covariances (after the filter reset it: it changed)."""
        ix, d = self.index[sep], self._d
        k = int((ix == well).nonzero()[0, 0])
        own = torch.arange(k * d, (k + 1) * d)
        self._joint[sep][own, :] = 0.0
        self._joint[sep][:, own] = 0.0

    # -- separator readings ------------------------------------------------------------------
    def allocate_and_learn(
        self,
        sep: str,
        one: Batch,
        live: torch.Tensor,
        measured: float,
        when: pd.Timestamp,
        *,
        learn: bool = True,
    ) -> Allocation | None:
        """A reading of ``sep`` (``measured`` Sm3/h at ``when``; ``one``: one sample per model
        well, ``live`` [W] the member wells flowing): its allocation, and (``learn``) the joint
        update. None when the reading cannot be used (a flowing well without a model yet, a
        zero total); counted as ``incomplete``."""
        filt = self.filt
        ix = self.index[sep]
        ready = filt.model.ready
        flowing = live[ix]
        if not bool(flowing.any()) or bool((flowing & ~ready[ix]).any()) or not measured > 0:
            self.counts["incomplete"] += 1
            return None
        n = len(filt.model.wells)
        t = int(when.value)
        now = torch.full((n,), t, dtype=torch.int64)
        log_h, H = filt.log_rate_and_gradient(one, live)
        theta, _, _, noise = filt.filter_state()
        grown = filt.grown_covariance(now)
        d, m = self._d, len(ix)
        lh = log_h[ix]
        hm = torch.where(flowing.unsqueeze(1), H[ix], 0.0)  # [M, D]
        q = torch.where(flowing, lh.exp(), torch.zeros_like(lh))
        share = q / float(q.sum())
        tau2 = torch.where(flowing, noise[ix, 1] ** 2, torch.zeros_like(lh))
        s2 = self.noise[sep] ** 2
        r = math.log(measured) - math.log(float(q.sum()))
        pm = grown[ix]  # [M, D, D]: each well's P at the reading
        rows = torch.arange(m)
        joint: torch.Tensor | None = None
        if self.cross:
            joint = self._joint[sep].clone()
            joint.view(m, d, m, d)[rows, :, rows, :] = pm
            sigma = torch.einsum("id,idje,je->ij", hm, joint.view(m, d, m, d), hm)
        else:
            sigma = torch.diag(torch.einsum("id,ide,ie->i", hm, pm, hm))
        # the wells' true log rates: prior covariance (parameters and misfit, calibrated),
        # then given the sum
        if self.calibrate:
            factor, meter = well_test_factor(filt, ix)
            prior = calibrated_prior(sigma, tau2, factor, meter)
        else:
            prior = sigma + torch.diag(tau2)
        alloc = self._allocate(sep, when, measured, lh, flowing, prior, s2)
        if learn:
            alloc.learned = self._learn(sep, theta, grown, pm, hm, share, tau2, s2, r, joint, now)
        return alloc

    def _learn(
        self,
        sep: str,
        theta: torch.Tensor,
        grown: torch.Tensor,
        pm: torch.Tensor,
        hm: torch.Tensor,
        share: torch.Tensor,
        tau2: torch.Tensor,
        s2: float,
        r: float,
        joint: torch.Tensor | None,
        now: torch.Tensor,
    ) -> bool:
        """The joint update of ``sep``'s wells from a reading with log innovation ``r``:
        ``theta`` [W, D] and ``grown`` [W, D, D] the filter's state at the reading, ``pm``,
        ``hm``, ``share``, ``tau2`` the members' P, sensitivities, shares and misfit
        variances, ``s2`` the meter's relative noise variance, ``joint`` the separator's
        joint covariance (None: block-diagonal). False if the reading was refused."""
        ix, d, m = self.index[sep], self._d, len(self.index[sep])
        rows = torch.arange(m)
        n = len(self.filt.model.wells)
        # the learning step: R holds the meter's noise and every member's misfit
        noise_var = s2 + float((share**2 * tau2).sum())
        g = share.unsqueeze(1) * hm  # [M, D]: the measurement row, well by well
        if joint is not None:
            c = torch.einsum("idje,je->id", joint.view(m, d, m, d), g)
        else:
            c = torch.einsum("ide,ie->id", pm, g)
        s_full = float((g * c).sum()) + noise_var
        z = r / math.sqrt(s_full)
        if self.gate and abs(z) > self.gate:
            self.counts["refused"] += 1
            return False
        if self.huber and abs(z) > self.huber:
            noise_var *= abs(z) / self.huber
            self.counts["downweighted"] += 1
        if joint is not None:  # the whole joint covariance: O((M D)^2)
            new_mean, new_cov, _ = sum_update(
                theta[ix].reshape(-1), joint, g.reshape(-1), r, noise_var
            )
            theta[ix] = new_mean.reshape(m, d)
            p_new = new_cov.view(m, d, m, d)[rows, :, rows, :]
            self._joint[sep] = new_cov
        else:  # each well's block alone: O(M D^2)
            gain = c / (float((g * c).sum()) + noise_var)
            theta[ix] = theta[ix] + gain * r
            p_new = pm - (float((g * c).sum()) + noise_var) * torch.einsum("id,ie->ide", gain, gain)
            p_new = 0.5 * (p_new + p_new.transpose(-1, -2))
        P = grown.clone()
        P[ix] = p_new
        wells = torch.zeros(n, dtype=torch.bool)
        # a member without a model yet has no filter state: left unstarted, so that its
        # first measurement starts it at its start variance (as without separator readings)
        wells[ix] = self.filt.model.ready[ix]
        self.filt.set_filter_state(theta, P, now, wells)
        self.counts["taken"] += 1
        return True

    def _allocate(
        self,
        sep: str,
        when: pd.Timestamp,
        measured: float,
        log_rate: torch.Tensor,
        flowing: torch.Tensor,
        sigma: torch.Tensor,
        s2: float,
    ) -> Allocation:
        """The reading split to the wells: their log rates ``log_rate`` [M] (prior mean, of
        rates in Sm3/h) with covariance ``sigma`` [M, M] (:func:`calibrated_prior`),
        conditioned on the measured total (relative noise variance ``s2``), then scaled to
        sum to it exactly; the intervals from the booked rates' variance (the posterior's
        plus s2^2 / S, the meter's error each booked rate carries)."""
        q = torch.where(flowing, log_rate.exp(), torch.zeros_like(log_rate))
        booked, sd = booked_allocation(
            log_rate, flowing, sigma, s2, measured, booking=self.calibrate
        )
        spread = Z90 * sd
        return Allocation(
            time=when,
            separator=sep,
            wells=self.members[sep],
            q_alloc=booked.numpy(),
            lo90=(booked * torch.exp(-spread)).numpy(),
            hi90=(booked * torch.exp(spread)).numpy(),
            q_pred=q.numpy(),
            measured=float(measured),
            residual=float(measured - float(q.sum())),
        )


def check_method(method: str) -> str | None:
    """None if ``method`` learns from separator readings (``bayes``), else the sentence
    saying what it does with them."""
    key = method.split(":")[0]
    if key == "bayes":
        return None
    return (
        f"The method '{method}' ignores separator readings: its fit is a per-well objective "
        f"solved for all wells independently, and a shared term over a separator's wells "
        f"is not implemented; use bayes to learn from the separator's total."
    )


@dataclass
class SeparatorRun:
    """What :func:`run_separator` gives: ``predictions`` of every well test after the split
    (time, well, predicted, measured, predicted_p05, predicted_p95; Sm3/h), ``allocation``
    (:data:`ALLOCATION_COLUMNS`, one row per reading and member well), ``counts`` (readings
    taken, down-weighted, refused, incomplete), ``runtime_s``."""

    model: str
    method: str
    predictions: pd.DataFrame
    allocation: pd.DataFrame
    counts: dict[str, int] = field(default_factory=dict)
    runtime_s: float = 0.0

    def well_mape(self) -> pd.Series:
        """MAPE (%) on the well tests, per well."""
        p = self.predictions
        err = (p["predicted"] - p["measured"]).abs() / p["measured"] * 100.0
        return err.groupby(p["well"]).mean()

    def reading_residuals(self) -> pd.DataFrame:
        """One row per reading: separator, time and ``percent``, the reconciliation residual
        (the total minus the sum of the wells' predictions before the reading) in % of the
        measured total (NaN for a total of 0)."""
        per = self.allocation.groupby(["separator", "time"], sort=True).agg(
            residual=("residual", "first"), predicted=("q_pred", "sum")
        )
        measured = per["residual"] + per["predicted"]
        out = (per["residual"] / measured.where(measured > 0) * 100.0).rename("percent")
        return out.reset_index()

    def sum_error(self) -> float:
        """Mean |sum of the wells' predictions - separator total| / total, %, over the
        readings (predictions before each reading is learned from)."""
        if self.allocation.empty:
            return float("nan")
        return float(self.reading_residuals()["percent"].abs().mean())


def run_separator(
    frame: pd.DataFrame,
    separators: SeparatorData,
    model_name: str,
    method: str = "bayes",
    *,
    split: str | pd.Timestamp | None = None,
    seed: int = 0,
    learn: bool = True,
    cross: bool = True,
    noise: float | Mapping[str, float] = SEPARATOR_NOISE,
    window: pd.Timedelta = SAMPLE_WINDOW,
    calibrate: bool = True,
) -> SeparatorRun:
    """The case 2 protocol with separator readings: fit ``model_name`` on the well tests
    before ``split`` (the case's default split), then go through the well tests and the
    readings after it in time order: predict each well test before learning from it; for
    each reading, allocate it and (``learn``) make the joint update. ``learn=False`` is the
    same run without learning from the readings (the baseline), allocations still made;
    ``calibrate=False`` the same run with the allocation's intervals uncalibrated (see
    :class:`SeparatorLearner`)."""
    from vfm_core.jobs.study import resolve_split

    started = time.perf_counter()
    if check_method(method) is not None:
        raise ConfigError(str(check_method(method)))
    split_ts = resolve_split(WELL_TEST, split, frame)
    is_test = target_mask(frame, WELL_TEST)
    before = (frame[TIME] < split_ts).to_numpy()
    meth = _started_filter(frame, separators, model_name, method, split_ts, seed)
    learner = SeparatorLearner(
        meth, separators.members, noise=noise, cross=cross, calibrate=calibrate
    )
    readings = separators.readings
    readings = readings[readings[TIME] >= split_ts].reset_index(drop=True)
    samples = member_samples(frame, readings, separators.members, window=window)
    one_batch = _OneSample(frame, list(meth.model.wells))
    code = {w: i for i, w in enumerate(meth.model.wells)}

    tests = np.flatnonzero(is_test & ~before)
    # in time order, a well test before a reading at the same time
    reading_times = pd.DatetimeIndex(readings[TIME]).asi8.tolist()
    events = sorted(
        [(int(one_batch.t_all[r]), 0, int(r)) for r in tests]
        + [(int(t), 1, k) for k, t in enumerate(reading_times)]
    )
    by_reading = {k: g for k, g in samples.groupby("reading")}
    predicted, p05, p95 = (np.full(len(frame), np.nan) for _ in range(3))
    allocations: list[dict[str, Any]] = []
    # the refits on schedule read the well tests learned so far (see _refits_due)
    memory = FrameMemory(frame, is_test, list(meth.model.wells), meth.model.extra_columns)
    for t_event, kind, index in events:
        if kind == 0:  # a well test: its refits due, then predicted, then learned from
            w = code[str(frame[WELL].iat[index])]
            _refits_due(learner, memory, w, t_event)
            batch = one_batch({w: index}, True)
            forecast = meth.predict(batch)
            for out, values in (
                (predicted, forecast.mean),
                (p05, forecast.p05),
                (p95, forecast.p95),
            ):
                out[index] = np.nan if values is None else float(values[w, 0])
            learner.learn_well_tests(batch)
            continue
        if index in by_reading:
            allocations += _reading_rows(
                learner, one_batch, code, by_reading[index], readings.iloc[index], learn
            )

    return SeparatorRun(
        model=model_name,
        method=method,
        predictions=_scored(frame, tests, predicted, p05, p95),
        allocation=pd.DataFrame(allocations, columns=list(ALLOCATION_COLUMNS)),
        counts=dict(learner.counts),
        runtime_s=time.perf_counter() - started,
    )


def _refits_due(learner: SeparatorLearner, memory: FrameMemory, well: int, t_ns: int) -> None:
    """Run the refits of well ``well`` due by ``t_ns`` (its next well test), on the well
    tests in ``memory`` (see :meth:`BayesianFilter.retrain_due`): a method that refits on
    schedule (``bayes`` with ``refresh``: a hybrid that learns from well tests only), as the
    study runs it. A well that learns from the readings is not refitted (they end its
    refits, as an MPFM's readings do: :meth:`BayesianFilter.set_filter_state`), so with
    ``learn`` they run only where no reading was learned for 30 days. A refitted well
    forgets its cross-covariances (its filter started again)."""
    meth = learner.filt
    assert isinstance(meth, BayesianFilter)
    now = torch.full((len(meth.model.wells),), NEVER, dtype=torch.int64)
    now[well] = t_ns
    for i in torch.nonzero(meth.retrain_due(memory, now)).flatten().tolist():
        learner.forget(learner.separator_of(i), i)


def _scored(
    frame: pd.DataFrame,
    tests: np.ndarray,
    predicted: np.ndarray,
    p05: np.ndarray,
    p95: np.ndarray,
) -> pd.DataFrame:
    """The well tests ``tests`` (rows of ``frame``) with their predictions (Sm3/h, by row of
    ``frame``): time, well, predicted, measured, predicted_p05, predicted_p95."""
    scored = frame.iloc[tests]
    return pd.DataFrame(
        {"time": scored[TIME].to_numpy(), "well": scored[WELL].astype(str).to_numpy()}
    ).assign(
        predicted=predicted[tests],
        measured=scored[TARGET].to_numpy(),
        predicted_p05=p05[tests],
        predicted_p95=p95[tests],
    )


def _started_filter(
    frame: pd.DataFrame,
    separators: SeparatorData,
    model_name: str,
    method: str,
    split_ts: pd.Timestamp,
    seed: int,
) -> BayesianFilter:
    """``method`` bound to ``model_name`` over the wells with well tests, fitted on the
    tests before ``split_ts`` and started there (as :func:`run_prequential` starts it)."""
    from vfm_core.jobs.study import _start_fresh, wells_of

    torch.manual_seed(seed)
    is_test = target_mask(frame, WELL_TEST)
    before = (frame[TIME] < split_ts).to_numpy()
    wells = wells_of(frame.iloc[np.flatnonzero(is_test)])
    for sep, ws in separators.members.items():
        missing = [w for w in ws if w not in wells]
        if missing:
            raise DataError(
                f"The wells {', '.join(missing)} of the separator '{sep}' have no well test; "
                "each member well needs at least one to be allocated a rate."
            )
    model = make_model(model_name, wells, seed=seed)
    if model.extra_columns:
        raise ConfigError(f"The model {model_name} needs extra features; use mm, hem or ham.")
    meth = parse_method(method)
    assert isinstance(meth, BayesianFilter)
    meth.bind(model, train=DEFAULT_TRAIN.get(model_name, TrainSettings()))
    meth.fit(make_batch(frame, wells, rows=np.flatnonzero(is_test & before)))
    had = set(frame.loc[is_test & before, WELL].astype(str))
    _start_fresh(
        model, [w for w in wells if w not in had], lambda w: make_model(model_name, [w], seed=seed)
    )
    meth.start(split_ts.value)
    return meth


class _OneSample:
    """Batches of one sample per well [W, 1] from rows of ``frame`` (well index -> row)."""

    def __init__(self, frame: pd.DataFrame, wells: list[str]) -> None:
        self.wells = wells
        self.x_all = torch.from_numpy(frame[list(INPUT_COLUMNS)].to_numpy(dtype=np.float64))
        self.y_all = frame[TARGET].to_numpy(dtype=np.float64)
        self.t_all = pd.DatetimeIndex(frame[TIME]).asi8

    def __call__(self, rows: dict[int, int], well_test: bool) -> Batch:
        n = len(self.wells)
        x = torch.zeros(n, 1, len(INPUT_COLUMNS), dtype=DTYPE)
        x[:] = self.x_all[next(iter(rows.values()))]  # padding: a finite sample
        y = torch.zeros(n, 1, dtype=DTYPE)
        mask = torch.zeros(n, 1, dtype=torch.bool)
        t = torch.full((n, 1), NEVER, dtype=torch.int64)
        row = torch.full((n, 1), -1, dtype=torch.int64)
        for w, r in rows.items():
            x[w, 0] = self.x_all[r]
            y[w, 0] = 0.0 if np.isnan(self.y_all[r]) else self.y_all[r]
            mask[w, 0] = True
            t[w, 0] = int(self.t_all[r])
            row[w, 0] = r
        return Batch(list(self.wells), x, y, mask, t, row, mask & well_test)


def _reading_rows(
    learner: SeparatorLearner,
    one_batch: _OneSample,
    code: dict[str, int],
    group: pd.DataFrame,
    reading: pd.Series,
    learn: bool,
) -> list[dict[str, Any]]:
    """One reading (``group``: its member samples from :func:`member_samples`) allocated
    and (``learn``) learned from; its allocation rows (none if it was not usable)."""
    flowing = group[~group["shut"].to_numpy()]
    rows = {code[w]: int(r) for w, r in zip(flowing[WELL], flowing["row"], strict=True)}
    if not rows:
        return []
    batch = one_batch(rows, False)
    alloc = learner.allocate_and_learn(
        str(reading[SEPARATOR_COLUMN]),
        batch,
        batch.mask[:, 0].clone(),
        float(reading[TARGET]),
        reading[TIME],
        learn=learn,
    )
    return [] if alloc is None else alloc.rows()
