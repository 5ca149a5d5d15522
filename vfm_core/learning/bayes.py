"""Bayesian online learning (``bayes[:key=value:...]``): a filter that knows how sure it is.

The state of a well is a Gaussian over the parameters its model exposes to a filter
(:meth:`vfm_core.models.base.ChokeModel.filter_blocks`: the mechanistic parameters in
prior standard deviations, every effect's, and the output layer of a network): the mean
is the model's parameters, the covariance P is kept here.

- **Start.** The batch (MAP) fit, then a Kalman pass over the history it was fitted on
  (linearised at the fit, J the sensitivity of the log rate to the parameters by central
  differences), so that a well that drifted starts where it ended, not at its history's
  average (see :meth:`BayesianFilter._fitted`). :func:`laplace_sd` gives the plain Laplace
  covariance of a fit (the Gauss-Newton Hessian of the MAP objective) for a diagnosis. A
  well without a fit (none before the filter's start) starts at its first measurement with
  each parameter's ``FilterBlock.start_var``: the prior, but a hybrid's output weights at
  their prior mean with no variance (its network's lower layers are unfitted draws: see
  :meth:`vfm_core.models.base.WellMLP.head_blocks`).
- **Drift.** Between measurements the parameters wander as a random walk: P grows by
  Q dt, dt in years, Q = diag(drift^2). Each parameter's drift is a property of the
  parameter (``Prior.drift`` for physical ones, see :class:`vfm_core.physics.Prior`; a
  network's output layer a few percent a year), times the option ``drift`` (default 1),
  or set one by one (``drift_c_d=0.8``). So a well test after 60 days of silence moves
  the parameters more than one after 2 days, and it moves what is likely to have moved
  (the discharge coefficient) rather than what was learned once (an effect's slope).
- **Update.** Each measurement y is one extended Kalman step in log space (iterated with
  ``iterations`` > 1),
  log y = log h(x; theta) + e, e ~ N(0, s^2), with the noise s of its source: MPFM and
  well test each have their own relative noise, estimated per well from the residuals of
  the fit before the split (divided by the rows less the parameters fitted, shrunk towards
  3 % and 1 % when there are few), then adapted online from the innovations (``adapt``, an
  exponentially weighted variance), so a well test counts for what it is. The Joseph form keeps P symmetric and positive.
- **Outliers.** An innovation beyond ``huber`` predictive standard deviations is
  down-weighted (its noise inflated by |z|/huber); beyond ``gate`` it is refused, and
  counted. Three refusals in a row mean the well itself changed: P is widened by a year's
  drift and the measurement is taken.
- **Prediction.** The rate h(x; theta) (the median of a log-normal), and its spread in log
  space sqrt(H (P + Q dt) H^T + s^2): the parameters' uncertainty at the time of the sample
  and the noise of the meter the rate is compared with (a well test's for the service's
  predictions). H, the sensitivity of the log rate, is taken at the well's last measured
  sample (in log space it barely depends on the inputs for the choke models), which saves
  a backward pass per prediction. The central 90 % interval is rate x exp(+-1.645 sd).
- **Calibration.** A filter's intervals are only as honest as its model. Each meter's
  intervals carry a factor learned by adaptive conformal inference (Gibbs and Candes,
  2021): after every measurement the factor's log grows by 0.9 ``calibrate`` if the
  measurement fell outside the 90 % interval given for it and shrinks by 0.1 ``calibrate``
  if inside, so in the long run 90 % fall inside, whatever the model lacks. The factor widens the intervals
  only; the filter's gain is the Kalman gain.
- **Variance factor (well tests).** Conformal steps are slow where measurements are few
  (nine well tests a well over a year move it by a few percent), and a data-driven model's
  errors on the next well test are larger than its filter's variance says (measured: lr
  and nn in case 2 have errors 1.6 times their spread; the fit's residuals cannot show it,
  they are in-sample and already set the meter noise). So a well test's forecast variance
  also carries a factor c^2 learned from the standardised errors z of the forecasts the
  filter gave for the well's earlier well tests before learning from them, conjugately:
  prior c^2 ~ InvGamma(nu0 / 2, nu0 / 2) (the filter is right, worth nu0 = ``cal_prior``
  = 2 errors), posterior InvGamma((nu0 + n) / 2, (nu0 + sum z^2) / 2) (each error
  discounts the older ones by 0.99, West and Harrison's variance discount), forecast a
  Student t with nu0 + n degrees of freedom: the 90 % half-width is
  t_0.95(nu0 + n) sqrt((nu0 + sum z^2) / (nu0 + n)) sd. A refused error counts as one at
  the gate. Widens or narrows the intervals only. MPFM readings (twice a day) are left to
  the conformal factor, which calibrates them in weeks.
- **Pooled over the wells (``cal_pool``).** The wells of one filter share a model and a
  drift allowance, so their factors are alike: each well's prior InvGamma(k / 2, k c0^2 /
  2) is then the one under which the other wells' errors are most likely (the stated prior
  counted as one more well; k, its weight in errors, in [nu0, nu0 + their n]; empirical
  Bayes, the moderated variances of Smyth 2004, see :func:`_pooled_prior`);
  the well's own errors then update it as above (t with k + n degrees of freedom). Wells
  that agree give a large k (the factor learned from all of them), wells that disagree a
  small one (each its own). A filter of one well has no others: the rule above, unless
  given the other wells' statistics (:meth:`BayesianFilter.pool_with`, or a
  :class:`CalibrationPool` shared by one-well filters, :meth:`BayesianFilter.share_errors`:
  each reads the others' statistics as they were before its time). The search is compiled
  (:mod:`vfm_core.learning._pool_kernels`, the same numbers). Off by default. The service
  shares one pool among the one-well filters of each model and method
  (:mod:`service.engine.pools`). The filter then couples its wells (:attr:`couples_wells`),
  so ``vfm evaluate`` replays it in time order, as a service sees the field
  (docs/guide/bayes.md, "At other meter noise levels").

Networks get the cheap approximation: only their output layer is filtered (last-layer
Bayesian learning); the layers below stay as fitted.

- **Refit (shared models).** ``mtl``'s filter covers each well's task vector only; its
  network is shared by every well, so no well's filter can carry it, and only a joint fit
  on every well's measurements moves it. So with ``refresh`` (default ``auto``: every 14
  days for a shared model; for a hybrid's wells, ``hem`` and ``ham``, every 14 days while
  a well learns from well tests only (no MPFM reading in the last 30 days, see
  :meth:`BayesianFilter.start`), its network's lower layers then refitted; never for the
  others; a period such as ``14d`` refits any model's every well) the model is refitted on schedule as
  ``pbl`` retrains it (MAP, warm-started, on every measurement before the due time; every
  missed refit of a gap runs), and the filter starts again from the refit
  (:meth:`BayesianFilter._fitted`): an EM-like alternation, the filter the posterior of
  the task vectors given the network, the refit the network's MAP given the data (see
  :meth:`BayesianFilter.retrain_due`). The start's Kalman passes run compiled
  (:mod:`vfm_core.learning._history_kernels`, the torch loop's numbers to rounding), and
  after a refit of the compiled filter the history is linearised by the compiled gradient
  at the refitted wells' rows only (:meth:`BayesianFilter._linearised`): a refit of a
  case-1 field costs about what its fit does (docs/guide/bayes.md, session 50).

Options: ``drift``, ``drift_<label>``,
``noise_mpfm``, ``noise_well_test`` (relative sd; default: from the data), ``iterations``
(Kalman iterations per update, default 1: the extended filter; more re-linearise at the
updated mean, which measured no better on the choke models), ``huber`` (3), ``gate`` (6), ``adapt`` (0.02),
``calibrate`` (0.05), ``cal_prior`` (2; 0: no variance factor), ``cal_pool`` (``off``, the
default; ``on``: the factor's prior from the other wells), ``params`` (labels to filter,
joined with '+'; default all), ``refresh`` (``auto``, ``off`` or a period such as ``30d``).
"""

from __future__ import annotations

import copy
import functools
import importlib
import math
import threading
from collections.abc import Collection, Hashable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import pandas as pd
import torch
from scipy.special import gammaln, stdtrit

from vfm_core.data import DTYPE, Batch
from vfm_core.errors import ConfigError
from vfm_core.learning.kernels import (
    compiled,
    compiled_effects,
    effect_arguments,
    effect_bounds,
    effect_parameters,
    kernels_enabled,
    physics_layout,
    plain_hybrid,
    plain_mm,
    predict_rates,
    writable,
)
from vfm_core.learning.memory import Memory
from vfm_core.learning.method import (
    NEVER,
    Forecast,
    LearningMethod,
    parse_options,
    parse_span,
    ready_for_group,
    register,
)
from vfm_core.learning.stacking import stack_for_learning, stacked_rates
from vfm_core.models import ChokeModel
from vfm_core.models.base import FilterBlock
from vfm_core.models.physical import Mechanistic

__all__ = [
    "BayesianFilter",
    "CalibrationPool",
    "laplace_sd",
    "pooled_factor",
    "NOISE_DEFAULTS",
    "Z90",
]

#: a central 90 % interval spans +-Z90 standard deviations (in log space)
Z90 = 1.6448536269514722
#: relative noise (sd) of each meter when the history says little: MPFM and well test
NOISE_DEFAULTS = (0.03, 0.01)
#: pseudo-rows of the default in the per-well noise estimate (shrinkage)
_NOISE_PRIOR_ROWS = 20.0
#: smallest relative noise the filter assumes (a perfect meter would freeze the model)
_NOISE_FLOOR = 0.002
_NS_PER_YEAR = 365.25 * 86400e9
_FD_STEP = 1e-4
#: refusals in a row after which a well is taken to have changed
_RESET_AFTER = 3
#: the intervals' variance factor (see :meth:`BayesianFilter._learn_calibration`): how many
#: standardised forecast errors the prior (the filter's own variance is right) counts for
_CAL_PRIOR = 2.0
#: ... and how much each new error discounts the older ones (a memory of about 100 well
#: tests a well: West and Harrison's variance discount)
_CAL_DISCOUNT = 0.99
#: the prior weights k (as fractions of the way from nu0 to nu0 + n, geometric) among which
#: the pooled prior's is chosen (see :func:`_pooled_prior`)
_POOL_GRID = np.linspace(0.0, 1.0, 33)
#: ... and the fixed-point steps of the prior's scale for each weight
_POOL_STEPS = 6
#: columns of a batch whose gradients one batched backward pass takes (its seeds are
#: columns x wells x columns: bounded for a study's long batches)
_GRAD_COLUMNS = 64
#: the publications a :class:`CalibrationPool` keeps per well (a reader asks for the
#: statistics as they were before its time: a few back cover a batch's or a worker's lag)
_POOL_KEEP = 8
#: the compiled step's forecast errors when none is wanted (cal, counted, cap 0: off, discount)
_NO_ERRORS = (np.zeros((0, 2, 3)), np.zeros(1, dtype=np.int64), 0.0, _CAL_DISCOUNT)
#: how often a shared model's network is refitted under the filter by default (see
#: :meth:`BayesianFilter.retrain_due`): the period of the batch learning it is compared with
_SHARED_REFRESH = pd.Timedelta(days=14)
#: ``auto`` refits a per-well hybrid's well only while it learns from well tests only: a
#: well with an MPFM reading in this span before (see :meth:`BayesianFilter._tests_only`)
#: has a meter, and its filter follows it without a refit
_MPFM_LAPSE = pd.Timedelta(days=30)
#: the per-well state a prediction reads (leading dimension: the well)
_PREDICT_STATE = ("_P", "_h", "_last", "_noise", "_scale", "_started")
#: ... and an update changes (its counters aside)
_LEARN_STATE = (*_PREDICT_STATE, "_run", "_cal", "_sent_t", "_sent_s")


def _flat(blocks: list[FilterBlock], n_wells: int) -> torch.Tensor:
    """The blocks' current values as one vector per well [W, D]."""
    return torch.cat([b.param.detach().reshape(n_wells, -1) for b in blocks], dim=1)


def _assign(blocks: list[FilterBlock], theta: torch.Tensor, wells: torch.Tensor) -> None:
    """Write [W, D] into the blocks' parameters for ``wells`` only."""
    n = theta.shape[0]
    with torch.no_grad():
        start = 0
        for b in blocks:
            view = b.param.data.reshape(n, -1)
            k = view.shape[1]
            view[wells] = theta[wells, start : start + k]
            start += k


def _log_rate(model: ChokeModel, batch: Batch) -> torch.Tensor:
    q = model.forward_batch(batch)
    return torch.log(torch.clamp(q, min=1e-12))


def _jacobian_fd(
    model: ChokeModel, blocks: list[FilterBlock], batch: Batch
) -> tuple[torch.Tensor, torch.Tensor]:
    """log h [W, N] and its sensitivity to every filtered parameter [W, N, D] (central
    differences, all wells at once: a well's rate depends only on its own parameters)."""
    n_w = batch.n_wells
    theta = _flat(blocks, n_w)
    everyone = torch.ones(n_w, dtype=torch.bool)
    with torch.no_grad():
        base = _log_rate(model, batch)
        cols = []
        for d in range(theta.shape[1]):
            step = torch.zeros_like(theta)
            step[:, d] = _FD_STEP
            _assign(blocks, theta + step, everyone)
            up = _log_rate(model, batch)
            _assign(blocks, theta - step, everyone)
            down = _log_rate(model, batch)
            cols.append((up - down) / (2 * _FD_STEP))
        _assign(blocks, theta, everyone)
    return base, torch.stack(cols, dim=-1)


def _source(batch: Batch) -> torch.Tensor:
    """0 for MPFM rows, 1 for well tests [W, N]."""
    assert batch.well_test is not None
    return batch.well_test.to(torch.int64)


def _well_rows(batch: Batch, start: int, stop: int) -> Batch:
    """The wells ``start`` to ``stop`` (rows) of ``batch``."""
    assert batch.well_test is not None and batch.extra is not None
    rows = slice(start, stop)
    return Batch(
        batch.wells[rows],
        batch.x[rows],
        batch.y[rows],
        batch.mask[rows],
        batch.time_ns[rows],
        batch.row[rows],
        batch.well_test[rows],
        batch.extra[rows],
        batch.extra_names,
    )


def _laplace(
    model: ChokeModel,
    blocks: list[FilterBlock],
    batch: Batch,
    prior_var: torch.Tensor,
    defaults: torch.Tensor,
    fixed: tuple[float | None, float | None],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Laplace covariance [W, D, D], noise per source [W, 2], last sensitivity [W, D] and
    last time [W] from a fit on ``batch``."""
    log_h, jac = _jacobian_fd(model, blocks, batch)
    y = torch.where(batch.mask & (batch.y > 0), batch.y, torch.ones_like(batch.y))
    ok = batch.mask & (batch.y > 0) & torch.isfinite(log_h)
    r = torch.where(ok, torch.log(y) - log_h, torch.zeros_like(log_h))
    src = _source(batch)
    noise = torch.empty(batch.n_wells, 2, dtype=DTYPE)
    for s in (0, 1):
        rows = ok & (src == s)
        n = rows.sum(1).to(DTYPE)
        # a robust spread: residuals beyond 5 median absolute deviations are clipped
        med = torch.where(rows, r.abs(), torch.full_like(r, float("nan"))).nanmedian(1).values
        cap = torch.nan_to_num(5 * 1.4826 * med, nan=1.0).clamp(min=1e-6).unsqueeze(1)
        ss = torch.where(rows, torch.clamp(r.abs(), max=cap) ** 2, torch.zeros_like(r)).sum(1)
        var = (ss + _NOISE_PRIOR_ROWS * defaults[s] ** 2) / (n + _NOISE_PRIOR_ROWS)
        noise[:, s] = var.sqrt().clamp(min=_NOISE_FLOOR)
        if fixed[s] is not None:
            noise[:, s] = float(fixed[s])  # type: ignore[arg-type]
    row_var = torch.gather(noise, 1, src) ** 2  # [W, N]
    w = torch.where(ok, 1.0 / row_var, torch.zeros_like(row_var))
    jac = torch.where(ok.unsqueeze(-1), jac, torch.zeros_like(jac))
    info = torch.einsum("wnd,wn,wne->wde", jac, w, jac) + torch.diag_embed(1.0 / prior_var).expand(
        batch.n_wells, -1, -1
    )
    cov = _inverse_spd(info)
    counts = ok.sum(1)
    last = (counts - 1).clamp(min=0)
    h_last = jac[torch.arange(batch.n_wells), last]
    t = torch.where(ok, batch.time_ns, torch.full_like(batch.time_ns, -1))
    t_last = t.max(dim=1).values
    return cov, noise, h_last, torch.where(counts > 0, t_last, torch.full_like(t_last, NEVER))


def _reorder(batch: Batch, order: torch.Tensor) -> Batch:
    """The batch with each well's samples in the given order [W, N]."""
    assert batch.well_test is not None and batch.extra is not None

    def take(t: torch.Tensor) -> torch.Tensor:
        idx = order if t.dim() == 2 else order.unsqueeze(-1).expand(-1, -1, t.shape[-1])
        return torch.gather(t, 1, idx)

    return Batch(
        batch.wells,
        take(batch.x),
        take(batch.y),
        take(batch.mask),
        take(batch.time_ns),
        take(batch.row),
        take(batch.well_test),
        take(batch.extra),
        batch.extra_names,
    )


def _noise_from(
    r: torch.Tensor,
    ok: torch.Tensor,
    src: torch.Tensor,
    defaults: torch.Tensor,
    dof: float,
) -> torch.Tensor:
    """Relative noise per well and meter [W, 2] from a fit's residuals ``r`` in log space:
    robust to outliers, corrected for the ``dof`` parameters the fit took (at most half the
    rows), and shrunk towards ``defaults`` with few rows."""
    noise = torch.empty(r.shape[0], 2, dtype=DTYPE)
    for s in (0, 1):
        rows = ok & (src == s)
        n = rows.sum(1).to(DTYPE)
        # residuals beyond 5 median absolute deviations are clipped
        med = torch.where(rows, r.abs(), torch.full_like(r, float("nan"))).nanmedian(1).values
        cap = torch.nan_to_num(5 * 1.4826 * med, nan=1.0).clamp(min=1e-6).unsqueeze(1)
        ss = torch.where(rows, torch.clamp(r.abs(), max=cap) ** 2, torch.zeros_like(r)).sum(1)
        free = n - torch.minimum(torch.full_like(n, dof), n / 2)
        var = (ss + _NOISE_PRIOR_ROWS * defaults[s] ** 2) / (free + _NOISE_PRIOR_ROWS)
        noise[:, s] = var.sqrt().clamp(min=_NOISE_FLOOR)
    return noise


def _history_pass(
    y: torch.Tensor,
    log_h: torch.Tensor,
    jac: torch.Tensor,
    ok: torch.Tensor,
    src: torch.Tensor,
    time_ns: torch.Tensor,
    noise: torch.Tensor,
    prior_var: torch.Tensor,
    q: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """A linear Kalman filter over history rows (time order per well), linearised at the fit:
    log y = log h + J m + e. Returns the state m [W, D] (offset from the fit) and P at the
    last row, the one-step-ahead innovations and their parameter variance [W, N], the last
    sensitivity [W, D] and the last time [W]."""
    P0 = _history_start(ok, time_ns, prior_var, q)
    R_all = torch.gather(noise, 1, src) ** 2
    kernel = _history_kernel()
    if kernel is not None:
        arrays = (y, log_h, jac, ok, R_all, time_ns, P0, q.to(DTYPE))
        out = kernel.history_pass(
            *(np.ascontiguousarray(a.numpy()) for a in arrays),
            int(NEVER),
            _NS_PER_YEAR,
        )
        return tuple(torch.from_numpy(a) for a in out)
    return _history_pass_torch(y, log_h, jac, ok, time_ns, R_all, P0, q)


def _history_start(
    ok: torch.Tensor, time_ns: torch.Tensor, prior_var: torch.Tensor, q: torch.Tensor
) -> torch.Tensor:
    """The history pass's start [W, D] (the diagonal of P): around the fit, as far as the
    well can have drifted over its history (at least a year's drift, at most the prior):
    the fit is the history's average."""
    first = torch.where(ok, time_ns, torch.full_like(time_ns, NEVER)).min(dim=1).values
    final = torch.where(ok, time_ns, torch.full_like(time_ns, -1)).max(dim=1).values
    span = ((final - first).clamp(min=0).to(DTYPE) / _NS_PER_YEAR).clamp(min=1.0)
    return torch.minimum(prior_var.unsqueeze(0), q.unsqueeze(0) * span.unsqueeze(1))


@functools.cache
def _kernels(module: str) -> Any:
    """The compiled kernels of ``vfm_core.learning.<module>`` (its ``load()``, once), or
    None when the kernels are off or numba is missing (the reference then runs)."""
    try:
        return importlib.import_module(f"vfm_core.learning.{module}").load()
    except ImportError:  # pragma: no cover - numba missing
        return None


def _history_kernel() -> Any:
    """The compiled history pass (:mod:`vfm_core.learning._history_kernels`), or None (the
    torch reference then runs)."""
    return _kernels("_history_kernels")


def _history_pass_torch(
    y: torch.Tensor,
    log_h: torch.Tensor,
    jac: torch.Tensor,
    ok: torch.Tensor,
    time_ns: torch.Tensor,
    R_all: torch.Tensor,
    P0: torch.Tensor,
    q: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """:func:`_history_pass` in torch, all wells a row at a time (the reference of the
    compiled pass, :mod:`vfm_core.learning._history_kernels`)."""
    n_w, n, d = jac.shape
    m = torch.zeros(n_w, d, dtype=DTYPE)
    P = torch.diag_embed(P0)
    eye = torch.eye(d, dtype=DTYPE)
    last = torch.full((n_w,), NEVER, dtype=torch.int64)
    h_last = torch.zeros(n_w, d, dtype=DTYPE)
    innov = torch.zeros(n_w, n, dtype=DTYPE)
    hph_all = torch.zeros(n_w, n, dtype=DTYPE)
    qd = torch.diag_embed(q)
    for k in range(n):
        live = ok[:, k]
        if not bool(live.any()):
            continue
        t = time_ns[:, k]
        dt = torch.where(
            live & (last != NEVER), (t - last).clamp(min=0).to(DTYPE) / _NS_PER_YEAR, 0.0
        )
        P = P + qd.unsqueeze(0) * dt.view(-1, 1, 1)
        H = jac[:, k]
        R = R_all[:, k]
        r = y[:, k] - log_h[:, k] - (H * m).sum(1)
        PH = torch.einsum("wde,we->wd", P, H)
        hph = (PH * H).sum(1)
        S = hph + R
        z = r / S.sqrt()
        # robust: a residual beyond 3 sd counts for less (Huber), one beyond 6 sd not at all
        w = torch.where(z.abs() > 3.0, 3.0 / z.abs(), torch.ones_like(z))
        live = live & (z.abs() <= 6.0)
        Rk = R / w
        K = PH / (hph + Rk).unsqueeze(1)
        m = torch.where(live.unsqueeze(1), m + K * r.unsqueeze(1), m)
        A = eye - torch.einsum("wd,we->wde", K, H)
        P_new = A @ P @ A.transpose(-1, -2) + torch.einsum("wd,we->wde", K, K) * Rk.view(-1, 1, 1)
        P = torch.where(live.view(-1, 1, 1), 0.5 * (P_new + P_new.transpose(-1, -2)), P)
        innov[:, k] = torch.where(ok[:, k], r, 0.0)
        hph_all[:, k] = torch.where(ok[:, k], hph, 0.0)
        h_last = torch.where(ok[:, k].unsqueeze(1), H, h_last)
        last = torch.where(ok[:, k], t, last)
    return m, P, innov, hph_all, h_last, last


def _inverse_spd(a: torch.Tensor) -> torch.Tensor:
    """Inverse of symmetric positive definite matrices [W, D, D] (with a jitter if needed)."""
    a = 0.5 * (a + a.transpose(-1, -2))
    eye = torch.eye(a.shape[-1], dtype=a.dtype)
    for jitter in (0.0, 1e-10, 1e-8, 1e-6):
        chol, info = torch.linalg.cholesky_ex(a + jitter * eye)
        if not bool(info.any()):
            return torch.cholesky_inverse(chol)
    return torch.linalg.pinv(a, hermitian=True)


def laplace_sd(
    model: ChokeModel, batch: Batch, noise: tuple[float, float] = NOISE_DEFAULTS
) -> dict[str, torch.Tensor]:
    """Posterior standard deviation [W] of every physical parameter of a fitted ``model``
    (SI units, keyed like ``model.physical_parameters()``), by a Laplace approximation on
    ``batch`` with the relative noise of each meter estimated as the filter does."""
    blocks = model.filter_blocks()
    if not blocks:
        return {}
    prior_var = torch.cat([b.prior_var for b in blocks])
    cov, _, _, _ = _laplace(
        model, blocks, batch, prior_var, torch.tensor(noise, dtype=DTYPE), (None, None)
    )
    return _physical_sd(blocks, cov)


def _physical_sd(blocks: list[FilterBlock], cov: torch.Tensor) -> dict[str, torch.Tensor]:
    sd = torch.diagonal(cov, dim1=-2, dim2=-1).clamp(min=0).sqrt()
    out: dict[str, torch.Tensor] = {}
    start = 0
    for b in blocks:
        for i, label in enumerate(b.labels):
            if float(b.scale[i]) > 0:
                out[label] = sd[:, start + i] * b.scale[i]
        start += b.size
    return out


def _refresh_text(value: str, method: str) -> str:
    """The ``refresh`` option checked: ``auto``, ``off`` (or 0) or a positive span."""
    value = value.strip()
    if value in ("0", "off"):
        return "off"
    if value != "auto":
        parse_span(value, "refresh period", method)
    return value


def _per_well_hybrid(model: ChokeModel) -> bool:
    """True for a hybrid (``hem``, ``ham``, with or without effects) of per-well networks."""
    return isinstance(model, Mechanistic) and model.net is not None and not model.shared


def _refresh_period(text: str, model: ChokeModel) -> int | None:
    """The refit's period in ns for ``model`` (None: never): ``auto`` refits a shared
    model every :data:`_SHARED_REFRESH`, and a per-well hybrid's wells as often while they
    learn from well tests only (see :meth:`BayesianFilter.start`); no other model."""
    if text == "off" or (text == "auto" and not (model.shared or _per_well_hybrid(model))):
        return None
    span = _SHARED_REFRESH if text == "auto" else parse_span(text, "refresh period", text)
    return int(span.value)


def _pooled_prior(
    count: np.ndarray, total: np.ndarray, nu0: float, outside: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Each well's prior for its well-test variance factor c^2 from the other wells' errors:
    ``(k, c0sq)`` [W], the prior InvGamma(k / 2, k c0sq / 2). ``count`` [W] and ``total``
    [W] are each well's (discounted) number and sum of squared standardised forecast errors;
    ``outside`` [K, 2] the same (count, total) of wells of the field outside this filter
    (the service's one-well filters: :meth:`BayesianFilter.pool_with`).

    Type-II maximum likelihood (empirical Bayes): the prior under which the other wells'
    errors are most likely, each well's errors given (k, c0sq) a scaled multivariate t,
    p(z) ∝ Gamma(k/2 + n/2) / Gamma(k/2) (k c0sq / 2)^(k/2) / (k c0sq / 2 + sum z^2 /
    2)^(k/2 + n/2). The stated prior (c^2 = 1, worth nu0 errors) counts as one more well
    with nu0 errors of z^2 = 1. k, the prior's weight in errors, is the best of
    :data:`_POOL_GRID` in [nu0, nu0 + the other wells' n] (never weaker than the stated
    prior, never worth more errors than it was taken from), c0sq the best for it
    (:data:`_POOL_STEPS` fixed-point steps). Wells that agree give a large k, wells that
    disagree the smallest. A well's own errors are left out of its prior (they update it).
    With no other well's error: k = nu0, c0sq = 1 (the stated prior)."""
    n_w = len(count)
    if outside is not None and len(outside):
        count = np.concatenate([count, outside[:, 0]])
        total = np.concatenate([total, outside[:, 1]])
    kernel = _pool_kernel()
    if kernel is not None:  # the same numbers, one loop per well (see _pool_kernels)
        k, c0sq = np.empty(n_w), np.empty(n_w)
        count, total = np.ascontiguousarray(count, float), np.ascontiguousarray(total, float)
        kernel.pooled_prior(count, total, n_w, float(nu0), _POOL_GRID, _POOL_STEPS, k, c0sq)
        return k, c0sq
    n_o = count.sum() - count[:n_w]
    if not (n_o > 0).any():
        return np.full(n_w, nu0), np.ones(n_w)  # no well has another's errors
    grid = nu0 * ((nu0 + float(count.sum())) / nu0) ** _POOL_GRID  # [G]
    return _pooled_prior_numpy(count, total, n_w, nu0, grid)


def pooled_factor(errors: np.ndarray, nu0: float) -> np.ndarray:
    """Each well's well-test variance factor c^2 [W] with its prior taken from the other
    wells' errors, as ``cal_pool`` gives it to a filter over these wells alone: ``errors``
    [W, 2] each well's (discounted) number and sum of squared standardised forecast errors
    (:meth:`BayesianFilter.well_test_errors`), ``nu0`` the stated prior's weight
    (``cal_prior``, > 0). The scale (k c0sq + sum z^2) / (k + n) of the posterior under the
    prior InvGamma(k / 2, k c0sq / 2) of :func:`_pooled_prior`."""
    count = np.ascontiguousarray(errors[:, 0], dtype=float)
    total = np.ascontiguousarray(errors[:, 1], dtype=float)
    k, c0sq = _pooled_prior(count, total, float(nu0))
    return (k * c0sq + total) / (k + count)


def _pooled_prior_numpy(
    count: np.ndarray, total: np.ndarray, n_w: int, nu0: float, grid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_pooled_prior` in numpy (the reference; ``VFM_KERNELS=0``): ``count`` and
    ``total`` [J0] of the filter's ``n_w`` wells then the outside ones, ``grid`` [G] the
    prior weights searched. Arrays of wells x weights x wells."""
    live = count > 0
    n_o = count.sum() - count[:n_w]
    a = grid[None, :, None] / 2  # [1, G, 1]: k / 2
    # the other wells j of each well w, and the stated prior as one more: [W, 1, J + 1]
    n = np.append(count, nu0)[None, None, :]
    s = np.append(total, nu0)[None, None, :]
    others = np.ones((n_w, len(count) + 1), dtype=bool)
    others[:, :-1] = live[None, :]
    others[np.arange(n_w), np.arange(n_w)] = False
    mask = others[:, None, :]
    m = others.sum(1)[:, None, None]  # [W, 1, 1]
    pooled = ((s * mask).sum(2) / (n * mask).sum(2))[:, :, None]  # [W, 1, 1]
    b = a * pooled  # [W, G, 1]: k c0sq / 2, from the pooled mean
    # the scale's likelihood equation m a / b = sum (a + n/2) / (b + s/2), by fixed point
    for _ in range(_POOL_STEPS):
        b = m * a / np.where(mask, (a + n / 2) / (b + s / 2), 0.0).sum(2, keepdims=True)
    ll = gammaln(a + n / 2) - gammaln(a) + a * np.log(b) - (a + n / 2) * np.log(b + s / 2)
    ll = np.where(mask, ll, 0.0).sum(2)  # [W, G]
    ll = np.where(grid[None, :] <= nu0 + n_o[:, None] + 1e-9, ll, -np.inf)
    best = np.argmax(ll, axis=1)
    k = grid[best]
    return k, 2.0 * b[np.arange(n_w), best, 0] / k


class CalibrationPool:
    """The well-test error statistics of wells whose filters are kept apart (the service's
    one filter a well), so that each well's variance factor takes its prior from all the
    others' errors with ``cal_pool=on`` (:meth:`BayesianFilter.share_errors`).

    Ordered in time, as one filter over all the wells learning the field's measurements
    in time order: a filter reading the pool at time t (a prediction or an update at t)
    counts each other well's (discounted) error count and sum of squares as they were
    after its measurements before t (:meth:`outside`); a filter that learned a well test
    at t publishes its statistics at t (:meth:`publish`). So the order in which threads
    handle wells with measurements at one time does not change the numbers. Thread-safe
    (one lock; the service's workers share one pool per model). Holds two numbers and a
    time per publication, :data:`_POOL_KEEP` publications a well."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._history: dict[str, list[tuple[int, float, float]]] = {}
        #: the latest publication's time (epoch ns), and a count of changes: a reader after
        #: every publication that saw the same count reads the same statistics again
        self.newest = NEVER
        self.generation = 0

    def publish(self, well: str, time_ns: int, count: float, total: float) -> None:
        """``well``'s statistics after its measurement at ``time_ns`` (epoch ns): the
        discounted number ``count`` and sum of squares ``total`` of its standardised
        well-test forecast errors (finite, >= 0). A publication at a time already held
        replaces it (a filter restored from its checkpoint publishes its own again)."""
        if not (math.isfinite(count) and math.isfinite(total) and count >= 0 and total >= 0):
            raise ValueError(
                f"Well {well}'s well-test error statistics must be finite and >= 0, "
                f"not ({count}, {total})."
            )
        with self._lock:
            rows = self._history.setdefault(well, [])
            row = (int(time_ns), float(count), float(total))
            same = [k for k, held in enumerate(rows) if held[0] == row[0]]
            if same:
                rows[same[-1]] = row
            else:
                rows.append(row)
            if len(rows) > 1 and rows[-2][0] > rows[-1][0]:
                rows.sort(key=lambda row: row[0])
            del rows[:-_POOL_KEEP]
            self.newest = max(self.newest, int(time_ns)) if self.newest != NEVER else int(time_ns)
            self.generation += 1  # (after newest: a reader that sees the count sees the time)

    def forget(self, well: str) -> None:
        """Drop ``well`` (removed, or restarted with a new model)."""
        with self._lock:
            self._history.pop(well, None)
            self.generation += 1

    def outside(self, wells: Collection[str], time_ns: int) -> np.ndarray:
        """The statistics [K, 2] (count, sum of squares) of every well not in ``wells`` that
        published before ``time_ns``, each its latest before then; wells in name order."""
        out = []
        with self._lock:
            for well in sorted(self._history):
                if well in wells:
                    continue
                latest = None
                for t, count, total in self._history[well]:
                    if t < time_ns:
                        latest = (count, total)
                if latest is not None:
                    out.append(latest)
        return np.array(out, dtype=float).reshape(-1, 2)


def _first_time(batch: Batch, row: int | None = None) -> int | None:
    """The earliest sample time (epoch ns) of ``batch`` (of its well ``row``), or None."""
    times = batch.time_ns if row is None else batch.time_ns[row]
    mask = batch.mask if row is None else batch.mask[row]
    return int(times[mask].min()) if bool(mask.any()) else None


def _pool_kernel() -> Any:
    """The compiled pooled prior (:mod:`vfm_core.learning._pool_kernels`), or None (the
    numpy reference then runs)."""
    return _kernels("_pool_kernels")


def _positive(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value >= 0):
        raise ValueError("not a number >= 0")
    return value


@register
class BayesianFilter(LearningMethod):
    """``bayes``: see the module docstring."""

    key = "bayes"
    kind = "bayes"
    summary = "a Kalman filter over the model's parameters, with drift and 90 % intervals"
    example = "bayes"
    intervals = True

    def __init__(
        self,
        text: str = "bayes",
        *,
        drift: float = 1.0,
        drifts: dict[str, float] | None = None,
        noise_mpfm: float | None = None,
        noise_well_test: float | None = None,
        iterations: int = 1,
        huber: float = 3.0,
        gate: float = 6.0,
        adapt: float = 0.02,
        calibrate: float = 0.05,
        cal_prior: float = _CAL_PRIOR,
        cal_pool: str = "off",
        params: tuple[str, ...] = (),
        refresh: str = "auto",
    ) -> None:
        super().__init__(text)
        if iterations < 1:
            raise ConfigError(f"Method '{text}': iterations must be at least 1.")
        if not 0.0 <= adapt < 1.0:
            raise ConfigError(f"Method '{text}': adapt must lie in [0, 1).")
        if gate and huber and gate < huber:
            raise ConfigError(f"Method '{text}': gate ({gate}) must not be below huber ({huber}).")
        self.drift = drift
        self.drifts = dict(drifts or {})
        self.noise = (noise_mpfm, noise_well_test)
        #: Kalman iterations per update (1 = the extended filter)
        self.kalman_iterations = iterations
        self.huber = huber
        self.gate = gate
        self.adapt = adapt
        self.calibrate = calibrate
        #: prior weight of the intervals' variance factor (0: the filter's variance as it is)
        self.cal_prior = cal_prior
        if cal_pool not in ("on", "off"):
            raise ConfigError(f"Method '{text}': cal_pool must be 'on' or 'off', not '{cal_pool}'.")
        #: the variance factor's prior from the other wells' errors (see :func:`_pooled_prior`)
        self.cal_pool = cal_pool == "on"
        #: (count, total) [K, 2] of the field's wells outside this filter (:meth:`pool_with`)
        self._outside: np.ndarray | None = None
        #: the pool shared with the other wells' filters (:meth:`share_errors`), if any,
        #: and whether the factors must be put in again at the next reading of it
        self._pool: CalibrationPool | None = None
        self._pool_stale = False
        #: the pool's change count at the last reading after all its publications (-1: none)
        self._pool_seen = -1
        self.params = tuple(params)
        #: the refit's period: ``auto`` (every 14 days for a shared model, else never),
        #: ``off`` or a span such as ``30d`` (see :meth:`retrain_due`)
        self.refresh = _refresh_text(refresh, text)
        self._blocks: list[FilterBlock] = []
        self._layout: dict[str, Any] | None = None

    @classmethod
    def from_text(cls, text: str) -> BayesianFilter:
        rest = text[len(cls.key) :]
        parts = [p for p in rest.split(":") if p]
        drifts = {}
        plain = []
        for part in parts:
            key, _, value = part.partition("=")
            if key.startswith("drift_") and value:
                try:
                    drifts[key[len("drift_") :]] = _positive(value)
                except ValueError:
                    raise ConfigError(
                        f"Method '{text}': {key}='{value}' is not a number >= 0."
                    ) from None
            else:
                plain.append(part)
        options = parse_options(
            text,
            ":".join(plain),
            {
                "drift": _positive,
                "noise_mpfm": _positive,
                "noise_well_test": _positive,
                "iterations": int,
                "huber": _positive,
                "gate": _positive,
                "adapt": _positive,
                "calibrate": _positive,
                "cal_prior": _positive,
                "cal_pool": str,
                "params": lambda v: tuple(p for p in v.split("+") if p),
                "refresh": lambda v: _refresh_text(v, text),
            },
            "bayes:drift=2:noise_well_test=0.01",
        )
        return cls(text, drifts=drifts, **options)

    # -- binding -----------------------------------------------------------------------------
    def bind(self, model: ChokeModel, **kw: Any) -> BayesianFilter:  # type: ignore[override]
        super().bind(model, **kw)
        self._rebind(model)
        n, d = len(model.wells), self._dim
        self._P = torch.zeros(n, d, d, dtype=DTYPE)
        self._last = torch.full((n,), NEVER, dtype=torch.int64)
        self._noise = torch.tensor([self._fixed_or_default(s) for s in (0, 1)], dtype=DTYPE).repeat(
            n, 1
        )
        self._h = torch.zeros(n, d, dtype=DTYPE)
        self._scale = torch.zeros(n, 2, dtype=DTYPE)
        # per meter (MPFM, well test; only the well tests' is learned): the discounted
        # count and sum of squared standardised forecast errors, and the log factor of
        # them already in _scale
        self._cal = torch.zeros(n, 2, 3, dtype=DTYPE)
        # each well's latest publications to its pool (:meth:`share_errors`): time (epoch
        # ns; NEVER: none) and (count, sum of squares), oldest first; a checkpoint keeps
        # them, so a filter restored brings back the statistics others read before its time
        self._sent_t = torch.full((n, _POOL_KEEP), NEVER, dtype=torch.int64)
        self._sent_s = torch.zeros(n, _POOL_KEEP, 2, dtype=DTYPE)
        self._started = torch.zeros(n, dtype=torch.bool)
        self._counts = {
            k: torch.zeros(n, dtype=torch.int64)
            for k in ("updates", "downweighted", "refused", "resets")
        }
        self._run = torch.zeros(n, dtype=torch.int64)
        #: the refit's period (ns; None: none) and each well's next refit (epoch ns)
        self._period = _refresh_period(self.refresh, model)
        self._refresh_at = torch.full((n,), NEVER, dtype=torch.int64)
        #: ``auto`` on a per-well hybrid: a well's refits run while it learns from well
        #: tests only (:meth:`start`, :meth:`_note_meters`; the others keep no meter times)
        self._by_meter = self.refresh == "auto" and _per_well_hybrid(model)
        #: each well's latest measurement the filter saw, per meter (MPFM, well test;
        #: epoch ns, NEVER: none; numpy: an update reads and writes a few of them)
        self._meter_t = np.full((n, 2), NEVER, dtype=np.int64)
        #: the wells whose refit now is followed by another before the filter starts
        self._starts_later = torch.zeros(n, dtype=torch.bool)
        #: True while :meth:`retrain_due` refits (the start then linearises compiled)
        self._refitting = False
        return self

    # -- the refit under the filter (scheduled retrains) ---------------------------------------
    def start(self, t_ns: int) -> None:
        """The refits' calendar (see :meth:`retrain_due`): the first one period after ``t_ns``.
        With ``auto`` on a per-well hybrid, for the wells that learn from well tests only at
        ``t_ns`` (:meth:`_tests_only`); the others get none (NEVER)."""
        if self._period is None:
            return
        at = int(t_ns) + self._period
        if self._by_meter:
            never = torch.full_like(self._refresh_at, NEVER)
            self._refresh_at = torch.where(self._tests_only(int(t_ns)), at, never)
        else:
            self._refresh_at[:] = at

    def _tests_only(self, t_ns: int | torch.Tensor) -> torch.Tensor:
        """Which wells [W] learn from well tests only at ``t_ns`` (epoch ns, or [W]): the
        filter has seen a measurement of theirs, and no MPFM reading in the
        :data:`_MPFM_LAPSE` before (none at all, or its meter failed that long ago)."""
        meter = torch.from_numpy(self._meter_t)
        mpfm = meter[:, 0]
        seen = (meter != NEVER).any(1)
        t = torch.as_tensor(t_ns, dtype=torch.int64)
        lapsed = torch.where(mpfm == NEVER, torch.ones_like(seen), t - mpfm > _MPFM_LAPSE.value)
        return seen & lapsed

    def _note_meters(self, batch: Batch, calendar: bool, wells: torch.Tensor | None = None) -> None:
        """With :attr:`_by_meter`: keep each well's latest measurement per meter from
        ``batch`` (its masked rows; ``wells`` [W]: of these wells only), and with
        ``calendar`` (a batch learned from): an MPFM reading ends a well's refits; a well
        test of a well without refits starts them, one period on, when the well learns from
        well tests only (:meth:`_tests_only`: none before, or a meter failed for
        :data:`_MPFM_LAPSE`)."""
        if not self._by_meter or batch.well_test is None:
            return
        # (plain Python over the rows: an update has one a well, where a torch or numpy
        # call each would cost a third of the compiled step; bench_bayes_update.py)
        held, at = self._meter_t, None
        rows = zip(
            batch.mask.tolist(), batch.well_test.tolist(), batch.time_ns.tolist(), strict=True
        )
        only = None if wells is None else wells.tolist()
        for i, (mask, tests, times) in enumerate(rows):
            if only is not None and not only[i]:
                continue
            for ok, test, t in zip(mask, tests, times, strict=True):
                s = 1 if test else 0
                if not ok or (held[i, s] != NEVER and t <= held[i, s]):
                    continue
                held[i, s] = t
                if not calendar or self._period is None:
                    continue
                at = self._refresh_at.numpy() if at is None else at
                if not test:
                    at[i] = NEVER
                elif at[i] == NEVER and (held[i, 0] == NEVER or t - held[i, 0] > _MPFM_LAPSE.value):
                    at[i] = t + self._period

    @property
    def period(self) -> pd.Timedelta | None:
        """The refit's period (None: no refit), as ``pbl``'s ``period``: the service reads it
        for its shortest retrain period and its catch-up (one refit on everything in place
        of more than ``model.max_catch_up_retrains`` missed ones). Before :meth:`bind`,
        ``auto`` reads as the shared models' period."""
        if hasattr(self, "_period"):
            return None if self._period is None else pd.Timedelta(self._period, unit="ns")
        if self.refresh == "off":
            return None
        if self.refresh == "auto":
            return _SHARED_REFRESH
        return parse_span(self.refresh, "refresh period", self.text)

    def next_due(self) -> int | None:
        """When the next refit of any well falls due (epoch ns), or None (no refit)."""
        if self._period is None or not self._refresh_at.numel():
            return None
        due = int(self._refresh_at.min())
        return None if due == NEVER else due

    def retrain_due(self, memory: Memory, now_ns: torch.Tensor) -> torch.Tensor:
        """Refit the model of every well whose refit is due by ``now_ns`` [W] (MAP, as
        ``pbl`` retrains: warm-started, on every measurement in ``memory`` before the due
        time), and start its filter again from the refit (:meth:`_fitted`: the Kalman pass
        over the refitted history). Why: the filter carries a posterior over each well's
        filter blocks only; the rest of the model (a shared network's layers, the same for
        every well; a per-well network's layers below the output) is a point estimate that
        only a fit on the measurements can move. Refits missed in a gap each run, as
        ``pbl``'s retrains do: each warm-started fit takes the early-stopped count of
        iterations further, so one refit in place of several leaves the model less fitted
        (measured: docs/guide/bayes.md, "Per-well networks on request"); the filter starts
        again after a well's last one only. Returns the refitted wells [W] (bool)."""
        changed = torch.zeros(len(self.model.wells), dtype=torch.bool)
        period = self._period
        if period is None or self.model.gradient_free or self._dim == 0:
            return changed
        at = self._refresh_at.clone()
        due = (at != NEVER) & (now_ns != NEVER) & (at <= now_ns)
        if not bool(due.any()):
            return changed
        if self.model.shared:  # one calendar for the field: every well refits together
            now_ns = torch.full_like(now_ns, int(now_ns[due].max()))
            at = torch.full_like(at, int(at[due].min()))
        self._refitting = True
        try:
            while True:
                due = (at != NEVER) & (now_ns != NEVER) & (at <= now_ns)
                if not bool(due.any()):
                    break
                t = int(at[due].min())
                wells = due & (at == t)
                # a well with another refit due by now starts its filter after that one
                self._starts_later = wells & (at + period <= now_ns)
                self.retrain(memory, t, None if bool(wells.all()) else wells)
                changed |= wells & self.model.ready
                at = torch.where(wells, at + period, at)
        finally:
            self._starts_later = torch.zeros_like(due)
            self._refitting = False
        self._refresh_at = at
        return changed

    def _fixed_or_default(self, s: int) -> float:
        fixed = self.noise[s]
        return float(fixed) if fixed is not None else NOISE_DEFAULTS[s]

    def _rebind(self, model: ChokeModel) -> None:
        blocks = model.filter_blocks()
        labels = [label for b in blocks for label in b.labels]
        unknown = sorted(set(self.params) - set(labels)) + sorted(set(self.drifts) - set(labels))
        if unknown:
            raise ConfigError(
                f"Method '{self.text}': the model {model.name} has no parameter {', '.join(unknown)}; "
                f"its filtered parameters are {', '.join(labels) or 'none'}."
            )
        self._blocks = blocks
        keep = torch.tensor(
            [not self.params or label in self.params for label in labels], dtype=torch.bool
        )
        self._labels = labels
        self._keep = keep
        prior_var = torch.cat([b.prior_var for b in blocks]) if blocks else torch.zeros(0)
        drift = torch.cat([b.drift for b in blocks]) if blocks else torch.zeros(0)
        drift = drift * self.drift
        for i, label in enumerate(labels):
            if label in self.drifts:
                drift[i] = self.drifts[label]
        # a parameter left out of the filter keeps its fitted value: no uncertainty, no drift
        self._prior_var = torch.where(keep, prior_var, torch.full_like(prior_var, 1e-30))
        # ... and a well's filter without a fit starts at (the blocks' start_var: the prior,
        # but none for a hybrid's output weights, see WellMLP.head_blocks)
        start_var = torch.cat([b.start_var for b in blocks]) if blocks else torch.zeros(0)
        self._start_var = torch.where(keep, start_var, self._prior_var)
        self._q = torch.where(keep, drift**2, torch.zeros_like(drift))
        self._dim = len(labels)
        self._layout = self._compiled_layout(model, blocks)

    def _compiled_layout(self, model: Any, blocks: list[FilterBlock]) -> dict[str, Any] | None:
        """What the compiled filter needs of ``model`` that does not change between updates
        (see :attr:`compiled`), or None where it does not apply."""
        if self.kalman_iterations != 1 or not blocks:
            return None
        params = [b.param for b in blocks]
        # with compiled effects (rate factors, real gas, slip): their parameters after the physics'
        base = compiled_effects(model)
        if plain_mm(model) or base == "mm":
            mine = effect_parameters(model)  # z, then each effect's (none: the plain mm)
            if [id(p) for p in params] != [id(q) for q in mine]:
                return None
            kind, lower = 0, None
        elif plain_hybrid(model) or base in ("hem", "ham"):
            net = model.net
            head = [*effect_parameters(model), net.weights[-1], net.biases[-1]]
            if [id(p) for p in params] != [id(q) for q in head]:
                return None
            kind, lower = (
                (2 if (base or model.compiled_as()) == "ham" else 1),
                (net.weights[0], net.biases[0]),
            )
        else:
            return None
        pos, mu, sigma = physics_layout(model)
        n_phys = len(model.phys.names)
        low, high = model.phys.z_low.numpy(), model.phys.z_high.numpy()
        e_low, e_high = effect_bounds(model)
        low, high = np.concatenate([low, e_low]), np.concatenate([high, e_high])
        if kind:
            free = np.full(self._dim - len(low), np.inf)  # the output layer: no bounds
            low, high = np.concatenate([low, -free]), np.concatenate([high, free])
        return {
            "kind": kind,
            "lower": lower,  # a hybrid's first layer (W1, b1): read as it is at each update
            "pos": pos,
            "mu": mu,
            "sigma": sigma,
            "n_phys": n_phys,
            "low": low,
            "high": high,
            # the filter's constants, in the order the compiled step reads them
            "rules": (
                low,
                high,
                self._start_var.numpy(),
                self._q.numpy(),
                self._keep.to(torch.float64).numpy(),
                np.array([self.noise[0] is not None, self.noise[1] is not None]),
                float(self.huber),
                float(self.gate),
                float(self.adapt),
                float(self.calibrate),
                int(NEVER),
                _RESET_AFTER,
                _NOISE_FLOOR,
                Z90,
                _NS_PER_YEAR,
            ),
            "blocks": [(b.param, b.size) for b in blocks],
        }

    # -- start ---------------------------------------------------------------------------------
    def _fitted(self, batch: Batch, wells: torch.Tensor) -> None:
        """Start the filter from a batch fit: a Kalman pass over the fitted history.

        A batch fit treats the history as if the well never changed, so for a drifting well
        it lands on the history's average, not on its end. The filter therefore runs over the
        history rows in time order, linearised at the fit (one Jacobian, no more model
        evaluations), starting around the fit with the spread the well can have drifted
        over its history (at least a year's, at most the prior's); its state at the last row is
        where the well is now. The noise of each meter comes from the fit's residuals,
        corrected for the parameters it took and shrunk towards the defaults when a meter
        has few rows."""
        # the fitted wells' meters only: a refit of some wells reads the memory up to its
        # due time, which may hold another well's measurements that well has not learned
        # yet (the study's rounds let wells run ahead); noted here, they were skipped when
        # it learned them, and a young well's refits never started (helper refresh57)
        self._note_meters(batch, calendar=False, wells=wells)
        if self._dim == 0 or self.model.gradient_free:
            return
        if bool(self._starts_later.any()):  # a refit with another one due before the filter
            wells = wells & ~self._starts_later
            if not bool(wells.any()):
                return
        model, blocks = self.model, self._blocks
        order = torch.argsort(
            torch.where(batch.mask, batch.time_ns, torch.full_like(batch.time_ns, NEVER)),
            dim=1,
            stable=True,
        )
        batch = _reorder(batch, order)
        theta = _flat(blocks, batch.n_wells)
        log_h, jac = self._linearised(batch, wells)
        ok = batch.mask & (batch.y > 0) & torch.isfinite(log_h) & wells.unsqueeze(1)
        y = torch.log(torch.where(ok, batch.y, torch.ones_like(batch.y)))
        src = _source(batch)
        defaults = torch.tensor([self._fixed_or_default(0), self._fixed_or_default(1)], dtype=DTYPE)
        # each meter's noise: the fit's residuals, with the degrees of freedom the fit took
        residual = torch.where(ok, y - log_h, torch.zeros_like(y))
        dof = float(int(self._keep.sum()) + 1)
        noise = self._fix_noise(_noise_from(residual, ok, src, defaults, dof))
        # ... then, for a well that drifted (its residuals hold the drift), from the pass's
        # one-step-ahead errors once the pass has settled (after a fifth of the rows)
        m, P, innov, _, h_last, t_last = _history_pass(
            y, log_h, jac, ok, src, batch.time_ns, noise, self._prior_var, self._q
        )
        rank = torch.cumsum(ok.long(), 1)
        settled = ok & (rank > (0.2 * ok.sum(1, keepdim=True)).clamp(min=dof))
        noise = torch.minimum(
            noise, self._fix_noise(_noise_from(innov, settled, src, defaults, dof))
        )
        m, P, _, _, h_last, t_last = _history_pass(
            y, log_h, jac, ok, src, batch.time_ns, noise, self._prior_var, self._q
        )
        has = wells & (t_last != NEVER)
        _assign(blocks, theta + m, has)
        model.project_()
        self._P[has] = P[has]
        self._noise[has] = noise[has]
        self._h[has] = h_last[has]
        self._last[has] = t_last[has]
        self._started |= has
        self._apply_calibration()

    def _linearised(self, batch: Batch, wells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """log h [W, N] and its sensitivity J [W, N, D] (masked by ``keep``) at the current
        parameters, for the start's Kalman passes. After a refit (:meth:`retrain_due`) with
        the compiled filter (:attr:`compiled`): J from the compiled closed-form gradient the
        updates take, at the refitted wells' samples only (the others' rows are not read);
        it differs from the central differences by their truncation error (measured 1e-12
        to 1e-7 relative). Otherwise (the first fit, the torch path) by central differences over
        every well (2 D model evaluations of the whole history: 90 % of a refit's cost on a
        case-1 field; docs/guide/bayes.md, "Per-well networks on request", session 50)."""
        model = self.model
        kernel = compiled()
        if (
            getattr(self, "_refitting", False)
            and kernel is not None
            and self._layout is not None
            and bool(model.ready[wells].all())
        ):
            with torch.no_grad():
                log_h = torch.log(torch.clamp(predict_rates(model, batch), min=1e-12))
            only = replace(batch, mask=batch.mask & wells.unsqueeze(1))
            return log_h, self._compiled_gradients(kernel, only)
        log_h, jac = _jacobian_fd(model, self._blocks, batch)
        return log_h, jac * self._keep.to(DTYPE)

    def _fix_noise(self, noise: torch.Tensor) -> torch.Tensor:
        for s in (0, 1):
            if self.noise[s] is not None:
                noise[:, s] = float(self.noise[s])  # type: ignore[arg-type]
        return noise

    def _grow(self, now: torch.Tensor) -> torch.Tensor:
        """P after the drift from each well's last update to ``now`` [W] (not stored)."""
        dt = torch.where(
            (self._last != NEVER) & (now != NEVER),
            (now - self._last).clamp(min=0).to(DTYPE) / _NS_PER_YEAR,
            torch.zeros(len(now), dtype=DTYPE),
        )
        return self._P + torch.diag_embed(self._q.unsqueeze(0) * dt.unsqueeze(1))

    # -- predictions ---------------------------------------------------------------------------
    def predict(self, batch: Batch) -> Forecast:
        mean = predict_rates(self.model, batch)
        if self._dim == 0 or self.model.gradient_free:
            return Forecast(mean)
        self._sync_pool(batch)
        return self._forecast(mean, batch)

    def _forecast(
        self, mean: torch.Tensor, batch: Batch, h: torch.Tensor | None = None
    ) -> Forecast:
        """The forecast of the rates ``mean`` [W, N] of ``batch``: their spread from the
        filter's state, with ``h`` [W, N, D] the sensitivity at each sample (by default
        :meth:`_sample_gradients`)."""
        if h is None:
            h = self._sample_gradients(batch)
        kernel = compiled()
        if kernel is not None:  # the same numbers, compiled (any model)
            return self._compiled_spread(kernel, mean, batch, h)
        sd = self._spread(batch.time_ns, _source(batch), h)
        missing = ~self._started.unsqueeze(1).expand_as(mean)
        nan = torch.full_like(mean, float("nan"))
        sd = torch.where(missing, nan, sd)
        return Forecast(mean, mean * sd, mean * torch.exp(-Z90 * sd), mean * torch.exp(Z90 * sd))

    def _spread(self, time_ns: torch.Tensor, src: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """Predictive sd of the log rate [W, N] at these times, for these meters, with ``h``
        [W, N, D] the sensitivity at each sample: the parameters' variance h (P + Q dt) h,
        plus the meter's noise, times the calibration factor of that meter."""
        var = self._variance(time_ns, src, h)
        return var.clamp(min=0).sqrt() * torch.exp(torch.gather(self._scale, 1, src))

    def _variance(self, time_ns: torch.Tensor, src: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """Predictive variance of the log rate [W, N] at these times, for these meters,
        without the intervals' factors: h (P + Q dt) h + s^2, h [W, N, D] at each sample.
        The sensitivity is taken at the predicted sample, not at the well's last measured
        one: for a hybrid its output-layer part is the network's hidden activations there
        (the predictive variance of last-layer learning), and the last measured sample is
        the direction the last update shrank P along (its h P h about the smallest)."""
        hph = torch.einsum("wnd,wde,wne->wn", h, self._P, h)
        hqh = (h**2 * self._q).sum(-1)
        dt = torch.where(
            self._last.unsqueeze(1) != NEVER,
            (time_ns - self._last.unsqueeze(1)).clamp(min=0).to(DTYPE) / _NS_PER_YEAR,
            torch.zeros(time_ns.shape, dtype=DTYPE),
        )
        noise = torch.gather(self._noise, 1, src) ** 2
        return hph + hqh * dt + noise

    def _sample_gradients(self, batch: Batch) -> torch.Tensor:
        """The sensitivity h [W, N, D] of each sample's log rate to the filtered parameters
        at their current values, masked by ``keep`` (as an update takes it); the stored h
        (at the well's last measured sample) where there is no sample or no model. Compiled
        for the compiled filter (:meth:`_compiled_gradients`), else by one batched backward
        pass over the columns (:meth:`_torch_sample_gradients`)."""
        kernel = compiled()
        if kernel is not None and self._layout is not None:
            return self._compiled_gradients(kernel, batch)
        n_w, n = batch.y.shape
        keep = self._keep.to(DTYPE)
        out = self._h.unsqueeze(1).expand(n_w, n, self._dim).clone()
        live = batch.mask & self.model.ready.unsqueeze(1)  # [W, N]
        if bool(live.any()):
            H = self._torch_sample_gradients(batch, live)
            out = torch.where(live.unsqueeze(2), H * keep, out)
        return out

    def _torch_sample_gradients(self, batch: Batch, live: torch.Tensor) -> torch.Tensor:
        """The gradient [W, N, D] of every sample's log rate to the filtered parameters: one
        forward pass of the whole batch, then backward passes batched over its columns
        (``is_grads_batched``, :data:`_GRAD_COLUMNS` at a time). A well's rate depends only
        on its own parameters and a sample's only on its own inputs, so the gradient of
        column k's rates summed over the wells is, per well, that sample's gradient."""
        blocks = self._blocks
        n_w, n = live.shape
        params = [b.param for b in blocks]
        parts: list[torch.Tensor] = []
        with torch.enable_grad():
            log_h = _log_rate(self.model, batch)  # [W, N]
            weight = live.to(log_h.dtype)
            for start in range(0, n, _GRAD_COLUMNS):
                cols = torch.arange(start, min(start + _GRAD_COLUMNS, n))
                seeds = torch.zeros(len(cols), n_w, n, dtype=log_h.dtype)
                seeds[torch.arange(len(cols)), :, cols] = weight[:, cols].T
                grads = torch.autograd.grad(
                    log_h,
                    params,
                    grad_outputs=seeds,
                    is_grads_batched=True,
                    retain_graph=start + _GRAD_COLUMNS < n,
                    allow_unused=True,
                )
                parts.append(
                    torch.cat(
                        [
                            (g if g is not None else torch.zeros(len(cols), *b.param.shape))
                            .reshape(len(cols), n_w, -1)
                            .detach()
                            for g, b in zip(grads, blocks, strict=True)
                        ],
                        dim=2,
                    )
                )
        return torch.cat(parts, 0).permute(1, 0, 2)  # [W, N, D]

    # -- many wells at once ----------------------------------------------------------------------
    def group_key(self) -> Hashable | None:
        """Filters of the same text and drift on models of one specification predict together
        (their means in one model call, their spreads from their stacked states); a model
        with nothing to filter predicts with the model alone."""
        if type(self).predict is not BayesianFilter.predict:
            return None
        model = self.model
        cached = self.__dict__.get("_group")
        if cached is not None and cached[0] is model and cached[1] is self._q:
            return cached[2]  # type: ignore[no-any-return]
        if model.gradient_free or self._dim == 0:
            key: Hashable = ("bayes-mean", model.stack_key())
        else:
            key = ("bayes", model.stack_key(), self.text, tuple(self._q.tolist()))
        self.__dict__["_group"] = (model, self._q, key)
        return key

    @classmethod
    def predict_group(cls, methods: Sequence[LearningMethod], batch: Batch) -> Forecast:
        mean = stacked_rates([m.model for m in methods], batch)
        first = methods[0]
        assert isinstance(first, BayesianFilter)
        if first.model.gradient_free or first._dim == 0:
            return Forecast(mean)
        hs, start = [], 0
        for k, method in enumerate(methods):  # each well's prior from the pool at its time
            assert isinstance(method, BayesianFilter)
            method._sync_pool(batch, k)
            stop = start + method._h.shape[0]  # h at each sample, from each well's own model
            hs.append(method._sample_gradients(_well_rows(batch, start, stop)))
            start = stop
        return cls._joined(methods, _PREDICT_STATE)._forecast(mean, batch, torch.cat(hs, 0))

    @staticmethod
    def _joined(methods: Sequence[LearningMethod], names: tuple[str, ...]) -> BayesianFilter:
        """A copy of the first filter with the filters' states ``names`` stacked by well."""
        filters = [m for m in methods if isinstance(m, BayesianFilter)]
        assert len(filters) == len(methods)
        joint = copy.copy(filters[0])
        for name in names:
            setattr(joint, name, torch.cat([getattr(f, name) for f in filters], 0))
        return joint

    def _on(self, model: ChokeModel) -> None:
        """Run this (joined) filter on ``model``: its filter blocks are the model's."""
        self._model = model
        self._rebind(model)

    def learn_key(self) -> Hashable | None:
        """Filters of exactly this class with the same text (every option) on gradient models
        of one specification learn together: the Kalman step written for many wells, on
        their stacked states; with ``cal_pool``, only those sharing one pool (the stacked
        step reads and publishes through the first one's: :meth:`share_errors`)."""
        if type(self) is not BayesianFilter or self.model.gradient_free or self._dim == 0:
            return None
        pool = None if self._pool is None else id(self._pool)
        return ("bayes", self.model.stack_key(), self.text, pool)

    @classmethod
    def learn_group(
        cls,
        methods: Sequence[LearningMethod],
        batches: Sequence[Batch],
        memories: Sequence[Memory | None],
    ) -> list[bool | None]:
        """The Kalman steps of the wells that are ready, as one multi-well step on the stacked
        models with the filters' states stacked (as the study updates a field's wells in one
        call); each well's parameters and filter state are written back after it ran."""
        ready = ready_for_group(methods, batches)
        out: list[bool | None] = [None] * len(methods)
        if len(ready) < 2:
            return out
        filters = [methods[k] for k in ready]
        stacked, batch = stack_for_learning([m.model for m in filters], [batches[k] for k in ready])
        for k in ready:  # each its own meters (and refit calendar); the joint none
            methods[k]._note_meters(batches[k], calendar=True)  # type: ignore[attr-defined]
        joint = cls._joined(filters, _LEARN_STATE)
        joint._by_meter = False
        joint._on(stacked.model)
        joint._counts = {
            name: torch.cat([f._counts[name] for f in filters], 0)  # type: ignore[attr-defined]
            for name in joint._counts
        }
        changed = joint._learn(batch, None)
        # every step ran: each well's parameters, then its filter state
        stacked.store([m.model for m in filters])
        for name in _LEARN_STATE:
            for f, row in zip(filters, getattr(joint, name).split(1, 0), strict=True):
                setattr(f, name, row.clone())
        for name, value in joint._counts.items():
            for f, row in zip(filters, value.split(1, 0), strict=True):
                f._counts[name] = row.clone()  # type: ignore[attr-defined]
        for f in filters:  # (their factors were put in beside each other: again alone)
            f._pool_stale = True  # type: ignore[attr-defined]
        for k, moved in zip(ready, changed.tolist(), strict=True):
            out[k] = bool(moved)
        return out

    # -- learning -----------------------------------------------------------------------------
    def _learn(self, batch: Batch, memory: Memory | None) -> torch.Tensor:
        model = self.model
        model.setup(batch)
        changed = torch.zeros(batch.n_wells, dtype=torch.bool)
        self._note_meters(batch, calendar=True)
        if self._dim == 0:
            return changed
        assert batch.well_test is not None
        # the well tests' variance factor: their forecast errors before learning from them
        wanted = self.cal_prior > 0 and bool(batch.well_test.any())
        fresh = self.cal_prior > 0 and not bool(self._started.all())
        self._sync_pool(batch)
        if self.compiled:  # the plain mm: the same steps, compiled (the errors learned too)
            changed, learned = self._compiled_learn(batch, wanted)
        else:
            changed, learned = self._torch_learn(batch, wanted)
        if learned or fresh:
            self._apply_calibration()
        if learned:
            self._publish(batch)
        return changed

    def _torch_learn(self, batch: Batch, wanted: bool) -> tuple[torch.Tensor, bool]:
        """:meth:`_learn` in torch: the k-th measurement of every well together, one extended
        Kalman step each (:meth:`_update`); when ``wanted``, the well tests' forecast errors
        learned into the variance factor's statistics: from the update's own forecast when
        each well has one measurement, else from a forecast of them all first
        (:meth:`_forecast_errors`), both from the state before the batch. Returns which
        wells took a measurement [W] and whether any forecast error was learned."""
        changed = torch.zeros(batch.n_wells, dtype=torch.bool)
        counts = batch.count()
        rows = int(counts.max()) if counts.numel() else 0
        errors = self._forecast_errors(batch) if wanted and rows > 1 else None
        own: list[tuple[np.ndarray, np.ndarray]] | None = [] if wanted and rows == 1 else None
        for k in range(rows):
            one = batch.select(torch.cumsum(batch.mask.long(), 1) == k + 1)
            changed |= self._update(one, own)
        if own and own[0][1].any():
            errors = own[0]
        if errors is not None:
            self._learn_calibration(*errors)
        return changed, errors is not None

    # -- the intervals' variance factor ------------------------------------------------------
    def _forecast_errors(self, batch: Batch) -> tuple[np.ndarray, np.ndarray] | None:
        """The squared standardised errors [W, N] of the forecasts the filter gave for the
        well tests of ``batch`` before learning from them: the log error over the filter's
        own spread sqrt(h (P + Q dt) h + s^2) (:meth:`_spread` without the intervals'
        factors, h at each well test's sample), and which count [W, N] (well tests of a well with a started filter and
        a model); None when none does. The compiled filter computes the same errors in its
        update pass (:meth:`_compiled_learn`), the torch path from its update's own forecast
        when each well has one measurement (:meth:`_update`); this is the reference, and
        the torch path's for batches with more."""
        assert batch.well_test is not None
        y = batch.y.numpy()
        live = batch.mask.numpy() & batch.well_test.numpy() & (y > 0)
        live &= (self.model.ready.numpy() & self._started.numpy())[:, None]
        if not live.any():
            return None
        mean = predict_rates(self.model, batch).detach().numpy()
        h = self._sample_gradients(batch).numpy()  # at each well test's sample
        P, last = self._P.numpy(), self._last.numpy()
        hph = np.einsum("wnd,wde,wne->wn", h, P, h)
        hqh = (h**2 * self._q.numpy()).sum(-1)
        dt = np.maximum(batch.time_ns.numpy() - last[:, None], 0) / _NS_PER_YEAR
        var = hph + hqh * dt + self._noise.numpy()[:, 1:2] ** 2
        z2 = np.log(np.where(live, y, 1.0) / np.where(live, mean, 1.0)) ** 2 / var
        live &= np.isfinite(z2)
        # an error beyond the gate (a refused measurement) counts as one at the gate
        return np.minimum(np.where(live, z2, 0.0), (self.gate or 6.0) ** 2), live

    def _own_errors(
        self, error: torch.Tensor, var: torch.Tensor, counted: torch.Tensor
    ) -> tuple[np.ndarray, np.ndarray]:
        """The squared standardised forecast errors [W, 1] of an update's forecast (log
        ``error`` [W], its variance ``var`` [W]) and which count [W, 1] (``counted``, where
        finite), capped at the gate as in :meth:`_forecast_errors`."""
        z2 = (error**2 / var).numpy()[:, None]
        live = counted.numpy()[:, None] & np.isfinite(z2)
        return np.minimum(np.where(live, z2, 0.0), (self.gate or 6.0) ** 2), live

    def _learn_calibration(self, z2: np.ndarray, live: np.ndarray) -> None:
        """Learn each well's well-test variance factor c^2 from the squared standardised
        forecast errors ``z2`` [W, N]: with the prior c^2 ~ InvGamma(nu0 / 2, nu0 / 2) (the
        filter's variance is right, as much as nu0 = ``cal_prior`` errors say) the
        posterior after n errors is InvGamma((nu0 + n) / 2, (nu0 + sum z^2) / 2), each
        error discounting the older ones by :data:`_CAL_DISCOUNT`."""
        cal = writable(self, "_cal")
        for k in range(z2.shape[1]):
            w = np.flatnonzero(live[:, k])
            cal[w, 1, 0] = _CAL_DISCOUNT * cal[w, 1, 0] + 1.0
            cal[w, 1, 1] = _CAL_DISCOUNT * cal[w, 1, 1] + z2[w, k]

    def _factor_prior(self, count: np.ndarray, total: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each well's prior InvGamma(k / 2, k c0sq / 2) for its well-test variance factor:
        ``(k, c0sq)`` [W], from the other wells' errors (:func:`_pooled_prior`) with
        ``cal_pool``, else the stated one (k = nu0 = ``cal_prior``, c0sq = 1)."""
        nu0 = float(self.cal_prior)
        if self.cal_pool:
            return _pooled_prior(count, total, nu0, self._outside)
        return np.full(len(count), nu0), np.ones(len(count))

    def _apply_calibration(self) -> None:
        """Put each started well's variance factor into its intervals: with the prior
        InvGamma(k / 2, k c0sq / 2) (:meth:`_factor_prior`; k = nu0, c0sq = 1 unpooled) the
        forecast of a log rate is a Student t with k + n degrees of freedom and scale
        sqrt((k c0sq + sum z^2) / (k + n)) times the filter's spread, so the central 90 %
        interval's half-width is t_0.95(k + n) sqrt(...) sd instead of 1.645 sd. Few
        errors give a heavy tail (t_0.95(2) = 2.92), many the normal's 1.645 times what
        the errors say. Kept in ``_scale`` (log), beside the conformal factor."""
        if self.cal_prior <= 0:
            return
        cal, scale = writable(self, "_cal"), writable(self, "_scale")
        # the well tests' factor only (MPFM readings come twice a day: the conformal factor
        # calibrates them within weeks; their log factor cal[:, 0, 2] stays 0)
        count, total, before = cal[:, 1, 0], cal[:, 1, 1], cal[:, 1, 2]
        k, c0sq = self._factor_prior(count, total)
        nu = k + count
        log_f = np.log(stdtrit(nu, 0.95) / Z90) + 0.5 * np.log((k * c0sq + total) / nu)
        log_f = np.where(self._started.numpy(), log_f, before)
        scale[:, 1] += log_f - before
        cal[:, 1, 2] = log_f

    def _start_filters(self, one: Batch, live: torch.Tensor) -> None:
        """Start the filter of each ``live`` well that has a model but no filter state yet
        (no fit: set up on its first measurement): its start variance (the prior, but none
        for a hybrid's output weights: :meth:`~vfm_core.models.base.WellMLP.head_blocks`),
        its clock at ``one``."""
        fresh = live & ~self._started
        if bool(fresh.any()):
            self._P[fresh] = torch.diag_embed(self._start_var).expand(int(fresh.sum()), -1, -1)
            self._last[fresh] = one.time_ns[fresh, 0]
            self._started |= fresh

    def _calibrate_intervals(
        self,
        y: torch.Tensor,
        log_h: torch.Tensor,
        sd_given: torch.Tensor,
        live: torch.Tensor,
        src: torch.Tensor,
    ) -> None:
        """Adaptive conformal calibration: was the measurement ``y`` (log) inside the 90 %
        interval given for it (``sd_given``)? A miss widens that meter's intervals, a hit
        narrows them a little: in the long run 90 % fall inside, whatever the model lacks."""
        miss = (y - log_h).abs() > Z90 * sd_given
        step = self.calibrate * (miss.to(DTYPE) - 0.1)
        rows = torch.arange(len(y))[live]
        self._scale[rows, src[live]] += step[live]

    def _screen(
        self,
        y: torch.Tensor,
        log_h: torch.Tensor,
        H: torch.Tensor,
        P: torch.Tensor,
        R: torch.Tensor,
        live: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The outlier screen on the standardised innovation: ``(live, weight, P)``. A
        measurement beyond ``gate`` is refused (after :data:`_RESET_AFTER` refusals in a row
        the well has changed: a year's drift is added to ``P`` and it is taken), one beyond
        ``huber`` down-weighted (``weight`` < 1 divides its noise variance)."""
        S0 = torch.einsum("wd,wde,we->w", H, P, H) + R
        z = (y - log_h) / S0.sqrt()
        weight = torch.ones(len(y), dtype=DTYPE)
        if self.huber:
            weight = torch.where(z.abs() > self.huber, self.huber / z.abs(), weight)
        refused = live & (z.abs() > self.gate) if self.gate else torch.zeros_like(live)
        self._run = torch.where(refused, self._run + 1, torch.where(live, 0, self._run))
        reset = refused & (self._run >= _RESET_AFTER)
        if bool(reset.any()):  # the well changed: a year's drift, then take it
            P = P + torch.diag_embed(self._q).unsqueeze(0) * reset.view(-1, 1, 1)
            self._counts["resets"] += reset.long()
            self._run = torch.where(reset, 0, self._run)
            refused = refused & ~reset
            weight = torch.where(reset, torch.ones_like(weight), weight)
        self._counts["refused"] += refused.long()
        self._counts["downweighted"] += (live & ~refused & (weight < 1)).long()
        return live & ~refused, weight, P

    def _joseph_covariance(
        self, K: torch.Tensor, H: torch.Tensor, P: torch.Tensor, Rk: torch.Tensor
    ) -> torch.Tensor:
        """The parameters' covariance after the update [W, D, D], in Joseph form
        (A P A' + K Rk K', A = I - K H), made exactly symmetric."""
        eye = torch.eye(self._dim, dtype=DTYPE)
        A = eye - torch.einsum("wd,we->wde", K, H)
        P_new = A @ P @ A.transpose(-1, -2) + torch.einsum("wd,we->wde", K, K) * Rk.view(-1, 1, 1)
        return 0.5 * (P_new + P_new.transpose(-1, -2))

    def _adapt_noise(
        self,
        y: torch.Tensor,
        h0: torch.Tensor,
        H0: torch.Tensor,
        P: torch.Tensor,
        R: torch.Tensor,
        live: torch.Tensor,
        src: torch.Tensor,
    ) -> None:
        """The meter's noise follows the innovations (their variance beyond the parameters',
        capped as the Huber weight caps them), at rate ``adapt``; a noise given fixed stays."""
        r0 = y - h0
        hph = torch.einsum("wd,wde,we->w", H0, P, H0)
        cap = (self.huber or 3.0) ** 2 * (hph + R)
        sample = torch.clamp(r0**2, max=cap) - hph
        new = (1 - self.adapt) * R + self.adapt * sample.clamp(min=_NOISE_FLOOR**2)
        fixed = torch.tensor([self.noise[0] is not None, self.noise[1] is not None])
        upd = live & ~fixed[src]
        idx = torch.arange(len(y))[upd]
        self._noise[idx, src[upd]] = new[upd].sqrt().clamp(min=_NOISE_FLOOR)

    def _update(
        self, one: Batch, errors: list[tuple[np.ndarray, np.ndarray]] | None = None
    ) -> torch.Tensor:
        """One measurement per well (masked where none): an iterated EKF step in log space.
        With ``errors``, the well tests' squared standardised forecast errors and which count
        [W, 1] are appended (as :meth:`_forecast_errors` gives them)."""
        model, blocks, n = self.model, self._blocks, one.n_wells
        live = one.mask[:, 0] & model.ready & (one.y[:, 0] > 0)
        counted = live & self._started & _source(one)[:, 0].bool()  # a started well's test
        self._start_filters(one, live)
        if not bool(live.any()):
            return live
        t = torch.where(live, one.time_ns[:, 0], self._last)
        src = _source(one)[:, 0]
        m = _flat(blocks, n)
        theta = m.clone()
        keep = self._keep.to(DTYPE)
        log_h, H = self._linearise(one, theta, live)  # the first iteration's, h at this sample
        H = H * keep
        # the spread the filter gave this measurement before it arrived (for calibration)
        h_given = torch.where(live.unsqueeze(1), H, self._h).unsqueeze(1)
        sd_given = self._spread(one.time_ns[:, :1], src.unsqueeze(1), h_given)[:, 0]
        if errors is not None:  # ... and its variance without the intervals' factors
            var_given = self._variance(one.time_ns[:, :1], src.unsqueeze(1), h_given)[:, 0]
        P = self._grow(t)
        self._P = torch.where(live.view(-1, 1, 1), P, self._P)
        self._last = torch.where(live, t, self._last)
        y = torch.log(torch.where(live, one.y[:, 0], torch.ones(n, dtype=DTYPE)))
        R = self._noise[torch.arange(n), src] ** 2
        h0 = None
        Rk = R.clone()
        for i in range(self.kalman_iterations):
            if i > 0:
                log_h, H = self._linearise(one, theta, live)
                H = H * keep
            if i == 0:
                h0, H0 = log_h, H
                if errors is not None:
                    errors.append(self._own_errors(y - log_h, var_given, counted))
                if self.calibrate > 0:
                    self._calibrate_intervals(y, log_h, sd_given, live, src)
                live, weight, P = self._screen(y, log_h, H, P, R, live)
                if not bool(live.any()):
                    return live
                Rk = R / weight
            S = torch.einsum("wd,wde,we->w", H, P, H) + Rk
            K = torch.einsum("wde,we->wd", P, H) / S.unsqueeze(1)
            innov = y - log_h - torch.einsum("wd,wd->w", H, m - theta)
            theta = torch.where(live.unsqueeze(1), m + K * innov.unsqueeze(1), m)
        assert h0 is not None
        self._P = torch.where(live.view(-1, 1, 1), self._joseph_covariance(K, H, P, Rk), self._P)
        _assign(blocks, theta, live)
        model.project_()
        self._h = torch.where(live.unsqueeze(1), H0, self._h)
        if self.adapt > 0:
            self._adapt_noise(y, h0, H0, P, R, live, src)
        self._counts["updates"] += live.long()
        return live

    def _linearise(
        self, one: Batch, theta: torch.Tensor, live: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """log h [W] and its gradient [W, D] at ``theta`` (one sample per well)."""
        model, blocks = self.model, self._blocks
        n = one.n_wells
        saved = _flat(blocks, n)
        if torch.equal(theta, saved):
            # at the current parameters (the first Kalman iteration): nothing to set or
            # restore, the parameters are kept within their bounds
            return self._log_rate_and_gradient(one, live)
        _assign(blocks, theta, live)
        model.project_()
        try:
            return self._log_rate_and_gradient(one, live)
        finally:
            _assign(blocks, saved, torch.ones(n, dtype=torch.bool))

    def _log_rate_and_gradient(
        self, one: Batch, live: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """log h [W] and its gradient [W, D] at the model's parameters (one sample per well)."""
        model, blocks = self.model, self._blocks
        n = one.n_wells
        with torch.enable_grad():
            log_h = _log_rate(model, one)[:, 0]
            total = torch.where(live, log_h, torch.zeros_like(log_h)).sum()
            grads = torch.autograd.grad(total, [b.param for b in blocks], allow_unused=True)
        H = torch.cat(
            [
                (g if g is not None else torch.zeros_like(b.param)).reshape(n, -1)
                for g, b in zip(grads, blocks, strict=True)
            ],
            dim=1,
        )
        return log_h.detach(), H.detach()

    # -- compiled (the plain mm) ------------------------------------------------------------
    @property
    def compiled(self) -> bool:
        """True when the compiled filter (:func:`vfm_core.learning.kernels.compiled`) runs
        this filter's updates: one Kalman iteration per update, on the plain ``mm`` (see
        :func:`~vfm_core.learning.kernels.plain_mm`) with its parameters the one filter
        block, or on the plain ``hem`` or ``ham`` (see
        :func:`~vfm_core.learning.kernels.plain_hybrid`) with its parameters and its
        network's output layer, or on either with effects that all have a compiled form
        (:func:`~vfm_core.learning.kernels.compiled_effects`: their parameters after the
        physical ones), and the kernels enabled. The same steps as :meth:`_update`,
        in the same order (``tests/test_kernels.py``)."""
        return self._layout is not None and kernels_enabled()

    def _compiled_learn(self, batch: Batch, wanted: bool) -> tuple[torch.Tensor, bool]:
        """:meth:`_learn` on the plain ``mm``, ``hem`` or ``ham`` (see :attr:`compiled`), in
        place: every well's measurements in ``batch`` one after another, each one extended
        Kalman step in log space with its calibration, Huber weight, gate, reset and noise
        adaptation; when ``wanted``, first each well's well tests' forecast errors, from
        its state before the batch, learned into the variance factor's statistics (as
        :meth:`_forecast_errors` then :meth:`_learn_calibration`, in the same compiled
        pass: no second forecast). Returns which wells took a measurement [W] and whether
        any forecast error was learned."""
        kernel = compiled()
        lay = self._layout
        assert kernel is not None and batch.well_test is not None and lay is not None
        model: Any = self.model
        n = batch.n_wells
        errors = _NO_ERRORS
        if wanted:  # the factor's statistics, learned in place; an error capped at the gate
            cap = float(self.gate or 6.0) ** 2
            errors = (writable(self, "_cal"), np.zeros(1, dtype=np.int64), cap, _CAL_DISCOUNT)
        counts = self._counts
        for name in counts:
            if not counts[name].is_contiguous():
                counts[name] = counts[name].contiguous()
        w1, b1 = self._compiled_network(n)
        changed = np.zeros(n, dtype=bool)
        blocks = lay["blocks"]
        with torch.no_grad():
            state = self._compiled_state(n)
            taken = kernel.bayes(
                state,
                writable(self, "_P"),
                writable(self, "_last"),
                writable(self, "_noise"),
                writable(self, "_h"),
                writable(self, "_scale"),
                writable(self, "_started"),
                writable(self, "_run"),
                counts["updates"].numpy(),
                counts["downweighted"].numpy(),
                counts["refused"].numpy(),
                counts["resets"].numpy(),
                changed,
                np.ascontiguousarray(batch.x.numpy()),
                np.ascontiguousarray(batch.y.numpy()),
                np.ascontiguousarray(batch.mask.numpy()),
                np.ascontiguousarray(batch.time_ns.numpy()),
                np.ascontiguousarray(batch.well_test.numpy()),
                model.ready.numpy(),
                lay["kind"],
                model.a_max.numpy(),
                lay["pos"],
                lay["mu"],
                lay["sigma"],
                lay["n_phys"],
                model.x_mean.numpy(),
                model.x_std.numpy(),
                w1,
                b1,
                model.y_scale.numpy(),
                lay["rules"],
                errors,
                *effect_arguments(model, batch),
            )
            if taken:  # written back through torch, as the torch path's in-place update
                values = torch.from_numpy(state)
                start = 0
                for p, k in blocks:
                    p.data.view(n, k).copy_(values[:, start : start + k])
                    start += k
        return torch.from_numpy(changed), wanted and bool(errors[1][0] > 0)

    def _compiled_network(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The compiled filter's hybrid's first layer (W1 [n, 6, hidden], b1 [n, hidden]),
        as it is now (empty for ``mm``)."""
        lay = self._layout
        assert lay is not None
        if lay["lower"] is None:  # mm: no network
            return np.zeros((n, 6, 0)), np.zeros((n, 0))
        w1, b1 = (p.detach().numpy() for p in lay["lower"])
        return w1, b1

    def _compiled_state(self, n: int) -> np.ndarray:
        """The compiled filter's state [n, D]: its blocks' parameters, concatenated."""
        assert self._layout is not None
        blocks = self._layout["blocks"]
        return np.concatenate([p.detach().numpy().reshape(n, k) for p, k in blocks], axis=1)

    def _compiled_gradients(self, kernel: Any, batch: Batch) -> torch.Tensor:
        """:meth:`_sample_gradients` by the compiled ``bayes_gradients`` (the gradient the
        compiled update takes, at each sample)."""
        lay, model, n = self._layout, self.model, batch.n_wells
        assert lay is not None
        w1, b1 = self._compiled_network(n)
        m: Any = model
        out = np.empty((n, batch.y.shape[1], self._dim))
        with torch.no_grad():
            kernel.bayes_gradients(
                self._compiled_state(n),
                np.ascontiguousarray(self._h.numpy()),
                lay["rules"][4],
                np.ascontiguousarray(batch.x.numpy()),
                np.ascontiguousarray(batch.mask.numpy()),
                m.ready.numpy(),
                lay["kind"],
                m.a_max.numpy(),
                lay["pos"],
                lay["mu"],
                lay["sigma"],
                lay["n_phys"],
                m.x_mean.numpy(),
                m.x_std.numpy(),
                w1,
                b1,
                m.y_scale.numpy(),
                *effect_arguments(model, batch),
                out,
            )
        return torch.from_numpy(out)

    def _compiled_spread(
        self, kernel: Any, mean: torch.Tensor, batch: Batch, h: torch.Tensor
    ) -> Forecast:
        """:meth:`predict`'s spread of the rates ``mean``, by the compiled
        ``bayes_spread`` (the same arithmetic as :meth:`_spread`; ``h`` [W, N, D] the
        sensitivity at each sample)."""
        assert batch.well_test is not None
        out = [np.empty(tuple(mean.shape)) for _ in range(3)]
        with torch.no_grad():
            kernel.bayes_spread(
                np.ascontiguousarray(mean.numpy()),
                np.ascontiguousarray(h.numpy()),
                writable(self, "_P"),
                self._q.numpy(),
                writable(self, "_last"),
                writable(self, "_noise"),
                writable(self, "_scale"),
                writable(self, "_started"),
                np.ascontiguousarray(batch.time_ns.numpy()),
                np.ascontiguousarray(batch.well_test.numpy()),
                int(NEVER),
                Z90,
                _NS_PER_YEAR,
                *out,
            )
        return Forecast(mean, *(torch.from_numpy(a) for a in out))

    # -- tuning -----------------------------------------------------------------------------------
    def tuning(self, grid: str) -> list[dict[str, Any]]:
        """How fast the parameters may drift (a factor on every default drift), and with the
        paper grid also how fast the meters' noise adapts."""
        scales = [0.25, 0.5, 1.0, 2.0, 4.0]
        adapts = [0.0, 0.02, 0.1] if grid == "paper" else [0.02]
        return [
            {"text": f"bayes:drift={d:g}" + (f":adapt={a:g}" if a != 0.02 else "")}
            for d in scales
            for a in adapts
        ]

    # -- what it knows ----------------------------------------------------------------------------
    def parameter_sd(self) -> dict[str, torch.Tensor]:
        """Posterior sd [W] of every physical parameter now (SI units, by name)."""
        if not self._blocks:
            return {}
        return _physical_sd(self._blocks, self._P)

    def stats(self) -> dict[str, torch.Tensor]:
        """Per well: measurements taken, down-weighted and refused, and resets after a change."""
        return {k: v.clone() for k, v in self._counts.items()}

    # -- a joint update's access (vfm_core.separator: one reading of many wells' sum) ------------
    def filter_state(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Copies of the filtered parameters theta [W, D] (the filter's own scale), their
        covariance P [W, D, D] at each well's last update, that time [W] (epoch ns) and each
        meter's relative noise [W, 2] (sd; MPFM, well test)."""
        theta = _flat(self._blocks, len(self.model.wells)) if self._blocks else torch.zeros(0)
        return theta.clone(), self._P.clone(), self._last.clone(), self._noise.clone()

    def grown_covariance(self, now_ns: torch.Tensor) -> torch.Tensor:
        """P [W, D, D] after each well's drift from its last update to ``now_ns`` [W]."""
        return self._grow(now_ns)

    def log_rate_and_gradient(
        self, one: Batch, live: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """log h [W] (h in Sm3/h) and its gradient over the filtered parameters [W, D] at
        the current parameters, for one sample per well (``live`` [W]: the wells that count)."""
        log_h, H = self._log_rate_and_gradient(one, live)
        return log_h, H * self._keep.to(DTYPE)

    def set_filter_state(
        self, theta: torch.Tensor, P: torch.Tensor, now_ns: torch.Tensor, wells: torch.Tensor
    ) -> None:
        """Take a joint update's result for ``wells`` [W] (bool): parameters theta [W, D]
        (then kept within their bounds), covariance P [W, D, D], last update ``now_ns`` [W].
        A separator's wells: its readings count as an MPFM's in :meth:`_note_meters` (such a
        well is not refitted under ``auto``: its filter follows the separator)."""
        _assign(self._blocks, theta, wells)
        self.model.project_()
        self._P[wells] = P[wells]  # in place: the compiled filter reads this same tensor
        self._last[wells] = now_ns[wells]
        self._started |= wells
        if self._by_meter:
            held = self._meter_t
            for i in torch.nonzero(wells & (now_ns != NEVER)).flatten().tolist():
                t = int(now_ns[i])
                if held[i, 0] == NEVER or t > held[i, 0]:
                    held[i, 0] = t
                self._refresh_at[i] = NEVER

    # -- state ----------------------------------------------------------------------------------
    @property
    def couples_wells(self) -> bool:
        """With ``cal_pool`` each well's variance factor takes its prior from the other
        wells' forecast errors (:func:`_pooled_prior`)."""
        return bool(self.cal_pool)

    def coupling_samples(self, batch: Batch) -> torch.Tensor | None:
        """The well tests: only their forecast errors enter the other wells' priors (an
        MPFM reading's interval carries no variance factor), so the wells' forecasts
        depend on each other's well tests alone."""
        assert batch.well_test is not None
        return batch.well_test & batch.mask

    def well_test_factor(self) -> torch.Tensor:
        """Each well's learned well-test variance factor c^2 [W]: the scale
        (k c0sq + sum z^2) / (k + n) of its InvGamma posterior (see
        :meth:`_learn_calibration` and :meth:`_factor_prior`); the prior's c0sq for a well
        with no error yet (1 unpooled), 1 for every well with ``cal_prior`` = 0. A copy: the
        allocation of a separator's total reads it
        (:func:`vfm_core.separator.well_test_factor`)."""
        if self.cal_prior <= 0:
            return torch.ones(self._cal.shape[0], dtype=DTYPE)
        count, total = self._cal[:, 1, 0].numpy(), self._cal[:, 1, 1].numpy()
        k, c0sq = self._factor_prior(count, total)
        return torch.from_numpy((k * c0sq + total) / (k + count)).to(DTYPE)

    def well_test_errors(self) -> torch.Tensor:
        """Each well's (discounted) number and sum of squared standardised well-test
        forecast errors [W, 2] (the variance factor's statistics, see
        :meth:`_learn_calibration`). A copy: what :meth:`pool_with` of another filter of the
        same field takes."""
        return self._cal[:, 1, :2].clone()

    def pool_with(self, outside: torch.Tensor | None) -> None:
        """With ``cal_pool``: count ``outside`` [K, 2] (:meth:`well_test_errors` of the
        field's wells outside this filter, e.g. the service's other one-well filters of the
        same model) among the other wells whose errors set each well's prior
        (:func:`_pooled_prior`), and put the factors into the intervals again. One-well
        filters so pooled give the factors of one filter over all the wells. ``None``: none
        outside."""
        if outside is None or outside.numel() == 0:
            self._outside = None
        else:
            values = torch.as_tensor(outside, dtype=DTYPE).reshape(-1, 2).numpy().copy()
            if not (np.isfinite(values).all() and (values >= 0).all()):
                raise ValueError("The wells' well-test error statistics must be finite and >= 0.")
            self._outside = values
        if self._dim and self.cal_prior > 0:
            self._apply_calibration()

    def share_errors(self, pool: CalibrationPool | None) -> None:
        """With ``cal_pool``: take each well's variance-factor prior from the errors of the
        wells of ``pool`` outside this filter (the service's other one-well filters of the
        same model), read at the time of each prediction or update (:meth:`_sync_pool`),
        and publish this filter's wells' statistics there whenever a well test adds to
        them (and now, at each well's last update: a filter restored from a checkpoint
        brings its statistics back). One-well filters so sharing a pool and fed in time
        order give the factors of one filter over all the wells fed in time order.
        ``None``, or ``cal_pool=off``: no pool."""
        self._pool = pool if self.cal_pool and self.cal_prior > 0 else None
        self._pool_stale = True
        if self._pool is None or not self._dim:
            return
        last, sent_t, sent_s = self._last.numpy(), self._sent_t.numpy(), self._sent_s.numpy()
        cal = self._cal.numpy()
        for i in np.flatnonzero(self._started.numpy() & (last != NEVER)):
            well = str(self.model.wells[i])
            for k in np.flatnonzero(sent_t[i] != NEVER):  # what it published before
                self._pool.publish(well, int(sent_t[i, k]), *map(float, sent_s[i, k]))
            if sent_t[i, -1] == NEVER or not np.array_equal(sent_s[i, -1], cal[i, 1, :2]):
                self._publish_well(int(i), int(last[i]))

    def _publish_well(self, i: int, time_ns: int) -> None:
        """Publish well ``i``'s well-test error statistics to the pool at ``time_ns`` (and
        keep them among its latest publications)."""
        assert self._pool is not None
        cal = self._cal.numpy()
        count, total = float(cal[i, 1, 0]), float(cal[i, 1, 1])
        self._pool.publish(str(self.model.wells[i]), time_ns, count, total)
        sent_t, sent_s = writable(self, "_sent_t"), writable(self, "_sent_s")
        if sent_t[i, -1] != time_ns:
            sent_t[i, :-1], sent_s[i, :-1] = sent_t[i, 1:].copy(), sent_s[i, 1:].copy()
        sent_t[i, -1], sent_s[i, -1] = time_ns, (count, total)

    def _publish(self, batch: Batch) -> None:
        """Publish the statistics of the wells with a well test in ``batch``, at its time."""
        if self._pool is None:
            return
        assert batch.well_test is not None
        tested = (batch.mask & batch.well_test).numpy()
        times = batch.time_ns.numpy()
        for i in np.flatnonzero(tested.any(1) & self._started.numpy()):
            self._publish_well(int(i), int(times[i][tested[i]].max()))

    def _sync_pool(self, batch: Batch, row: int | None = None) -> None:
        """Read the pool (:meth:`share_errors`) as of ``batch``'s earliest sample (of its
        well ``row``) and, when the other wells' statistics changed, put each well's
        factor into its intervals again (:meth:`pool_with`)."""
        pool = self._pool
        if pool is None or not self._dim:
            return
        time_ns = _first_time(batch, row)
        if time_ns is None:
            return
        # after every publication, and none since the last reading: the same statistics
        generation = pool.generation
        latest = pool.newest == NEVER or time_ns > pool.newest
        if latest and not self._pool_stale and self._pool_seen == generation:
            return
        self._pool_seen = generation if latest else -1
        outside = pool.outside(self.model.wells, time_ns)
        held = np.zeros((0, 2)) if self._outside is None else self._outside
        if not self._pool_stale and outside.shape == held.shape and np.array_equal(outside, held):
            return
        self._pool_stale = False
        self._outside = outside if len(outside) else None
        self._apply_calibration()

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state.update(
            P=self._P.clone(),
            last=self._last.clone(),
            noise=self._noise.clone(),
            h=self._h.clone(),
            started=self._started.clone(),
            run=self._run.clone(),
            scale=self._scale.clone(),
            cal=self._cal.clone(),
            sent_t=self._sent_t.clone(),
            sent_s=self._sent_s.clone(),
            refresh_at=self._refresh_at.clone(),
            meter_t=torch.from_numpy(self._meter_t.copy()),
            counts={k: v.clone() for k, v in self._counts.items()},
        )
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        names = ("P", "last", "noise", "h", "started", "run", "scale", "cal", "refresh_at")
        # (one saved before session 51 has no meter_t: NEVER, none seen, until the next
        # measurements; its refresh_at then holds no refit of a hybrid under auto)
        for name in (*names, "sent_t", "sent_s"):
            if name in state:
                setattr(self, f"_{name}", torch.as_tensor(state[name]).clone())
        if "meter_t" in state:
            self._meter_t = torch.as_tensor(state["meter_t"]).numpy().copy()
        for k, v in state.get("counts", {}).items():
            self._counts[k] = torch.as_tensor(v).clone()
        if self._pool is not None:  # its statistics back in the pool, its factors again
            self.share_errors(self._pool)
