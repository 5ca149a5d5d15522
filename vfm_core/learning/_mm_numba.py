"""The numba kernels of :mod:`vfm_core.learning.kernels` (imported by it, and only when
the kernels are used: importing this module compiles them, or loads them from numba's
cache next to it).

They are module-level functions so that numba's disk cache finds them again in the next
process (a kernel that calls another through a closure is compiled anew every time)."""

from __future__ import annotations

import math

import numba
import numpy as np

from vfm_core import physics as ph
from vfm_core.units import KELVIN_OFFSET, PA_PER_BAR

_R_GAS, _P_SC, _T_SC = ph.R_GAS, ph.P_SC, ph.T_SC
_PA_PER_BAR, _KELVIN = PA_PER_BAR, KELVIN_OFFSET
_PER_HOUR = 3600.0
# error_model="numpy": a division by zero gives inf or NaN, as in torch, never raises
jit = numba.njit(cache=True, nogil=True, error_model="numpy")


@jit
def rate_grad(theta: np.ndarray, x: np.ndarray, a_max: float, dq: np.ndarray) -> float:
    """The plain Sachdeva rate q (Sm3/h) of one sample ``x`` (the six inputs in file
    units) at ``theta`` (SI, in _NAMES order), and dq / dtheta into ``dq`` [6]
    (models.physical._sachdeva_vjp's pullback with physics.flux_vjp, for a unit
    cotangent)."""
    rho_oil, rho_wat, kappa, m_gas, p_cr, c_d = (
        theta[0],
        theta[1],
        theta[2],
        theta[3],
        theta[4],
        theta[5],
    )
    p_cr_used = min(max(p_cr, 0.05), 0.99)
    inside = 1.0 if (p_cr >= 0.05 and p_cr <= 0.99) else 0.0
    k = kappa
    rho_sc = _P_SC * m_gas / (_R_GAS * _T_SC)
    u = x[0]
    p1 = x[1] * _PA_PER_BAR
    p2 = x[2] * _PA_PER_BAR
    t1 = x[3] + _KELVIN
    xg = x[4]
    eo = x[5]
    # physics._flux, z = 1, no slip
    ratio = p2 / p1
    pr = max(ratio, p_cr_used)
    rho_g1 = p1 * m_gas / (_R_GAS * t1)
    eta_wat = 1.0 - xg - eo
    v_liq = eo / rho_oil + eta_wat / rho_wat
    expansion = 1.0 - pr ** ((k - 1.0) / k)
    energy = v_liq * (1.0 - pr) + xg * k / (k - 1.0) * expansion / rho_g1
    rho_g2 = rho_g1 * pr ** (1.0 / k)
    v_mix = xg / rho_g2 + v_liq
    head = 2.0 * p1 * energy
    flux = math.sqrt(max(head, 0.0)) / v_mix
    gas_sc = xg / rho_sc
    per_kg = gas_sc + (eo / rho_oil + eta_wat / rho_wat)
    unit_area = a_max * u
    area = c_d * unit_area
    q = area * flux * per_kg * _PER_HOUR
    g_flux = area * per_kg * _PER_HOUR
    if head > 0:
        g_e = g_flux * flux * 0.5 / energy
        g_m = -g_flux * flux / v_mix
    else:
        g_e = 0.0
        g_m = 0.0
    pra = 1.0 - expansion  # p_r^a, as flux_vjp takes it
    gas = xg * pr ** (-1.0 / k) / rho_g1
    log_pr = math.log(pr)
    d_v = g_e * (1.0 - pr) + g_m
    d_rho_g1 = g_e * (-xg * k / (k - 1.0) * expansion / rho_g1**2) - g_m * gas / rho_g1
    d_pr = g_e * (-v_liq - xg * pra / pr / rho_g1) - g_m * gas / (k * pr)
    d_k = (
        g_e * (-xg * (expansion / (k - 1.0) ** 2 + pra * log_pr / (k * (k - 1.0))) / rho_g1)
        + g_m * gas * log_pr / k**2
    )
    if p_cr_used > ratio:
        at_cr = 1.0
    elif p_cr_used == ratio:
        at_cr = 0.5
    else:
        at_cr = 0.0
    g_kg = area * flux * _PER_HOUR
    dq[0] = d_v * (-eo / rho_oil**2) - g_kg * eo / rho_oil**2
    dq[1] = d_v * (-eta_wat / rho_wat**2) - g_kg * eta_wat / rho_wat**2
    dq[2] = d_k
    dq[3] = d_rho_g1 * rho_g1 / m_gas - g_kg * gas_sc / m_gas
    dq[4] = d_pr * at_cr * inside
    dq[5] = (flux * per_kg * _PER_HOUR) * unit_area
    return q


@jit
def rates(z: np.ndarray, x: np.ndarray, a_max: np.ndarray, mu: np.ndarray,
          sigma: np.ndarray, out: np.ndarray) -> None:  # fmt: skip
    """The plain Sachdeva rate [W, N] (Sm3/h) of every sample, into ``out``."""
    n_wells, n_samples = out.shape
    theta = np.zeros(6)
    dq = np.zeros(6)
    for w in range(n_wells):
        for i in range(6):
            theta[i] = mu[i] + sigma[i] * z[w, i]
        for j in range(n_samples):
            out[w, j] = rate_grad(theta, x[w, j], a_max[w], dq)


@jit
def hybrid_rates(
    z: np.ndarray,
    pos: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    x: np.ndarray,
    a_max: np.ndarray,
    x_mean: np.ndarray,
    x_std: np.ndarray,
    w1: np.ndarray,
    b1: np.ndarray,
    w2: np.ndarray,
    b2: np.ndarray,
    y_scale: np.ndarray,
    area_model: bool,
    out: np.ndarray,
) -> None:
    """The rate [W, N] (Sm3/h) of a hybrid with one hidden ReLU layer, into ``out``: the
    network o = b2 + relu(b1 + x_norm W1) W2 of the normalised inputs; ``hem``: the
    Sachdeva rate plus y_scale o; ``ham`` (``area_model``): the Sachdeva rate with C_D
    replaced by C_D0 exp(o). ``theta[i]`` is mu[i] + sigma[i] z[w, pos[i]], or mu[i] where
    pos[i] < 0 (a parameter the model does not learn: ``ham``'s C_D0)."""
    n_wells, n_samples = out.shape
    hidden = w1.shape[2]
    theta = np.zeros(6)
    dq = np.zeros(6)
    xn = np.zeros(6)
    for w in range(n_wells):
        for i in range(6):
            theta[i] = mu[i] + sigma[i] * z[w, pos[i]] if pos[i] >= 0 else mu[i]
        c_d = theta[5]
        for j in range(n_samples):
            for i in range(6):
                xn[i] = (x[w, j, i] - x_mean[w, i]) / x_std[w, i]
            o = b2[w, 0]
            for k in range(hidden):
                a = b1[w, k]
                for i in range(6):
                    a += xn[i] * w1[w, i, k]
                if not a <= 0.0:  # ReLU (a NaN passes, as torch's)
                    o += a * w2[w, k, 0]
            if area_model:
                theta[5] = c_d * math.exp(o)
                out[w, j] = rate_grad(theta, x[w, j], a_max[w], dq)
            else:
                out[w, j] = rate_grad(theta, x[w, j], a_max[w], dq) + y_scale[w] * o


@jit
def online(  # noqa: PLR0913 - the arrays of one update
    z: np.ndarray,
    m: np.ndarray,
    v: np.ndarray,
    counts: np.ndarray,
    hold: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    mask: np.ndarray,
    a_max: np.ndarray,
    scale: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    z_low: np.ndarray,
    z_high: np.ndarray,
    noise: float,
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    max_norm: float,
    steps: int,
    adam: bool,
) -> None:
    n_wells, n_samples = y.shape
    n_par = z.shape[1]
    grad = np.zeros(n_par)
    held = np.zeros(n_par)
    theta = np.zeros(n_par)
    dq = np.zeros(n_par)
    for w in range(n_wells):
        n = 0
        for j in range(n_samples):
            if mask[w, j]:
                n += 1
        has = n > 0
        n_safe = max(float(n), 1.0)
        # MapObjective: prior weight sigma^2 / n, d loss / d rate = e * d_factor
        weight = noise**2 / n_safe if has else 0.0
        d_factor = (2.0 / n_safe if has else 0.0) / scale[w]
        for i in range(n_par):
            held[i] = z[w, i]
        for _ in range(steps):
            for i in range(n_par):
                theta[i] = mu[i] + sigma[i] * z[w, i]
                grad[i] = 0.0
            for j in range(n_samples):
                if not mask[w, j]:
                    continue  # torch: a zero gradient there
                q = rate_grad(theta, x[w, j], a_max[w], dq)
                g = (q - y[w, j]) / scale[w] * d_factor
                for i in range(n_par):
                    grad[i] += g * dq[i]
            # to the standardised parameters, plus the prior's pull; then the clip
            sq = 0.0
            for i in range(n_par):
                grad[i] = grad[i] * sigma[i] + 2.0 * weight * z[w, i]
                sq += grad[i] * grad[i]
            clip = min(max_norm / (math.sqrt(sq) + 1e-12), 1.0)
            if adam:
                counts[w] += 1.0
                c = counts[w]
                step_size = lr / (1.0 - beta1**c)
                root = math.sqrt(1.0 - beta2**c)
            for i in range(n_par):
                gi = grad[i] * clip
                if adam:
                    m[w, i] = m[w, i] + (1.0 - beta1) * (gi - m[w, i])
                    v[w, i] = v[w, i] * beta2 + (1.0 - beta2) * gi * gi
                    denom = math.sqrt(v[w, i]) / root + eps
                    zi = z[w, i] + (-step_size) * m[w, i] / denom
                else:
                    zi = z[w, i] + (-lr) * gi
                z[w, i] = max(min(zi, z_high[i]), z_low[i])
            if hold[w]:
                for i in range(n_par):
                    z[w, i] = held[i]


@jit
def bayes(  # noqa: PLR0913, PLR0912, PLR0915 - one Kalman step, as BayesianFilter._update
    z: np.ndarray,
    P: np.ndarray,
    last: np.ndarray,
    noise: np.ndarray,
    h: np.ndarray,
    scale: np.ndarray,
    started: np.ndarray,
    run: np.ndarray,
    updates: np.ndarray,
    downweighted: np.ndarray,
    refused_count: np.ndarray,
    resets: np.ndarray,
    changed: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    mask: np.ndarray,
    time_ns: np.ndarray,
    well_test: np.ndarray,
    ready: np.ndarray,
    a_max: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    z_low: np.ndarray,
    z_high: np.ndarray,
    prior_var: np.ndarray,
    q: np.ndarray,
    keep: np.ndarray,
    fixed: np.ndarray,
    huber: float,
    gate: float,
    adapt: float,
    calibrate: float,
    never: int,
    reset_after: int,
    noise_floor: float,
    z90: float,
    ns_per_year: float,
) -> bool:
    n_wells, n_samples = y.shape
    d = z.shape[1]
    theta = np.zeros(d)
    dq = np.zeros(d)
    H = np.zeros(d)
    K = np.zeros(d)
    Pg = np.zeros((d, d))
    AP = np.zeros((d, d))
    taken = False
    for w in range(n_wells):
        # a well's measurements one after another, in column order (the torch path
        # takes every well's k-th measurement together: the wells do not interact)
        for j in range(n_samples):
            if not (mask[w, j] and ready[w] and y[w, j] > 0):
                continue
            t = time_ns[w, j]
            s = 1 if well_test[w, j] else 0
            if not started[w]:  # a model but no filter state yet: the prior
                for a in range(d):
                    for b in range(d):
                        P[w, a, b] = 0.0
                    P[w, a, a] = prior_var[a]
                last[w] = t
                started[w] = True
            # the spread the filter gave this measurement before it arrived (_spread)
            hph = 0.0
            hqh = 0.0
            for a in range(d):
                hqh += h[w, a] ** 2 * q[a]
                for b in range(d):
                    hph += h[w, a] * P[w, a, b] * h[w, b]
            dt = float(max(t - last[w], 0)) / ns_per_year if last[w] != never else 0.0
            var = hph + hqh * dt + noise[w, s] ** 2
            sd_given = math.sqrt(max(var, 0.0)) * math.exp(scale[w, s])
            # P after the drift since the last update (_grow); kept if refused
            if last[w] != never and t != never:
                dt = float(max(t - last[w], 0)) / ns_per_year
            else:
                dt = 0.0
            for a in range(d):
                for b in range(d):
                    Pg[a, b] = P[w, a, b]
                Pg[a, a] = P[w, a, a] + q[a] * dt
            for a in range(d):
                for b in range(d):
                    P[w, a, b] = Pg[a, b]
            last[w] = t
            log_y = math.log(y[w, j])
            R = noise[w, s] ** 2
            # log h and its gradient H at the current parameters (_log_rate_and_gradient)
            for i in range(d):
                theta[i] = mu[i] + sigma[i] * z[w, i]
            rate = rate_grad(theta, x[w, j], a_max[w], dq)
            clamped = max(rate, 1e-12)
            log_h = math.log(clamped)
            for i in range(d):
                H[i] = (dq[i] * sigma[i] / clamped if rate >= 1e-12 else 0.0) * keep[i]
            if calibrate > 0:  # adaptive conformal calibration of this meter's intervals
                miss = 1.0 if abs(log_y - log_h) > z90 * sd_given else 0.0
                scale[w, s] += calibrate * (miss - 0.1)
            hph = 0.0
            for a in range(d):
                for b in range(d):
                    hph += H[a] * Pg[a, b] * H[b]
            zz = abs(log_y - log_h) / math.sqrt(hph + R)
            weight = huber / zz if (huber != 0 and zz > huber) else 1.0
            refused = gate != 0 and zz > gate
            run[w] = run[w] + 1 if refused else 0
            if refused and run[w] >= reset_after:  # the well changed: a year's drift
                for a in range(d):
                    Pg[a, a] += q[a]
                resets[w] += 1
                run[w] = 0
                refused = False
                weight = 1.0
            if refused:
                refused_count[w] += 1
                continue
            if weight < 1:
                downweighted[w] += 1
            Rk = R / weight
            hph = 0.0
            for a in range(d):
                for b in range(d):
                    hph += H[a] * Pg[a, b] * H[b]
            S = hph + Rk
            for a in range(d):
                ph_a = 0.0
                for b in range(d):
                    ph_a += Pg[a, b] * H[b]
                K[a] = ph_a / S
            innov = log_y - log_h
            # Joseph form: (I - K H) P (I - K H)^T + K K^T Rk, symmetrised
            for a in range(d):
                for b in range(d):
                    acc = Pg[a, b]
                    for c in range(d):
                        acc -= K[a] * H[c] * Pg[c, b]
                    AP[a, b] = acc
            for a in range(d):
                for b in range(d):
                    acc = AP[a, b]
                    for c in range(d):
                        acc -= AP[a, c] * H[c] * K[b]
                    P[w, a, b] = acc + K[a] * K[b] * Rk
            for a in range(d):
                for b in range(a + 1, d):
                    mean = 0.5 * (P[w, a, b] + P[w, b, a])
                    P[w, a, b] = mean
                    P[w, b, a] = mean
            for i in range(d):
                z[w, i] = max(min(z[w, i] + K[i] * innov, z_high[i]), z_low[i])
                h[w, i] = H[i]
            if adapt > 0 and not fixed[s]:
                # the meter's noise follows the innovations (beyond the parameters')
                cap = (huber if huber != 0 else 3.0) ** 2 * (hph + R)
                sample = min(innov**2, cap) - hph
                new = (1.0 - adapt) * R + adapt * max(sample, noise_floor**2)
                noise[w, s] = max(math.sqrt(new), noise_floor)
            updates[w] += 1
            changed[w] = True
            taken = True
    if taken:  # model.project_() after an update: every well within its bounds
        for w in range(n_wells):
            for i in range(d):
                z[w, i] = max(min(z[w, i], z_high[i]), z_low[i])
    return taken


@jit
def bayes_spread(
    mean: np.ndarray,
    h: np.ndarray,
    P: np.ndarray,
    q: np.ndarray,
    last: np.ndarray,
    noise: np.ndarray,
    scale: np.ndarray,
    started: np.ndarray,
    time_ns: np.ndarray,
    well_test: np.ndarray,
    never: int,
    z90: float,
    ns_per_year: float,
    std: np.ndarray,
    p05: np.ndarray,
    p95: np.ndarray,
) -> None:
    """``BayesianFilter.predict``'s spread of the rates ``mean`` [W, N] (any model, any
    number of filtered parameters D): the predictive sd of the log rate sqrt(h (P + Q dt)
    h + s^2) times the meter's calibration factor (NaN for a well without filter state),
    as std = rate sd and the central 90 % bounds rate exp(+-z90 sd)."""
    n_wells, n_samples = mean.shape
    d = h.shape[1]
    for w in range(n_wells):
        hph = 0.0
        hqh = 0.0
        for a in range(d):
            hqh += h[w, a] ** 2 * q[a]
            for b in range(d):
                hph += h[w, a] * P[w, a, b] * h[w, b]
        for j in range(n_samples):
            rate = mean[w, j]
            if not started[w]:
                std[w, j] = np.nan
                p05[w, j] = np.nan
                p95[w, j] = np.nan
                continue
            s = 1 if well_test[w, j] else 0
            dt = float(max(time_ns[w, j] - last[w], 0)) / ns_per_year if last[w] != never else 0.0
            var = hph + hqh * dt + noise[w, s] ** 2
            sd = math.sqrt(max(var, 0.0)) * math.exp(scale[w, s])
            std[w, j] = rate * sd
            p05[w, j] = rate * math.exp(-z90 * sd)
            p95[w, j] = rate * math.exp(z90 * sd)


def warm_up() -> None:
    """Run each kernel once on a made-up sample (compiles it, or loads it from the cache)."""
    one = np.ones((1, 6))
    mu = np.array([840.0, 1017.5, 1.28, 0.0205, 0.55, 0.825])
    x = np.array([[[0.5, 50.0, 20.0, 60.0, 0.1, 0.5]]])
    ones, yes = np.ones((1, 1)), np.ones((1, 1), dtype=bool)
    online(
        np.zeros((1, 6)), np.zeros((1, 6)), np.zeros((1, 6)), np.zeros(1), np.zeros(1, dtype=bool),
        x, ones, yes, np.ones(1), np.ones(1), mu, one[0], -one[0], one[0],
        0.05, 1e-3, 0.9, 0.999, 1e-8, 1.0, 1, True,
    )  # fmt: skip
    rates(np.zeros((1, 6)), x, np.ones(1), mu, one[0], np.zeros((1, 1)))
    pos = np.arange(6)
    for area_model in (False, True):
        hybrid_rates(
            np.zeros((1, 6)), pos, mu, one[0], x, np.ones(1), np.zeros((1, 6)), one,
            np.ones((1, 6, 4)), np.ones((1, 4)), np.ones((1, 4, 1)), np.ones((1, 1)), np.ones(1),
            area_model, np.zeros((1, 1)),
        )  # fmt: skip
    count = np.zeros(1, dtype=np.int64)
    bayes(
        np.zeros((1, 6)), np.zeros((1, 6, 6)), np.zeros(1, dtype=np.int64), np.ones((1, 2)),
        np.zeros((1, 6)), np.zeros((1, 2)), np.zeros(1, dtype=bool), count.copy(), count.copy(),
        count.copy(), count.copy(), count.copy(), np.zeros(1, dtype=bool),
        x, ones, yes, np.ones((1, 1), dtype=np.int64), yes, np.ones(1, dtype=bool),
        np.ones(1), mu, one[0], -one[0], one[0], one[0], one[0], one[0], np.zeros(2, dtype=bool),
        3.0, 6.0, 0.02, 0.05, -1, 3, 0.002, 1.645, 3.15e16,
    )  # fmt: skip
    out = [np.zeros((1, 1)) for _ in range(3)]
    bayes_spread(
        ones, np.zeros((1, 6)), np.zeros((1, 6, 6)), one[0], np.zeros(1, dtype=np.int64),
        np.ones((1, 2)), np.zeros((1, 2)), np.ones(1, dtype=bool),
        np.ones((1, 1), dtype=np.int64), yes, -1, 1.645, 3.15e16, *out,
    )  # fmt: skip
