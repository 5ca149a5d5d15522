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
_M_AIR, _PA_PER_PSI = ph.M_AIR, 6894.757293168
# error_model="numpy": a division by zero gives inf or NaN, as in torch, never raises
jit = numba.njit(cache=True, nogil=True, error_model="numpy")
#: a part of a longer kernel, named for what it does: numba inlines it into its caller (in
#: numba's IR, so the caller compiles to what it was before the part had a name)
part = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")


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
def _real_gas_z(m_gas: float, p1: float, t1: float, strength: float) -> tuple:  # type: ignore[type-arg]
    """effects.RealGas's Z = max(1 + strength (Z_Papay - 1), 0.2) at p1 (Pa), t1 (K)
    (physics.z_factor_papay, Sutton's pseudo-critical properties), 1.0 where the floor
    passes a gradient (torch.clamp's) else 0.0, Z_Papay and dZ_Papay / dM_gas."""
    gamma = m_gas / _M_AIR
    t_pc = (169.2 + 349.5 * gamma - 74.0 * gamma**2) * (5.0 / 9.0)
    p_pc = (756.8 - 131.0 * gamma - 3.6 * gamma**2) * _PA_PER_PSI
    t_pr = t1 / t_pc
    p_pr = p1 / p_pc
    e1 = 10.0 ** (0.9813 * t_pr)
    e2 = 10.0 ** (0.8157 * t_pr)
    zp = 1.0 - 3.52 * p_pr / e1 + 0.274 * p_pr**2 / e2
    zr = 1.0 + strength * (zp - 1.0)
    d_tpr = -t_pr / t_pc * ((349.5 - 148.0 * gamma) * (5.0 / 9.0) / _M_AIR)
    d_ppr = -p_pr / p_pc * ((-131.0 - 7.2 * gamma) * _PA_PER_PSI / _M_AIR)
    ln10 = math.log(10.0)
    dzp_dm = (-3.52 / e1 + 0.548 * p_pr / e2) * d_ppr + (
        3.52 * 0.9813 * ln10 * p_pr / e1 - 0.274 * 0.8157 * ln10 * p_pr**2 / e2
    ) * d_tpr
    return (zr if not zr < 0.2 else 0.2), (1.0 if zr >= 0.2 else 0.0), zp, dzp_dm


@jit
def _slip_flux(
    root_head: float, flux: float, v_liq: float, xg: float, rho_g2: float, exponent: float
) -> tuple:  # type: ignore[type-arg]
    """effects.Slip's flux G (G_slip / G)^exponent, G_slip = sqrt(2 p1 E) / v_s the flux
    with Simpson's slip (physics._flux with slip=True: v_s = A B, A = x / rho_g2 + s v,
    B = x + l / s, s = (rho_l / rho_g2)^(1/6), rho_l = l / max(v, 1e-12), l = 1 - x),
    both fluxes clamped at 1e-12 in the ratio; returns it, G_slip, v_s, s, A, B, its
    derivatives by G and by G_slip, and log(G_slip / G)."""
    lf = 1.0 - xg
    rho_l = lf / (v_liq if not v_liq < 1e-12 else 1e-12)
    s = (rho_l / rho_g2) ** (1.0 / 6.0) if lf > 1e-9 else 1.0
    big_a = xg / rho_g2 + s * v_liq
    big_b = xg + lf / s
    v_s = big_a * big_b
    flux_s = root_head / v_s
    c = flux if not flux < 1e-12 else 1e-12
    cs = flux_s if not flux_s < 1e-12 else 1e-12
    log_ratio = math.log(cs / c)
    r_w = math.exp(exponent * log_ratio)
    fe = flux * r_w
    by_flux = r_w - fe * exponent * (1.0 if flux >= 1e-12 else 0.0) / c
    by_slip = fe * exponent * (1.0 if flux_s >= 1e-12 else 0.0) / cs
    return fe, flux_s, v_s, s, big_a, big_b, by_flux, by_slip, log_ratio


@jit
def _slip_back(
    g_ms: float, v_liq: float, xg: float, s: float, big_a: float, big_b: float, gas: float
) -> tuple:  # type: ignore[type-arg]
    """From d / d v_s (``g_ms``) of :func:`_slip_flux`'s v_s to d / dv (the liquid volume
    per kg) and d / d log rho_g2 (``gas`` = x / rho_g2); s moves with log rho_l - log
    rho_g2 (no gradient where it is 1 or v is at its floor, as torch's where and clamp)."""
    lf = 1.0 - xg
    d_v = g_ms * big_b * s
    d_lg2 = -g_ms * big_b * gas
    if lf > 1e-9:
        d_ls = g_ms * (big_b * v_liq - big_a * lf / (s * s)) * s / 6.0  # per d log s
        d_lg2 += -d_ls
        if v_liq >= 1e-12:
            d_v += -d_ls / v_liq
    return d_v, d_lg2


@jit
def flux_rate_grad(  # noqa: PLR0913 - one sample and its flux effects
    theta: np.ndarray,
    x: np.ndarray,
    a_max: float,
    dq: np.ndarray,
    has_gas: bool,
    strength: float,
    has_slip: bool,
    exponent: float,
    d_e: np.ndarray,
) -> float:
    """:func:`rate_grad` with the effects that change the flux itself, as
    models.physical's ``_sachdeva_rate`` computes them: the upstream Z of effects.RealGas
    with ``has_gas`` (:func:`_real_gas_z`), the flux of effects.Slip with ``has_slip``
    (:func:`_slip_flux`). dq / dtheta into ``dq`` [6] (M_gas through Z too), dq /
    d strength and dq / d exponent into ``d_e`` [2]: the cotangents a_f of G and a_s of
    G_slip give dE (a_f G + a_s G_slip) / 2E, dv_mix -a_f G / v_mix, dv_s -a_s G_slip /
    v_s (:func:`_slip_back`), then as physics.flux_vjp."""
    rho_oil, rho_wat, k, m_gas, p_cr, c_d = theta[0], theta[1], theta[2], theta[3], theta[4], theta[5]  # fmt: skip
    p_cr_used = min(max(p_cr, 0.05), 0.99)
    u, p1, p2, t1, xg, eo = x[0], x[1] * _PA_PER_BAR, x[2] * _PA_PER_BAR, x[3] + _KELVIN, x[4], x[5]  # fmt: skip
    zz, z_in, zp, dzp_dm = 1.0, 0.0, 1.0, 0.0
    if has_gas:
        zz, z_in, zp, dzp_dm = _real_gas_z(m_gas, p1, t1, strength)
    ratio = p2 / p1  # physics._flux with z from here
    pr = max(ratio, p_cr_used)
    rho_g1 = p1 * m_gas / (zz * _R_GAS * t1)
    eta_wat = 1.0 - xg - eo
    v_liq = eo / rho_oil + eta_wat / rho_wat
    expansion = 1.0 - pr ** ((k - 1.0) / k)
    energy = v_liq * (1.0 - pr) + xg * k / (k - 1.0) * expansion / rho_g1
    rho_g2 = rho_g1 * pr ** (1.0 / k)
    v_mix = xg / rho_g2 + v_liq
    head = 2.0 * p1 * energy
    root_head = math.sqrt(max(head, 0.0))
    flux = root_head / v_mix
    gas_sc = xg / (_P_SC * m_gas / (_R_GAS * _T_SC))
    per_kg = gas_sc + (eo / rho_oil + eta_wat / rho_wat)
    unit_area = a_max * u
    area = c_d * unit_area
    g_flux = area * per_kg * _PER_HOUR
    fe, flux_s, v_s, s, big_a, big_b, a_f, a_s = flux, 0.0, 1.0, 1.0, 0.0, 0.0, g_flux, 0.0
    d_e[1] = 0.0
    if has_slip:
        fe, flux_s, v_s, s, big_a, big_b, by_flux, by_slip, log_ratio = _slip_flux(
            root_head, flux, v_liq, xg, rho_g2, exponent
        )
        a_f, a_s = g_flux * by_flux, g_flux * by_slip
        d_e[1] = g_flux * fe * log_ratio
    q = area * fe * per_kg * _PER_HOUR
    flowing = head > 0
    g_e = (a_f * flux + a_s * flux_s) * 0.5 / energy if flowing else 0.0
    g_m = -a_f * flux / v_mix if flowing else 0.0
    pra, log_pr = 1.0 - expansion, math.log(pr)  # p_r^a, log p_r
    gas = xg * pr ** (-1.0 / k) / rho_g1  # x / rho_g2
    d_v = g_e * (1.0 - pr) + g_m  # the cotangents of v and of log rho_g2
    d_lg2 = -g_m * gas
    if has_slip and flowing:
        d_vs, d_lg2s = _slip_back(-a_s * flux_s / v_s, v_liq, xg, s, big_a, big_b, gas)
        d_v += d_vs
        d_lg2 += d_lg2s
    d_rho_g1 = g_e * (-xg * k / (k - 1.0) * expansion / rho_g1**2) + d_lg2 / rho_g1
    d_pr = g_e * (-v_liq - xg * pra / pr / rho_g1) + d_lg2 / (k * pr)
    d_k = (
        g_e * (-xg * (expansion / (k - 1.0) ** 2 + pra * log_pr / (k * (k - 1.0))) / rho_g1)
        - d_lg2 * log_pr / k**2
    )
    at_cr = 1.0 if p_cr_used > ratio else (0.5 if p_cr_used == ratio else 0.0)
    inside = 1.0 if (p_cr >= 0.05 and p_cr <= 0.99) else 0.0
    d_z = d_rho_g1 * (-rho_g1 / zz) * z_in
    g_kg = area * fe * _PER_HOUR
    dq[0] = d_v * (-eo / rho_oil**2) - g_kg * eo / rho_oil**2
    dq[1] = d_v * (-eta_wat / rho_wat**2) - g_kg * eta_wat / rho_wat**2
    dq[2] = d_k
    dq[3] = d_rho_g1 * rho_g1 / m_gas - g_kg * gas_sc / m_gas + d_z * strength * dzp_dm
    dq[4] = d_pr * at_cr * inside
    dq[5] = (fe * per_kg * _PER_HOUR) * unit_area
    d_e[0] = d_z * (zp - 1.0)
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
    ze: np.ndarray,
    fx: tuple,  # type: ignore[type-arg]
) -> None:
    """The rate [W, N] (Sm3/h) of a hybrid with one hidden ReLU layer, into ``out``: the
    network o = b2 + relu(b1 + x_norm W1) W2 of the normalised inputs; ``hem``: the
    Sachdeva rate plus y_scale o; ``ham`` (``area_model``): the Sachdeva rate with C_D
    replaced by C_D0 exp(o). ``theta[i]`` is mu[i] + sigma[i] z[w, pos[i]], or mu[i] where
    pos[i] < 0 (a parameter the model does not learn: ``ham``'s C_D0). ``ze`` [W, P], ``fx``:
    the compiled effects (:func:`_factor_at`), whose factor multiplies the Sachdeva rate."""
    n_wells, n_samples = out.shape
    hidden = w1.shape[2]
    theta = np.zeros(6)
    dq = np.zeros(6)
    xn = np.zeros(6)
    pe, scratch = np.zeros(ze.shape[1]), _scratch(fx)
    for w in range(n_wells):
        for i in range(6):
            theta[i] = mu[i] + sigma[i] * z[w, pos[i]] if pos[i] >= 0 else mu[i]
        c_d = theta[5]
        effect_values(w, ze, fx[1], fx[2], pe)
        for j in range(n_samples):
            fxj = _factor_at(fx, pe, scratch, x[w, j, 0], w, j)
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
                out[w, j] = _rate_at(fx, pe, scratch, theta, x[w, j], a_max[w], dq) * fxj
            else:
                plain = _rate_at(fx, pe, scratch, theta, x[w, j], a_max[w], dq)
                out[w, j] = plain * fxj + y_scale[w] * o


@jit
def map_weights(mask: np.ndarray, w: int, noise: float, scale: float) -> tuple[float, float]:
    """:class:`~vfm_core.learning.training.MapObjective`'s factors for well ``w`` with n
    samples in ``mask``: the prior's weight sigma^2 / n and d loss / d rate per scaled error
    (2 / n / scale); both 0 for a well without samples."""
    n = 0
    for j in range(mask.shape[1]):
        if mask[w, j]:
            n += 1
    if n == 0:
        return 0.0, 0.0
    return noise**2 / float(n), 2.0 / float(n) / scale


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
        weight, d_factor = map_weights(mask, w, noise, scale[w])
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


# -- effects that multiply the rate (vfm_core.effects, Effect.compiled_factor) -------------
#: the codes of :class:`vfm_core.effects.CompiledFactor` (kept equal to its constants);
#: FX_GAS and FX_SLIP change the flux itself (:func:`flux_rate_grad`), their factor is 1
FX_EROSION, FX_VALVE, FX_FAMILY, FX_BIAS, FX_GAS, FX_SLIP, FX_SUGGEST = 1, 2, 3, 4, 5, 6, 7
#: the critical ratio: p_cr moves towards Sachdeva's solved ratio (:func:`_rate_at`), factor 1
FX_CRITICAL = 8


@jit
def valve_family(u: float, family: int) -> float:
    """physics.AREA_FUNCTIONS in their order (linear, equal_percentage, quick_opening,
    convex, sigmoid), with their default shapes."""
    if family == 1:
        r = 30.0
        return (r ** (u - 1.0) - 1.0 / r) / (1.0 - 1.0 / r)
    if family == 2:
        return (u if not u < 0.0 else 0.0) ** 0.6
    if family == 3:
        return 0.25 * u + 0.75 * u**2
    if family == 4:
        uc = min(max(u, 0.0), 1.0)
        return uc**1.5 / (uc**1.5 + (1.0 - uc) ** 1.5)
    return u


@jit
def _erosion(
    p: np.ndarray, p0: int, row: np.ndarray, basis: float, t_ns: int, d_f: np.ndarray
) -> float:
    """Erosion's area factor max(1 + rate x, 0.05), times max(1 + step [t >= t_step], 0.05)
    with a step (``row`` of the terms: code, first parameter, count, column, has step,
    step time); its derivatives into ``d_f``. torch's clamp passes no gradient below its
    floor, and a NaN through."""
    a = 1.0 + p[p0] * basis
    ft = a if not a < 0.05 else 0.05
    d_f[p0] = basis if a >= 0.05 else 0.0
    if row[4]:
        after = 1.0 if t_ns >= row[5] else 0.0
        b = 1.0 + p[p0 + 1] * after
        fb = b if not b < 0.05 else 0.05
        d_f[p0] *= fb
        d_f[p0 + 1] = ft * (after if b >= 0.05 else 0.0)
        ft = ft * fb
    return ft


@jit
def _valve(p: np.ndarray, p0: int, knots: int, u: float, u_ref: float, d_f: np.ndarray) -> float:
    """Valve's area factor a(u) / max(a(u_ref), 1e-9) u_ref / u, a piecewise linear with
    slopes exp(p), and its derivatives into ``d_f``."""
    uc = min(max(u, 1e-3), 1.0)
    rc = min(max(u_ref, 1e-3), 1.0)
    a_u = 0.0
    a_r = 0.0
    width = 1.0 / knots
    for k in range(knots):
        s = math.exp(p[p0 + k])
        a_u += min(max(uc - k / knots, 0.0), width) * s
        a_r += min(max(rc - k / knots, 0.0), width) * s
    arc = a_r if not a_r < 1e-9 else 1e-9
    inside = 1.0 if a_r >= 1e-9 else 0.0
    for k in range(knots):
        s = math.exp(p[p0 + k])
        ov_u = min(max(uc - k / knots, 0.0), width)
        ov_r = min(max(rc - k / knots, 0.0), width)
        d_f[p0 + k] = s * (ov_u / arc - a_u * ov_r * inside / (arc * arc)) * u_ref / uc
    return a_u / arc * u_ref / uc


@jit
def _family(p: np.ndarray, p0: int, family: int, u: float, u_ref: float, d_f: np.ndarray) -> float:
    """A valve family's area factor curve(u) / max(curve(ref), 1e-9) ref / u, the curve
    (1 - w) u + w A(u), and its derivative into ``d_f``."""
    w = p[p0]
    uc = min(max(u, 1e-3), 1.0)
    rc = min(max(u_ref, 1e-3), 1.0)
    fam_u = valve_family(uc, family)
    fam_r = valve_family(rc, family)
    cu = (1.0 - w) * uc + w * fam_u
    cr = (1.0 - w) * rc + w * fam_r
    crc = cr if not cr < 1e-9 else 1e-9
    inside = 1.0 if cr >= 1e-9 else 0.0
    d_f[p0] = ((fam_u - uc) / crc - cu * (fam_r - rc) * inside / (crc * crc)) * rc / uc
    return cu / crc * rc / uc


@jit
def _bias(p: np.ndarray, p0: int, years: float, well_test: bool, d_f: np.ndarray) -> float:
    """The meter bias' output factor: 1 + bias + drift years on MPFM rows, 1 on well tests."""
    if well_test:
        return 1.0
    d_f[p0] = 1.0
    d_f[p0 + 1] = years
    return 1.0 + p[p0] + p[p0 + 1] * years


@jit
def _suggest(p: np.ndarray, p0: int, form: int, c0: float, c1: float, d_f: np.ndarray) -> float:
    """Suggest's output factor from its two columns (``c0``, ``c1``: the step, or sin and
    cos of the season's phase, or the fixed factor; ``Suggest.compiled_columns``) by
    ``form``: 0 max(1 + k c0, 0.05), 1 exp(clamp(k c0, -5, 5)), 2 1 + k_sin c0 + k_cos c1,
    3 c0; its derivatives into ``d_f``. torch's clamp passes no gradient outside its
    range, and a NaN through."""
    if form == 3:
        return c0
    if form == 2:
        d_f[p0] = c0
        d_f[p0 + 1] = c1
        return 1.0 + p[p0] * c0 + p[p0 + 1] * c1
    a = p[p0] * c0
    if form == 1:
        inside = a >= -5.0 and a <= 5.0
        f = math.exp(a if inside or a != a else (5.0 if a > 5.0 else -5.0))
        d_f[p0] = f * c0 if inside else 0.0
        return f
    b = 1.0 + a
    d_f[p0] = c0 if b >= 0.05 else 0.0
    return b if not b < 0.05 else 0.05


@jit
def effect_factor(
    terms: np.ndarray,
    pe: np.ndarray,
    u: float,
    extra: np.ndarray,
    well_test: bool,
    t_ns: int,
    u_ref: float,
    f: np.ndarray,
    d_f: np.ndarray,
) -> float:
    """The rate factor F of one sample: the product of every compiled effect's area and
    output factors (the hooks of :mod:`vfm_core.effects`, the same arithmetic), and
    dF / d(effect parameter) into ``d_f`` [P] (SI, in the order of ``pe``, the effects'
    parameters [P] in SI units). ``terms`` [T, 6]: per effect its code, first parameter,
    number of parameters, feature column and two integer settings; ``u`` the opening, -;
    ``extra`` the sample's feature columns; ``u_ref`` the well's reference opening;
    ``f`` [T] scratch (each effect's factor)."""
    n_t = terms.shape[0]
    for k in range(d_f.shape[0]):
        d_f[k] = 0.0
    for t in range(n_t):
        code, p0, col = terms[t, 0], terms[t, 1], terms[t, 3]
        if code == FX_EROSION:
            f[t] = _erosion(pe, p0, terms[t], extra[col], t_ns, d_f)
        elif code == FX_VALVE:
            f[t] = _valve(pe, p0, terms[t, 4], u, u_ref, d_f)
        elif code == FX_FAMILY:
            f[t] = _family(pe, p0, terms[t, 4], u, u_ref, d_f)
        elif code == FX_BIAS:
            f[t] = _bias(pe, p0, extra[col], well_test, d_f)
        elif code == FX_SUGGEST:
            f[t] = _suggest(pe, p0, terms[t, 4], extra[col], extra[col + 1], d_f)
        elif code == FX_GAS or code == FX_SLIP or code == FX_CRITICAL:
            f[t] = 1.0  # in the flux (_rate_at), not a factor
        else:
            f[t] = math.nan  # (no other code: Effect.compiled_factor names these eight)
    total = 1.0
    for t in range(n_t):
        total *= f[t]
    for t in range(n_t):  # each effect's derivatives times the other effects' factors
        other = 1.0
        for s in range(n_t):
            if s != t:
                other *= f[s]
        for k in range(terms[t, 1], terms[t, 1] + terms[t, 2]):
            d_f[k] *= other
    return total


@jit
def _factor_at(fx: tuple, pe: np.ndarray, scratch: tuple, u: float, w: int, j: int) -> float:  # type: ignore[type-arg]
    """:func:`effect_factor` of sample j (opening ``u``) of well w, 1 without effects:
    ``fx`` the effects' (terms, mu_e, sigma_e, extra [W, N, E], well_test [W, N], time_ns
    [W, N], u_ref [W]), ``scratch`` (dF, f) of :func:`_scratch`."""
    terms, _, _, extra, well_test, time_ns, u_ref = fx
    d_f, f = scratch[0], scratch[1]
    if terms.shape[0] == 0:
        return 1.0
    return effect_factor(
        terms, pe, u, extra[w, j], well_test[w, j], time_ns[w, j], u_ref[w], f, d_f
    )


@jit
def _scratch(fx: tuple) -> tuple:  # type: ignore[type-arg]
    """The arrays :func:`_factor_at` and :func:`_rate_at` write: dF [P], each effect's
    factor [T], dq / d(effect parameter) of the flux effects [P] (0 for the others),
    :func:`flux_rate_grad`'s two derivatives, and the critical ratio's theta [6], solved
    ratio and p_cr (:func:`_critical_theta`)."""
    p = fx[1].shape[0]
    return np.zeros(p), np.zeros(fx[0].shape[0]), np.zeros(p), np.zeros(2), np.zeros(8)


@jit
def _rate_at(
    fx: tuple,  # type: ignore[type-arg]
    pe: np.ndarray,
    scratch: tuple,  # type: ignore[type-arg]
    theta: np.ndarray,
    x: np.ndarray,
    a_max: float,
    dq: np.ndarray,
) -> float:
    """The Sachdeva rate of one sample ``x`` (Sm3/h) with the effects that change the flux
    (real gas, slip: :func:`flux_rate_grad`), :func:`rate_grad` without them; dq / dtheta
    into ``dq`` and dq / d(their parameters) into ``scratch[2]`` (0 for every other
    effect's parameter, whose factor :func:`_factor_at` gives)."""
    terms = fx[0]
    i_gas, i_slip, i_crit = -1, -1, -1
    for t in range(terms.shape[0]):
        if terms[t, 0] == FX_GAS:
            i_gas = terms[t, 1]
        elif terms[t, 0] == FX_SLIP:
            i_slip = terms[t, 1]
        elif terms[t, 0] == FX_CRITICAL:
            i_crit = terms[t, 1]
    if i_crit >= 0:
        theta = _critical_theta(theta, x, pe[i_crit], scratch[4])
    d_q, d_e = scratch[2], scratch[3]
    if i_gas < 0 and i_slip < 0:
        q = rate_grad(theta, x, a_max, dq)
    else:
        q = flux_rate_grad(
            theta,
            x,
            a_max,
            dq,
            i_gas >= 0,
            pe[i_gas] if i_gas >= 0 else 0.0,
            i_slip >= 0,
            pe[i_slip] if i_slip >= 0 else 0.0,
            d_e,
        )
    if i_gas >= 0:
        d_q[i_gas] = d_e[0]
    if i_slip >= 0:
        d_q[i_slip] = d_e[1]
    if i_crit >= 0:  # p_cr' = p_cr + weight (y_c - p_cr), no gradient through y_c (torch's)
        g = dq[4]
        dq[4] = g - g * pe[i_crit]
        d_q[i_crit] = g * (scratch[4][6] - scratch[4][7])
    return q


@jit
def sachdeva_critical_ratio(
    eta_gas: float, rho_g1: float, v_liq: float, kappa: float, iterations: int
) -> float:
    """Sachdeva's critical ratio y_c of one sample by bisection on (1e-4, 0.9999), the
    arithmetic of :func:`vfm_core.physics.sachdeva_critical_ratio` (n = kappa); like it,
    no derivative (the torch path passes no gradient through the solved ratio)."""
    x = max(eta_gas, 1e-9) if not eta_gas != eta_gas else eta_gas
    k = kappa
    kk = k / (k - 1.0)
    a = v_liq * rho_g1 / x
    lo, hi = 1e-4, 0.9999
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        b = a * mid ** (1.0 / k)
        rhs = ((kk + a * (1.0 - mid)) / (kk + k / 2.0 + k * b + k / 2.0 * b**2)) ** kk
        if rhs - mid > 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@jit
def _critical_theta(theta: np.ndarray, x: np.ndarray, weight: float, out: np.ndarray) -> np.ndarray:
    """``theta`` with p_cr moved towards Sachdeva's solved ratio (CriticalRatio's hook:
    p_cr + weight (y_c - p_cr), y_c from 30 bisection steps, the ideal gas), in out[:6];
    y_c and the mechanistic p_cr in out[6], out[7]."""
    p1 = x[1] * _PA_PER_BAR
    t1 = x[3] + _KELVIN
    rho_g1 = p1 * theta[3] / (1.0 * _R_GAS * t1)
    v_liq = x[5] / theta[0] + (1.0 - x[4] - x[5]) / theta[1]
    y_c = sachdeva_critical_ratio(x[4], rho_g1, v_liq, theta[2], 30)
    for i in range(6):
        out[i] = theta[i]
    out[4] = theta[4] + weight * (y_c - theta[4])
    out[6] = y_c
    out[7] = theta[4]
    return out[:6]


@jit
def effect_values(
    w: int, ze: np.ndarray, mu_e: np.ndarray, sigma_e: np.ndarray, pe: np.ndarray
) -> None:
    """The effects' parameters of well ``w`` in SI units into ``pe``: mu + sigma z."""
    for k in range(pe.shape[0]):
        pe[k] = mu_e[k] + sigma_e[k] * ze[w, k]


@jit
def _prior_(w: int, z: np.ndarray, g: np.ndarray, sigma: np.ndarray, weight: float) -> float:
    """The gradient ``g`` of well w's parameters ``z`` to the standardised ones, plus the
    prior's pull; returns its sum of squares (for the clip)."""
    sq = 0.0
    for k in range(g.shape[0]):
        g[k] = g[k] * sigma[k] + 2.0 * weight * z[w, k]
        sq += g[k] * g[k]
    return sq


@jit
def _corrections_(
    counts: np.ndarray, w: int, size: np.ndarray, root: np.ndarray, hyper: tuple
) -> None:  # type: ignore[type-arg]
    """Adam's step counts of well w advanced by one, and each row's bias corrections."""
    lr, beta1, beta2, _ = hyper
    for r in range(counts.shape[0]):
        counts[r, w] += 1.0
        size[r] = lr / (1.0 - beta1 ** counts[r, w])
        root[r] = math.sqrt(1.0 - beta2 ** counts[r, w])


@jit
def _bounded_step_(  # noqa: PLR0913 - one well's parameters and their state
    w: int,
    z: np.ndarray,
    m: np.ndarray,
    v: np.ndarray,
    g: np.ndarray,
    rows: np.ndarray,
    size: np.ndarray,
    root: np.ndarray,
    clip: float,
    low: np.ndarray,
    high: np.ndarray,
    hyper: tuple,  # type: ignore[type-arg]
    adam: bool,
) -> None:
    """One Adam (``rows`` each parameter's bias-correction row) or SGD step of well w's
    parameters ``z`` with the gradient clip g, projected into [low, high] (torch's
    single-tensor Adam, as :func:`online`)."""
    lr, beta1, beta2, eps = hyper
    for k in range(g.shape[0]):
        gk = g[k] * clip
        if adam:
            r = rows[k]
            m[w, k] = m[w, k] + (1.0 - beta1) * (gk - m[w, k])
            v[w, k] = v[w, k] * beta2 + (1.0 - beta2) * gk * gk
            zk = z[w, k] + (-size[r]) * m[w, k] / (math.sqrt(v[w, k]) / root[r] + eps)
        else:
            zk = z[w, k] + (-lr) * gk
        z[w, k] = max(min(zk, high[k]), low[k])


@jit
def effect_rates(
    z: np.ndarray,
    x: np.ndarray,
    a_max: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    ze: np.ndarray,
    fx: tuple,  # type: ignore[type-arg]
    out: np.ndarray,
) -> None:
    """The Sachdeva rate [W, N] (Sm3/h) of ``mm`` with compiled effects (``ze`` [W, P]
    their standardised parameters, ``fx`` as :func:`_factor_at` has it), into ``out``."""
    n_wells, n_samples = out.shape
    theta = np.zeros(6)
    dq = np.zeros(6)
    pe = np.zeros(ze.shape[1])
    scratch = _scratch(fx)
    for w in range(n_wells):
        for i in range(6):
            theta[i] = mu[i] + sigma[i] * z[w, i]
        effect_values(w, ze, fx[1], fx[2], pe)
        for j in range(n_samples):
            out[w, j] = _rate_at(fx, pe, scratch, theta, x[w, j], a_max[w], dq) * _factor_at(
                fx, pe, scratch, x[w, j, 0], w, j
            )


@jit
def effect_online(  # noqa: PLR0913 - the arrays of one update
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
    bounds: tuple,  # type: ignore[type-arg]
    noise: float,
    hyper: tuple,  # type: ignore[type-arg]
    max_norm: float,
    steps: int,
    adam: bool,
    eff: tuple,  # type: ignore[type-arg]
    fx: tuple,  # type: ignore[type-arg]
) -> None:
    """``ol``'s E steps on ``mm`` with compiled effects, in place, as :func:`online` on the
    plain ``mm``: the MAP gradient through the rate q_plain F (F of :func:`effect_factor`)
    in ``z`` [W, 6] (``bounds`` its (low, high)) and the effects' parameters (``eff``: ze
    [W, P], their moments me, ve, ``rows`` [P] each one's row of ``counts``, their bounds
    low_e, high_e), the per-well clip over both, Adam (``counts`` [R, W] the step counts,
    row 0 z's; ``hyper`` lr, beta1, beta2, eps) or SGD, the projection, wells in ``hold``
    kept still. ``fx`` as :func:`_factor_at` has it."""
    ze, me, ve, rows, low_e, high_e = eff
    n_wells, n_samples = y.shape
    grad, theta, dq, zero = np.zeros(6), np.zeros(6), np.zeros(6), np.zeros(6, np.int64)
    ge, pe, scratch = np.zeros(ze.shape[1]), np.zeros(ze.shape[1]), _scratch(fx)
    size, root = np.zeros(counts.shape[0]), np.zeros(counts.shape[0])
    for w in range(n_wells):
        weight, d_factor = map_weights(mask, w, noise, scale[w])
        held, held_e = z[w].copy(), ze[w].copy()
        for _ in range(steps):
            for i in range(6):
                theta[i] = mu[i] + sigma[i] * z[w, i]
            effect_values(w, ze, fx[1], fx[2], pe)
            grad[:] = 0.0
            ge[:] = 0.0
            for j in range(n_samples):
                if not mask[w, j]:
                    continue  # torch: a zero gradient there
                q = _rate_at(fx, pe, scratch, theta, x[w, j], a_max[w], dq)
                fxj = _factor_at(fx, pe, scratch, x[w, j, 0], w, j)
                g = (q * fxj - y[w, j]) / scale[w] * d_factor
                for i in range(6):
                    grad[i] += g * (dq[i] * fxj)
                for k in range(ge.shape[0]):
                    ge[k] += g * (q * scratch[0][k] + scratch[2][k] * fxj)
            sq = _prior_(w, z, grad, sigma, weight) + _prior_(w, ze, ge, fx[2], weight)
            clip = min(max_norm / (math.sqrt(sq) + 1e-12), 1.0)
            if adam:
                _corrections_(counts, w, size, root, hyper)
            _bounded_step_(w, z, m, v, grad, zero, size, root, clip, *bounds, hyper, adam)  # type: ignore[call-arg]
            _bounded_step_(w, ze, me, ve, ge, rows, size, root, clip, low_e, high_e, hyper, adam)
            if hold[w]:
                z[w] = held
                ze[w] = held_e


@jit
def effect_fit_steps(  # noqa: PLR0913 - the arrays of a training chunk
    z: np.ndarray,
    moments: tuple,  # type: ignore[type-arg]
    counts: np.ndarray,
    todo: np.ndarray,
    data: tuple,  # type: ignore[type-arg]
    n_full: np.ndarray,
    model: tuple,  # type: ignore[type-arg]
    noise: float,
    hyper: tuple,  # type: ignore[type-arg]
    max_norm: float,
    adam: bool,
    losses: np.ndarray,
    eff: tuple,  # type: ignore[type-arg]
    fx: tuple,  # type: ignore[type-arg]
    valid: tuple,  # type: ignore[type-arg]
) -> None:
    """Training steps of :func:`vfm_core.learning.training.fit_batch` on ``mm`` with
    compiled effects, in place, as :func:`fit_steps` on the plain ``mm`` (the same
    mini-batches, objective, per-well clip, Adam or SGD, projection), the gradient through
    the rate q_plain F as :func:`effect_online` takes it. ``z`` [W, 6] and its (m, v) in
    ``moments``; ``eff`` the effects' parameters, moments, rows of ``counts`` [R, W] and
    bounds (:func:`effect_online`); ``data``: x, y, has (the chunk's mini-batches, step s
    in columns [s width, (s + 1) width), or [0, width) at every step when ``same``),
    width, same; ``model``: a_max, y_scale, mu, sigma, z_low, z_high; ``hyper`` lr,
    beta1, beta2, eps. ``fx`` the effects of the chunk's samples (:func:`_factor_at`,
    their columns those of ``x``). Each step's objective per well (before the step) is
    added to ``losses`` [W]. ``valid``: (validate, xv, yv, hv, fxv, val_out): with
    validate, the mean squared scaled error on the held-out rows after step s goes to
    ``val_out[w, s]``."""
    x, y, has, width, same = data
    a_max, scale, mu, sigma, z_low, z_high = model
    ze, me, ve, rows, low_e, high_e = eff
    grad, theta, dq, zero = np.zeros(6), np.zeros(6), np.zeros(6), np.zeros(6, np.int64)
    ge, pe, scratch = np.zeros(ze.shape[1]), np.zeros(ze.shape[1]), _scratch(fx)
    size, root = np.ones(counts.shape[0]), np.ones(counts.shape[0])
    for w in range(z.shape[0]):
        n = n_full[w]
        weight = noise**2 / max(n, 1.0) if n > 0 else 0.0
        for s in range(todo[w]):
            c0, n_data, d_factor = _mini_batch(has, w, s, width, same, n, scale[w])
            for i in range(6):
                theta[i] = mu[i] + sigma[i] * z[w, i]
            effect_values(w, ze, fx[1], fx[2], pe)
            grad[:] = 0.0
            ge[:] = 0.0
            sse = 0.0
            for j in range(c0, c0 + width):
                if not has[w, j]:
                    continue
                q = _rate_at(fx, pe, scratch, theta, x[w, j], a_max[w], dq)
                fxj = _factor_at(fx, pe, scratch, x[w, j, 0], w, j)
                e = (q * fxj - y[w, j]) / scale[w]
                sse += e * e
                g = e * d_factor
                for i in range(6):
                    grad[i] += g * (dq[i] * fxj)
                for k in range(ge.shape[0]):
                    ge[k] += g * (q * scratch[0][k] + scratch[2][k] * fxj)
            if n > 0:  # the objective: mean squared scaled error plus the weighted prior
                penalty = _squares(w, z) + _squares(w, ze)
                losses[w] += sse / max(float(n_data), 1.0) + penalty * weight
            sq = _prior_(w, z, grad, sigma, weight) + _prior_(w, ze, ge, fx[2], weight)
            clip = min(max_norm / (math.sqrt(sq) + 1e-12), 1.0)
            if adam:
                _corrections_(counts, w, size, root, hyper)
            _bounded_step_(w, z, moments[0], moments[1], grad, zero, size, root, clip, z_low, z_high, hyper, adam)  # fmt: skip
            _bounded_step_(w, ze, me, ve, ge, rows, size, root, clip, low_e, high_e, hyper, adam)
            if valid[0]:
                val_out = valid[5]
                val_out[w, s] = _effect_validation(w, z, ze, model, valid, theta, dq, pe, scratch)


@jit
def _squares(w: int, z: np.ndarray) -> float:
    """Well w's sum of squared standardised parameters (its prior penalty, unweighted)."""
    total = 0.0
    for k in range(z.shape[1]):
        total += z[w, k] * z[w, k]
    return total


@jit
def _effect_validation(  # noqa: PLR0913 - one well's parameters and its scratch arrays
    w: int,
    z: np.ndarray,
    ze: np.ndarray,
    model: tuple,  # type: ignore[type-arg]
    valid: tuple,  # type: ignore[type-arg]
    theta: np.ndarray,
    dq: np.ndarray,
    pe: np.ndarray,
    scratch: tuple,  # type: ignore[type-arg]
) -> float:
    """The mean squared scaled error of well w (``mm`` with compiled effects) on its
    held-out rows (``valid``: validate, xv, yv, hv, fxv, val_out), early stopping's
    measure."""
    _, xv, yv, hv, fxv, _ = valid
    a_max, scale, mu, sigma, _, _ = model
    for i in range(6):
        theta[i] = mu[i] + sigma[i] * z[w, i]
    effect_values(w, ze, fxv[1], fxv[2], pe)
    sse = 0.0
    n_val = 0
    for j in range(hv.shape[1]):
        if not hv[w, j]:
            continue
        n_val += 1
        q = _rate_at(fxv, pe, scratch, theta, xv[w, j], a_max[w], dq)
        e = (q * _factor_at(fxv, pe, scratch, xv[w, j, 0], w, j) - yv[w, j]) / scale[w]
        sse += e * e
    return sse / max(float(n_val), 1.0)


@jit
def hybrid_online(  # noqa: PLR0913, PLR0912, PLR0915 - the arrays of one update
    kind: int,
    z: np.ndarray,
    w1: np.ndarray,
    b1: np.ndarray,
    w2: np.ndarray,
    b2: np.ndarray,
    mz: np.ndarray,
    vz: np.ndarray,
    mw1: np.ndarray,
    vw1: np.ndarray,
    mb1: np.ndarray,
    vb1: np.ndarray,
    mw2: np.ndarray,
    vw2: np.ndarray,
    mb2: np.ndarray,
    vb2: np.ndarray,
    counts: np.ndarray,
    hold: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    mask: np.ndarray,
    a_max: np.ndarray,
    scale: np.ndarray,
    pos: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    x_mean: np.ndarray,
    x_std: np.ndarray,
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
    eff: tuple,  # type: ignore[type-arg]
    fx: tuple,  # type: ignore[type-arg]
) -> None:
    """``ol``'s E steps on ``hem`` (``kind`` 1) or ``ham`` (2) with one hidden layer, in
    place, as :func:`online` on the plain ``mm``: the closed-form gradient of the MAP
    objective (the prior on the physical parameters only, as ``ol`` has it) through the
    Sachdeva rate and the network, the per-well clip over all of a well's parameters,
    Adam (``counts`` [5 + E, W]: each parameter's step count per well, in the order z, W1,
    b1, W2, b2, then the effects' tensors) or SGD, the projection of z into its bounds,
    and wells in ``hold`` kept still. ``eff``, ``fx``: the compiled effects, whose factor
    multiplies the Sachdeva rate, as :func:`effect_online` has them (none: P = 0)."""
    ze, me, ve, rows, low_e, high_e = eff
    ge, pe, scratch = np.zeros(ze.shape[1]), np.zeros(ze.shape[1]), _scratch(fx)
    hyper, zero = (lr, beta1, beta2, eps), np.zeros(z.shape[1], np.int64)
    net, moments = (w1, b1, w2, b2), (mw1, vw1, mb1, vb1, mw2, vw2, mb2, vb2)
    work, grads = _hybrid_scratch(z.shape[1], w1.shape[2])
    data = (x, y, mask, a_max, scale, x_mean, x_std, mu, 0, y.shape[1])
    size, root = np.zeros(counts.shape[0]), np.zeros(counts.shape[0])
    for w in range(y.shape[0]):
        weight, d_fac = map_weights(mask, w, noise, scale[w])
        held = (z[w].copy(), w1[w].copy(), b1[w].copy(), w2[w].copy(), b2[w].copy(), ze[w].copy())
        for _ in range(steps):
            _hybrid_theta_(work[0], mu, sigma, z, pos, w)
            effect_values(w, ze, fx[1], fx[2], pe)
            _zero_(grads)
            ge[:] = 0.0
            gb2, _ = _hybrid_gradients_(kind, w, net, grads, ge, work, data, fx, pe, scratch, d_fac)
            # the physical parameters standardised, plus the prior's pull; then the clip
            sq = _net_squares(_prior_(w, z, grads[0], sigma, weight), grads, gb2)
            sq += _prior_(w, ze, ge, fx[2], weight)
            clip = min(max_norm / (math.sqrt(sq) + 1e-12), 1.0)
            if adam:
                _corrections_(counts, w, size, root, hyper)
            _bounded_step_(
                w, z, mz, vz, grads[0], zero, size, root, clip, z_low, z_high, hyper, adam
            )
            _net_step_(w, net, moments, grads, gb2, clip, size, root, hyper, adam)
            _bounded_step_(w, ze, me, ve, ge, rows, size, root, clip, low_e, high_e, hyper, adam)
            if hold[w]:
                z[w], w1[w], b1[w] = held[0], held[1], held[2]
                w2[w], b2[w], ze[w] = held[3], held[4], held[5]


@part
def _hybrid_scratch(n_par: int, hidden: int) -> tuple:  # type: ignore[type-arg]
    """The arrays :func:`hybrid_online` works in: (theta, dq/dtheta, the normalised sample,
    the pre-activations, the activations) and the gradients (z [n_par], W1 [6, hidden], b1,
    W2 [hidden])."""
    work = (np.zeros(6), np.zeros(6), np.zeros(6), np.zeros(hidden), np.zeros(hidden))
    grads = (np.zeros(n_par), np.zeros((6, hidden)), np.zeros(hidden), np.zeros(hidden))
    return work, grads


@part
def _hybrid_theta_(
    theta: np.ndarray, mu: np.ndarray, sigma: np.ndarray, z: np.ndarray, pos: np.ndarray, w: int
) -> None:
    """Well w's six mechanistic parameters (SI) into ``theta``: mu + sigma z for the learned
    ones (``pos`` their column in z), the prior mean for the others."""
    for i in range(6):
        theta[i] = mu[i] + sigma[i] * z[w, pos[i]] if pos[i] >= 0 else mu[i]


@part
def _zero_(grads: tuple) -> None:  # type: ignore[type-arg]
    """The hybrid's gradients (z, W1, b1, W2) set to 0."""
    gz, gw1, gb1, gw2 = grads
    for i in range(gz.shape[0]):
        gz[i] = 0.0
    for k in range(gb1.shape[0]):
        gb1[k] = 0.0
        gw2[k] = 0.0
        for i in range(6):
            gw1[i, k] = 0.0


@part
def _net_forward_(
    net: tuple,  # type: ignore[type-arg]
    w: int,
    x: np.ndarray,
    j: int,
    mean: np.ndarray,
    std: np.ndarray,
    work: tuple,  # type: ignore[type-arg]
) -> float:
    """Well w's one-hidden-layer network on its sample j of ``x`` (normalised by ``mean``,
    ``std`` into ``work``'s xn, the pre-activations and ReLU activations kept there for
    the backward pass): its output."""
    w1, b1, w2, b2 = net
    xn, pre, act = work[2], work[3], work[4]
    for i in range(6):
        xn[i] = (x[w, j, i] - mean[w, i]) / std[w, i]
    o = b2[w, 0]
    for k in range(pre.shape[0]):
        a = b1[w, k]
        for i in range(6):
            a += xn[i] * w1[w, i, k]
        pre[k] = a
        act[k] = a if not a <= 0.0 else 0.0  # ReLU (a NaN passes)
        o += act[k] * w2[w, k, 0]
    return o


@part
def _net_backward_(net: tuple, w: int, g_o: float, grads: tuple, work: tuple) -> None:  # type: ignore[type-arg]
    """The gradient ``g_o`` of the network's output back into W2, b1 and W1 (``grads``),
    through the ReLU (threshold_backward: none where the pre-activation is not positive)."""
    w2 = net[2]
    gw1, gb1, gw2 = grads[1], grads[2], grads[3]
    xn, pre, act = work[2], work[3], work[4]
    for k in range(pre.shape[0]):
        gw2[k] += g_o * act[k]
        if pre[k] > 0:
            g_a = g_o * w2[w, k, 0]
            gb1[k] += g_a
            for i in range(6):
                gw1[i, k] += xn[i] * g_a


@part
def _hybrid_gradients_(  # noqa: PLR0913 - one well's samples and its gradients
    kind: int,
    w: int,
    net: tuple,  # type: ignore[type-arg]
    grads: tuple,  # type: ignore[type-arg]
    ge: np.ndarray,
    work: tuple,  # type: ignore[type-arg]
    data: tuple,  # type: ignore[type-arg]
    fx: tuple,  # type: ignore[type-arg]
    pe: np.ndarray,
    scratch: tuple,  # type: ignore[type-arg]
    d_factor: float,
) -> tuple[float, float]:
    """The MAP data term's gradient of well w's hybrid (``kind`` 1 hem, 2 ham) summed over
    its samples in columns [c0, c0 + width) into ``grads`` (z, W1, b1, W2) and the
    effects' ``ge``; returns b2's and the sum of squared scaled errors. ``data``: x, y,
    mask, a_max, y_scale, x_mean, x_std, mu, c0, width."""
    x, y, mask, a_max, scale, x_mean, x_std, mu, c0, width = data
    theta, dq, gz = work[0], work[1], grads[0]
    gb2 = 0.0
    sse = 0.0
    for j in range(c0, c0 + width):
        if not mask[w, j]:
            continue
        fxj = _factor_at(fx, pe, scratch, x[w, j, 0], w, j)
        o = _net_forward_(net, w, x, j, x_mean, x_std, work)
        if kind == 2:
            theta[5] = mu[5] * math.exp(o)
            plain = _rate_at(fx, pe, scratch, theta, x[w, j], a_max[w], dq)
            rate = plain * fxj
            dq_do = dq[5] * theta[5] * fxj
        else:
            plain = _rate_at(fx, pe, scratch, theta, x[w, j], a_max[w], dq)
            rate = plain * fxj + scale[w] * o
            dq_do = scale[w]
        e = (rate - y[w, j]) / scale[w]
        sse += e * e
        g = e * d_factor
        for i in range(gz.shape[0]):
            gz[i] += g * (dq[i] * fxj)
        for k in range(ge.shape[0]):
            ge[k] += g * (plain * scratch[0][k] + scratch[2][k] * fxj)
        g_o = g * dq_do
        gb2 += g_o
        _net_backward_(net, w, g_o, grads, work)
    return gb2, sse


@part
def _net_squares(sq: float, grads: tuple, gb2: float) -> float:  # type: ignore[type-arg]
    """``sq`` plus the squares of the network's gradients (b1, W2, W1, then b2), for the clip."""
    gw1, gb1, gw2 = grads[1], grads[2], grads[3]
    for k in range(gb1.shape[0]):
        sq += gb1[k] * gb1[k] + gw2[k] * gw2[k]
        for i in range(6):
            sq += gw1[i, k] * gw1[i, k]
    sq += gb2 * gb2
    return sq


@part
def _net_step_(  # noqa: PLR0913 - one well's network and its state
    w: int,
    net: tuple,  # type: ignore[type-arg]
    moments: tuple,  # type: ignore[type-arg]
    grads: tuple,  # type: ignore[type-arg]
    gb2: float,
    clip: float,
    size: np.ndarray,
    root: np.ndarray,
    hyper: tuple,  # type: ignore[type-arg]
    adam: bool,
) -> None:
    """One Adam (rows 1-4 of the bias corrections ``size``, ``root``: W1, b1, W2, b2) or
    SGD step of well w's network with the clipped gradients, as torch's single-tensor Adam."""
    w1, b1, w2, b2 = net
    mw1, vw1, mb1, vb1, mw2, vw2, mb2, vb2 = moments
    _adam_(w1[w].reshape(-1), grads[1].reshape(-1), mw1[w].reshape(-1), vw1[w].reshape(-1),
           clip, size[1], root[1], hyper, adam)  # fmt: skip
    _adam_(b1[w], grads[2], mb1[w], vb1[w], clip, size[2], root[2], hyper, adam)
    _adam_(w2[w, :, 0], grads[3], mw2[w, :, 0], vw2[w, :, 0], clip, size[3], root[3], hyper, adam)
    lr, beta1, beta2, eps = hyper
    gi = gb2 * clip
    if adam:
        mb2[w, 0] = mb2[w, 0] + (1.0 - beta1) * (gi - mb2[w, 0])
        vb2[w, 0] = vb2[w, 0] * beta2 + (1.0 - beta2) * gi * gi
        denom = math.sqrt(vb2[w, 0]) / root[4] + eps
        b2[w, 0] = b2[w, 0] + (-size[4]) * mb2[w, 0] / denom
    else:
        b2[w, 0] = b2[w, 0] + (-lr) * gi


@jit
def fit_steps(  # noqa: PLR0913, PLR0912, PLR0915 - the arrays of a training chunk
    kind: int,
    z: np.ndarray,
    w1: np.ndarray,
    b1: np.ndarray,
    w2: np.ndarray,
    b2: np.ndarray,
    moments: tuple,  # type: ignore[type-arg]
    counts: np.ndarray,
    todo: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    has: np.ndarray,
    width: int,
    same: bool,
    n_full: np.ndarray,
    a_max: np.ndarray,
    scale: np.ndarray,
    pos: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    x_mean: np.ndarray,
    x_std: np.ndarray,
    z_low: np.ndarray,
    z_high: np.ndarray,
    noise: float,
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    max_norm: float,
    adam: bool,
    losses: np.ndarray,
    validate: bool,
    xv: np.ndarray,
    yv: np.ndarray,
    hv: np.ndarray,
    val_out: np.ndarray,
) -> None:
    """Training steps of :func:`vfm_core.learning.training.fit_batch` on the plain ``mm``
    (``kind`` 0), ``hem`` (1) or ``ham`` (2, one hidden layer), in place: well ``w`` takes
    ``todo[w]`` steps, step s on the mini-batch in columns [s width, (s + 1) width) of
    ``x``, ``y``, ``has`` (or columns [0, width) at every step when ``same``). A step is
    the MAP objective's closed-form gradient (:class:`MapObjective` with the prior on
    every parameter, weighted by sigma^2 / ``n_full``, the data term by the mini-batch's
    count), the per-well clip, Adam (``moments``: (m, v) of z, W1, b1, W2, b2; ``counts``
    [5, W] each parameter's step count) or SGD, and the projection of z into its bounds.
    Each step's objective per well (before the step, as ``MapObjective.gradients_`` gives
    it) is added to ``losses`` [W]. With ``validate``, the mean squared scaled error on the
    held-out rows ``xv``, ``yv``, ``hv`` after step s goes to ``val_out[w, s]`` (early
    stopping's measure)."""
    mz, vz = moments[0], moments[1]
    net, hyper = (w1, b1, w2, b2), (lr, beta1, beta2, eps)
    work, grads = _hybrid_scratch(z.shape[1], w1.shape[2])
    data = (x, y, has, a_max, scale, x_mean, x_std, mu)
    size, root = np.ones(5), np.ones(5)
    for w in range(z.shape[0]):
        n = n_full[w]
        weight = noise**2 / max(n, 1.0) if n > 0 else 0.0
        for s in range(todo[w]):
            c0, n_data, d_factor = _mini_batch(has, w, s, width, same, n, scale[w])
            _hybrid_theta_(work[0], mu, sigma, z, pos, w)
            _zero_(grads)
            sse, gb2 = _fit_gradients_(kind, w, c0, width, net, grads, work, data, d_factor)
            if n > 0:  # the objective: mean squared scaled error plus the weighted prior
                penalty = _fit_penalty(kind, w, z, net)
                losses[w] += sse / max(float(n_data), 1.0) + penalty * weight
            sq, gb2 = _fit_prior_pull_(kind, w, z, net, grads, gb2, sigma, weight)
            clip = min(max_norm / (math.sqrt(sq) + 1e-12), 1.0)
            if adam:
                _corrections_(counts, w, size, root, hyper)
            _adam_(z[w], grads[0], mz[w], vz[w], clip, size[0], root[0], hyper, adam)
            for i in range(z.shape[1]):
                z[w, i] = max(min(z[w, i], z_high[i]), z_low[i])
            if kind != 0:
                _net_step_(w, net, moments[2:], grads, gb2, clip, size, root, hyper, adam)
            if validate:
                _hybrid_theta_(work[0], mu, sigma, z, pos, w)
                valid = (xv, yv, hv, a_max, scale, x_mean, x_std, mu)
                val_out[w, s] = _fit_validation(kind, w, net, work, valid)


@jit
def hybrid_effect_fit_steps(  # noqa: PLR0913 - the arrays of a training chunk
    kind: int,
    params: tuple,  # type: ignore[type-arg]
    moments: tuple,  # type: ignore[type-arg]
    counts: np.ndarray,
    todo: np.ndarray,
    data: tuple,  # type: ignore[type-arg]
    n_full: np.ndarray,
    model: tuple,  # type: ignore[type-arg]
    noise: float,
    hyper: tuple,  # type: ignore[type-arg]
    max_norm: float,
    adam: bool,
    losses: np.ndarray,
    eff: tuple,  # type: ignore[type-arg]
    fx: tuple,  # type: ignore[type-arg]
    valid: tuple,  # type: ignore[type-arg]
) -> None:
    """Training steps of :func:`vfm_core.learning.training.fit_batch` on ``hem`` (``kind``
    1) or ``ham`` (2) with compiled effects, in place, as :func:`fit_steps` on the plain
    hybrid (the prior on every parameter, the network's He-scaled), the gradient through
    the effects as :func:`hybrid_online` takes it (:func:`_hybrid_gradients_`).
    ``params`` z, W1, b1, W2, b2 and ``moments`` their (m, v) in that order; ``counts``
    [5 + E, W]; ``model``: a_max, y_scale, pos, mu, sigma, x_mean, x_std, z_low, z_high;
    ``data``, ``eff``, ``fx``, ``valid``, ``losses`` as :func:`effect_fit_steps` has them."""
    z, w1, b1, w2, b2 = params
    net = (w1, b1, w2, b2)
    x, y, has, width, same = data
    a_max, scale, pos, mu, sigma, x_mean, x_std, z_low, z_high = model
    ze, me, ve, rows, low_e, high_e = eff
    ge, pe, scratch = np.zeros(ze.shape[1]), np.zeros(ze.shape[1]), _scratch(fx)
    work, grads = _hybrid_scratch(z.shape[1], w1.shape[2])
    size, root = np.ones(counts.shape[0]), np.ones(counts.shape[0])
    for w in range(z.shape[0]):
        n = n_full[w]
        weight = noise**2 / max(n, 1.0) if n > 0 else 0.0
        for s in range(todo[w]):
            c0, n_data, d_factor = _mini_batch(has, w, s, width, same, n, scale[w])
            _hybrid_theta_(work[0], mu, sigma, z, pos, w)
            effect_values(w, ze, fx[1], fx[2], pe)
            _zero_(grads)
            ge[:] = 0.0
            step = (x, y, has, a_max, scale, x_mean, x_std, mu, c0, width)
            gb2, sse = _hybrid_gradients_(kind, w, net, grads, ge, work, step, fx, pe, scratch, d_factor)  # fmt: skip
            if n > 0:  # the objective: mean squared scaled error plus the weighted prior
                penalty = _fit_penalty(kind, w, z, net) + _squares(w, ze)
                losses[w] += sse / max(float(n_data), 1.0) + penalty * weight
            sq, gb2 = _fit_prior_pull_(kind, w, z, net, grads, gb2, sigma, weight)
            sq += _prior_(w, ze, ge, fx[2], weight)
            clip = min(max_norm / (math.sqrt(sq) + 1e-12), 1.0)
            if adam:
                _corrections_(counts, w, size, root, hyper)
            _adam_(z[w], grads[0], moments[0][w], moments[1][w], clip, size[0], root[0], hyper, adam)  # fmt: skip
            for i in range(z.shape[1]):
                z[w, i] = max(min(z[w, i], z_high[i]), z_low[i])
            _net_step_(w, net, moments[2:], grads, gb2, clip, size, root, hyper, adam)
            _bounded_step_(w, ze, me, ve, ge, rows, size, root, clip, low_e, high_e, hyper, adam)
            if valid[0]:
                _hybrid_theta_(work[0], mu, sigma, z, pos, w)
                effect_values(w, ze, fx[1], fx[2], pe)
                val_out = valid[5]
                val_out[w, s] = _hybrid_effect_validation(kind, w, net, work, model, valid, pe, scratch)  # fmt: skip


@jit
def _hybrid_effect_validation(  # noqa: PLR0913 - one well's network and its scratch arrays
    kind: int,
    w: int,
    net: tuple,  # type: ignore[type-arg]
    work: tuple,  # type: ignore[type-arg]
    model: tuple,  # type: ignore[type-arg]
    valid: tuple,  # type: ignore[type-arg]
    pe: np.ndarray,
    scratch: tuple,  # type: ignore[type-arg]
) -> float:
    """The mean squared scaled error of well w's hybrid with compiled effects on its
    held-out rows (``valid``: validate, xv, yv, hv, fxv, val_out; theta in ``work`` and the
    effects' values in ``pe`` already), early stopping's measure."""
    _, xv, yv, hv, fxv, _ = valid
    a_max, scale, _, mu, _, x_mean, x_std, _, _ = model
    theta, dq = work[0], work[1]
    sse = 0.0
    n_val = 0
    for j in range(hv.shape[1]):
        if not hv[w, j]:
            continue
        n_val += 1
        o = _net_forward_(net, w, xv, j, x_mean, x_std, work)
        fxj = _factor_at(fxv, pe, scratch, xv[w, j, 0], w, j)
        if kind == 2:
            theta[5] = mu[5] * math.exp(o)
            rate = _rate_at(fxv, pe, scratch, theta, xv[w, j], a_max[w], dq) * fxj
        else:
            rate = _rate_at(fxv, pe, scratch, theta, xv[w, j], a_max[w], dq) * fxj + scale[w] * o
        e = (rate - yv[w, j]) / scale[w]
        sse += e * e
    return sse / max(float(n_val), 1.0)


@part
def _mini_batch(
    has: np.ndarray, w: int, s: int, width: int, same: bool, n: float, scale: float
) -> tuple[int, int, float]:
    """Step s's mini-batch of well w: its first column (0 at every step when ``same``),
    its count of rows, and the data term's factor 2 / (count y_scale) (0 for a well
    without data, ``n`` its full count)."""
    c0 = 0 if same else s * width
    n_data = 0
    for j in range(c0, c0 + width):
        if has[w, j]:
            n_data += 1
    d_factor = 2.0 / max(float(n_data), 1.0) / scale if n > 0 else 0.0
    return c0, n_data, d_factor


@part
def _fit_gradients_(  # noqa: PLR0913 - one step's mini-batch and its gradients
    kind: int,
    w: int,
    c0: int,
    width: int,
    net: tuple,  # type: ignore[type-arg]
    grads: tuple,  # type: ignore[type-arg]
    work: tuple,  # type: ignore[type-arg]
    data: tuple,  # type: ignore[type-arg]
    d_factor: float,
) -> tuple[float, float]:
    """The data term's gradient of well w's ``mm`` (``kind`` 0) or hybrid (1 hem, 2 ham)
    over the mini-batch's columns [c0, c0 + width) into ``grads`` (z, W1, b1, W2); returns
    the sum of squared scaled errors and b2's gradient. ``data``: x, y, has, a_max,
    y_scale, x_mean, x_std, mu."""
    x, y, has, a_max, scale, x_mean, x_std, mu = data
    theta, dq, gz = work[0], work[1], grads[0]
    gb2 = 0.0
    sse = 0.0
    for j in range(c0, c0 + width):
        if not has[w, j]:
            continue
        if kind == 0:
            rate = rate_grad(theta, x[w, j], a_max[w], dq)
            dq_do = 0.0
        else:
            o = _net_forward_(net, w, x, j, x_mean, x_std, work)
            if kind == 2:
                theta[5] = mu[5] * math.exp(o)
                rate = rate_grad(theta, x[w, j], a_max[w], dq)
                dq_do = dq[5] * theta[5]
            else:
                rate = rate_grad(theta, x[w, j], a_max[w], dq) + scale[w] * o
                dq_do = scale[w]
        e = (rate - y[w, j]) / scale[w]
        sse += e * e
        g = e * d_factor
        for i in range(gz.shape[0]):
            gz[i] += g * dq[i]
        if kind != 0:
            g_o = g * dq_do
            gb2 += g_o
            _net_backward_(net, w, g_o, grads, work)
    return sse, gb2


@part
def _fit_penalty(kind: int, w: int, z: np.ndarray, net: tuple) -> float:  # type: ignore[type-arg]
    """Well w's prior penalty before its weight: sum z^2, and for a hybrid the network's
    He-scaled squares (WellMLP.prior_penalty)."""
    w1, b1, w2, b2 = net
    penalty = 0.0
    for i in range(z.shape[1]):
        penalty += z[w, i] * z[w, i]
    if kind != 0:
        hidden = b1.shape[1]
        net1 = 0.0
        net2 = 0.0
        nb = 0.0
        for k in range(hidden):
            net2 += w2[w, k, 0] * w2[w, k, 0]
            nb += b1[w, k] * b1[w, k]
            for i in range(6):
                net1 += w1[w, i, k] * w1[w, i, k]
        penalty += net1 / (2.0 / 6.0) + nb + net2 / (2.0 / hidden) + b2[w, 0] ** 2
    return penalty


@part
def _fit_prior_pull_(  # noqa: PLR0913 - one well's parameters and gradients
    kind: int,
    w: int,
    z: np.ndarray,
    net: tuple,  # type: ignore[type-arg]
    grads: tuple,  # type: ignore[type-arg]
    gb2: float,
    sigma: np.ndarray,
    weight: float,
) -> tuple[float, float]:
    """The gradients to the standardised z plus every parameter's prior pull (the
    network's He-scaled, WellMLP.prior_gradients), in place; returns their sum of squares
    (for the clip) and b2's gradient."""
    w1, b1, w2, b2 = net
    gz, gw1, gb1, gw2 = grads
    hidden = gb1.shape[0]
    he1 = 2.0 / (2.0 / 6.0)  # WellMLP.prior_gradients: 2 / he_var, he_var = 2 / fan_in
    he2 = 2.0 / (2.0 / hidden) if hidden > 0 else 0.0
    sq = 0.0
    for i in range(gz.shape[0]):
        gz[i] = gz[i] * sigma[i] + 2.0 * weight * z[w, i]
        sq += gz[i] * gz[i]
    if kind != 0:
        for k in range(hidden):
            gb1[k] += 2.0 * weight * b1[w, k]
            gw2[k] += he2 * weight * w2[w, k, 0]
            sq += gb1[k] * gb1[k] + gw2[k] * gw2[k]
            for i in range(6):
                gw1[i, k] += he1 * weight * w1[w, i, k]
                sq += gw1[i, k] * gw1[i, k]
        gb2 += 2.0 * weight * b2[w, 0]
        sq += gb2 * gb2
    return sq, gb2


@part
def _fit_validation(kind: int, w: int, net: tuple, work: tuple, valid: tuple) -> float:  # type: ignore[type-arg]
    """The mean squared scaled error of well w on its held-out rows (``valid``: xv, yv,
    hv, a_max, y_scale, x_mean, x_std, mu; theta in ``work`` already), early stopping's
    measure."""
    xv, yv, hv, a_max, scale, x_mean, x_std, mu = valid
    w1, b1, w2, b2 = net
    theta, dq, xn = work[0], work[1], work[2]
    sse = 0.0
    n_val = 0
    for j in range(hv.shape[1]):
        if not hv[w, j]:
            continue
        n_val += 1
        o = b2[w, 0]
        if kind != 0:
            for i in range(6):
                xn[i] = (xv[w, j, i] - x_mean[w, i]) / x_std[w, i]
            for k in range(b1.shape[1]):
                a = b1[w, k]
                for i in range(6):
                    a += xn[i] * w1[w, i, k]
                if not a <= 0.0:
                    o += a * w2[w, k, 0]
        if kind == 2:
            theta[5] = mu[5] * math.exp(o)
            rate = rate_grad(theta, xv[w, j], a_max[w], dq)
        elif kind == 1:
            rate = rate_grad(theta, xv[w, j], a_max[w], dq) + scale[w] * o
        else:
            rate = rate_grad(theta, xv[w, j], a_max[w], dq)
        e = (rate - yv[w, j]) / scale[w]
        sse += e * e
    return sse / max(float(n_val), 1.0)


@jit
def _pull_(g: np.ndarray, p: np.ndarray, k: float) -> float:
    """``g += k p`` (a Gaussian prior's pull) in place; returns the sum of g's squares."""
    sq = 0.0
    for i in range(g.size):
        g[i] += k * p[i]
        sq += g[i] * g[i]
    return sq


@jit
def _adam_(  # noqa: PLR0913 - one parameter's update
    p: np.ndarray,
    g: np.ndarray,
    m: np.ndarray,
    v: np.ndarray,
    clip: float,
    size: float,
    root: float,
    hyper: tuple[float, float, float, float],
    adam: bool,
) -> None:
    """One Adam (``hyper``: lr, beta1, beta2, eps) or SGD step of the flat parameter ``p``
    with gradient ``clip g``, in place (torch's single-tensor Adam, as in
    :func:`hybrid_online`)."""
    lr, beta1, beta2, eps = hyper
    for i in range(p.size):
        gi = g[i] * clip
        if adam:
            m[i] = m[i] + (1.0 - beta1) * (gi - m[i])
            v[i] = v[i] * beta2 + (1.0 - beta2) * gi * gi
            p[i] = p[i] + (-size) * m[i] / (math.sqrt(v[i]) / root + eps)
        else:
            p[i] = p[i] + (-lr) * gi


@jit
def lr_fit_steps(  # noqa: PLR0913, PLR0915 - the arrays of a training chunk
    params: tuple,  # type: ignore[type-arg]
    moments: tuple,  # type: ignore[type-arg]
    counts: np.ndarray,
    todo: np.ndarray,
    xn: np.ndarray,
    y: np.ndarray,
    has: np.ndarray,
    width: int,
    same: bool,
    n_full: np.ndarray,
    scale: np.ndarray,
    noise: float,
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    max_norm: float,
    adam: bool,
    losses: np.ndarray,
    validate: bool,
    xv: np.ndarray,
    yv: np.ndarray,
    hv: np.ndarray,
    val_out: np.ndarray,
    prec: np.ndarray,
) -> None:
    """:func:`fit_steps` for ``lr``: q = y_scale (w . x_norm + b), the prior w ~ N(0, 1 /
    prec) (``prec`` [W, 6], the model's ``w_prec``), b ~ N(1, 1); ``params`` (w [W, 6], b
    [W]), ``moments`` ((m, v) of each), ``counts`` [2, W]; ``xn`` (and ``xv``) normalised."""
    wt, bt = params
    mw, vw, mb, vb = moments
    n_wells, n_in = wt.shape
    g = np.zeros(n_in)
    size, root = np.ones(2), np.ones(2)
    hyper = (lr, beta1, beta2, eps)
    for w in range(n_wells):
        n = n_full[w]
        weight = noise**2 / max(n, 1.0) if n > 0 else 0.0
        for s in range(todo[w]):
            c0, n_data, d_factor = _mini_batch(has, w, s, width, same, n, scale[w])
            sse, gb = _lr_gradients_(params, (xn, y, has, scale), w, c0, width, d_factor, g)
            if n > 0:
                penalty = (bt[w] - 1.0) ** 2
                for i in range(n_in):
                    penalty += prec[w, i] * wt[w, i] * wt[w, i]
                losses[w] += sse / max(float(n_data), 1.0) + penalty * weight
            sq = 0.0
            for i in range(n_in):
                g[i] += 2.0 * weight * prec[w, i] * wt[w, i]
                sq += g[i] * g[i]
            gb += 2.0 * weight * (bt[w] - 1.0)
            sq += gb * gb
            clip = min(max_norm / (math.sqrt(sq) + 1e-12), 1.0)
            if adam:
                _corrections_(counts, w, size, root, hyper)
            _adam_(wt[w], g, mw[w], vw[w], clip, size[0], root[0], hyper, adam)
            gbs = np.array([gb])
            _adam_(
                bt[w : w + 1],
                gbs,
                mb[w : w + 1],
                vb[w : w + 1],
                clip,
                size[1],
                root[1],
                hyper,
                adam,
            )
            if validate:
                val_out[w, s] = _lr_val(wt[w], bt[w], xv[w], yv[w], hv[w], scale[w])


@part
def _lr_gradients_(  # noqa: PLR0913 - one step's mini-batch
    params: tuple,  # type: ignore[type-arg]
    data: tuple,  # type: ignore[type-arg]
    w: int,
    c0: int,
    width: int,
    d_factor: float,
    g: np.ndarray,
) -> tuple[float, float]:
    """The data term's gradient of well w's ``lr`` over the mini-batch's columns [c0,
    c0 + width) (``data``: xn, y, has, y_scale): w's into ``g``; returns the sum of squared
    scaled errors and b's gradient."""
    wt, bt = params
    xn, y, has, scale = data
    for i in range(g.shape[0]):
        g[i] = 0.0
    gb = 0.0
    sse = 0.0
    for j in range(c0, c0 + width):
        if not has[w, j]:
            continue
        dot = 0.0
        for i in range(g.shape[0]):
            dot += xn[w, j, i] * wt[w, i]
        e = (scale[w] * (dot + bt[w]) - y[w, j]) / scale[w]
        sse += e * e
        d = e * d_factor * scale[w]
        for i in range(g.shape[0]):
            g[i] += d * xn[w, j, i]
        gb += d
    return sse, gb


@part
def _lr_val(
    wt: np.ndarray, bt: float, xv: np.ndarray, yv: np.ndarray, hv: np.ndarray, scale: float
) -> float:
    """The mean squared scaled error of one well's ``lr`` on its held-out rows."""
    sse = 0.0
    n_val = 0
    for j in range(hv.shape[0]):
        if hv[j]:
            dot = 0.0
            for i in range(wt.shape[0]):
                dot += xv[j, i] * wt[i]
            e = (scale * (dot + bt) - yv[j]) / scale
            sse += e * e
            n_val += 1
    return sse / max(float(n_val), 1.0)


@jit
def _mtl_forward(params: tuple, inp: np.ndarray) -> tuple:  # type: ignore[type-arg]
    """``mtl``'s two residual blocks on the rows ``inp`` (normalised inputs, then the task
    vector): the activations the backward pass needs and the output before ``b_out``."""
    _, w_in, b_in, w1a, w1b, b1a, b1b, w2a, w2b, b2a, b2b, w_out, _ = params
    h0 = np.dot(inp, w_in) + b_in
    u_a = np.dot(np.maximum(h0, 0.0), w1a) + b1a
    h1 = h0 + (np.dot(np.maximum(u_a, 0.0), w2a) + b2a)
    u_b = np.dot(np.maximum(h1, 0.0), w1b) + b1b
    h2 = h1 + (np.dot(np.maximum(u_b, 0.0), w2b) + b2b)
    return h0, u_a, h1, u_b, h2, np.dot(h2, w_out)


@jit
def _mtl_backward(  # noqa: PLR0913 - the forward pass's activations
    params: tuple,  # type: ignore[type-arg]
    inp: np.ndarray,
    h0: np.ndarray,
    u_a: np.ndarray,
    h1: np.ndarray,
    u_b: np.ndarray,
    h2: np.ndarray,
    g: np.ndarray,
) -> tuple:  # type: ignore[type-arg]
    """The gradients of :func:`_mtl_forward`'s output rows, weighted by ``g`` [rows, 1]
    (``MultiTask.rate_vjp``'s pullback): the shared tensors' (in the model's order, w_in
    to b_out, flat) and each row's gradient of its task vector [rows, task]."""
    _, w_in, _, w1a, w1b, _, _, w2a, w2b, _, _, w_out, _ = params
    n_in = inp.shape[1] - params[0].shape[1]
    gw_out = np.dot(h2.T, g)
    gb_out = g.sum(0)
    dh = np.dot(g, w_out.T)
    # block b (the last), then block a
    gw2b = np.dot(np.maximum(u_b, 0.0).T, dh)
    gb2b = dh.sum(0)
    du = np.where(u_b > 0.0, np.dot(dh, w2b.T), 0.0)
    gw1b = np.dot(np.maximum(h1, 0.0).T, du)
    gb1b = du.sum(0)
    dh = dh + np.where(h1 > 0.0, np.dot(du, w1b.T), 0.0)
    gw2a = np.dot(np.maximum(u_a, 0.0).T, dh)
    gb2a = dh.sum(0)
    du = np.where(u_a > 0.0, np.dot(dh, w2a.T), 0.0)
    gw1a = np.dot(np.maximum(h0, 0.0).T, du)
    gb1a = du.sum(0)
    dh = dh + np.where(h0 > 0.0, np.dot(du, w1a.T), 0.0)
    gw_in = np.dot(inp.T, dh)
    gb_in = dh.sum(0)
    d_beta = np.dot(dh, np.ascontiguousarray(w_in[n_in:].T))
    shared = (
        gw_in.reshape(-1), gb_in, gw1a.reshape(-1), gw1b.reshape(-1), gb1a, gb1b,
        gw2a.reshape(-1), gw2b.reshape(-1), gb2a, gb2b, gw_out.reshape(-1), gb_out,
    )  # fmt: skip
    return shared, d_beta


@jit
def mtl_online(  # noqa: PLR0913, PLR0915 - the arrays of one update
    params: tuple,  # type: ignore[type-arg]
    moments: tuple,  # type: ignore[type-arg]
    count: np.ndarray,
    idle: np.ndarray,
    zn: np.ndarray,
    y: np.ndarray,
    mask: np.ndarray,
    scale: np.ndarray,
    steps: int,
    beta1: float,
    beta2: float,
    eps: float,
    lr: float,
    max_norm: float,
) -> None:
    """``ol``'s E Adam steps on ``mtl`` with two residual blocks (``MultiTask.rate_vjp``'s
    closed form), in place: the mean squared scaled error of each well's rows (``ol`` has
    no prior on a network), the per-well clip of the task vectors beta, the clip of the
    shared weights by their global norm (``clip_grad_norm_``), torch's single-tensor Adam
    on all 13 tensors (``count[0]``: their common step count), then the idle wells' beta
    put back (their moments still move, as torch's optimiser moves them). ``params``:
    beta, w_in, b_in, w1.0, w1.1, b1.0, b1.1, w2.0, w2.1, b2.0, b2.1, w_out, b_out (the
    model's parameter order); ``zn`` the normalised inputs [W, N, 6]."""
    beta, w_in, b_in, w1a, w1b, b1a, b1b, w2a, w2b, b2a, b2b, w_out, b_out = params
    n_wells, n_cols = mask.shape
    n_in = zn.shape[2]
    task = beta.shape[1]
    rows = 0
    for w in range(n_wells):
        for j in range(n_cols):
            if mask[w, j]:
                rows += 1
    if rows == 0:
        return
    inp = np.zeros((rows, n_in + task))
    target = np.zeros(rows)
    well = np.zeros(rows, dtype=np.int64)
    d_row = np.zeros(rows)
    r = 0
    for w in range(n_wells):
        n = 0
        for j in range(n_cols):
            if mask[w, j]:
                n += 1
        for j in range(n_cols):
            if mask[w, j]:
                well[r] = w
                target[r] = y[w, j]
                d_row[r] = 2.0 / max(float(n), 1.0) / scale[w] * scale[w]  # d loss / d out per e
                for i in range(n_in):
                    inp[r, i] = zn[w, j, i]
                r += 1
    held = beta.copy()
    grads_beta = np.zeros_like(beta)
    for _ in range(steps):
        for r in range(rows):
            for i in range(task):
                inp[r, n_in + i] = beta[well[r], i]
        h0, u_a, h1, u_b, h2, out = _mtl_forward(params, inp)
        g = np.zeros((rows, 1))
        for r in range(rows):
            w = well[r]
            q = scale[w] * ((1.0 + out[r, 0]) + b_out[0])
            g[r, 0] = (q - target[r]) / scale[w] * d_row[r]
        shared, d_beta = _mtl_backward(params, inp, h0, u_a, h1, u_b, h2, g)
        grads_beta[:] = 0.0
        for r in range(rows):
            for i in range(task):
                grads_beta[well[r], i] += d_beta[r, i]
        # beta: clipped per well; the shared weights: by their global norm
        coef = _mtl_clip_(grads_beta, shared, max_norm)
        _mtl_adam_(params, moments, grads_beta, shared, coef, count, (lr, beta1, beta2, eps), True)
        for w in range(n_wells):
            if idle[w]:
                for i in range(task):
                    beta[w, i] = held[w, i]


@jit
def _mtl_adam_(  # noqa: PLR0913 - the 13 tensors' update
    params: tuple,  # type: ignore[type-arg]
    moments: tuple,  # type: ignore[type-arg]
    grads_beta: np.ndarray,
    shared: tuple,  # type: ignore[type-arg]
    coef: float,
    count: np.ndarray,
    hyper: tuple[float, float, float, float],
    adam: bool,
) -> None:
    """One Adam (or SGD) step of ``mtl``'s 13 tensors, in place: beta with ``grads_beta``
    (clipped per well already), the shared tensors with ``coef`` times their gradients
    (the global-norm clip); ``count[0]``, the common step count, is advanced."""
    beta, w_in, b_in, w1a, w1b, b1a, b1b, w2a, w2b, b2a, b2b, w_out, b_out = params
    lr, beta1, beta2, _ = hyper
    size, root = lr, 1.0
    if adam:
        count[0] += 1.0
        size = lr / (1.0 - beta1 ** count[0])
        root = math.sqrt(1.0 - beta2 ** count[0])
    m = moments
    _adam_(beta.reshape(-1), grads_beta.reshape(-1), m[0].reshape(-1), m[1].reshape(-1),
           1.0, size, root, hyper, adam)  # fmt: skip
    _adam_(w_in.reshape(-1), shared[0], m[2].reshape(-1), m[3].reshape(-1), coef, size, root, hyper, adam)  # fmt: skip
    _adam_(b_in, shared[1], m[4], m[5], coef, size, root, hyper, adam)
    _adam_(w1a.reshape(-1), shared[2], m[6].reshape(-1), m[7].reshape(-1), coef, size, root, hyper, adam)  # fmt: skip
    _adam_(w1b.reshape(-1), shared[3], m[8].reshape(-1), m[9].reshape(-1), coef, size, root, hyper, adam)  # fmt: skip
    _adam_(b1a, shared[4], m[10], m[11], coef, size, root, hyper, adam)
    _adam_(b1b, shared[5], m[12], m[13], coef, size, root, hyper, adam)
    _adam_(w2a.reshape(-1), shared[6], m[14].reshape(-1), m[15].reshape(-1), coef, size, root, hyper, adam)  # fmt: skip
    _adam_(w2b.reshape(-1), shared[7], m[16].reshape(-1), m[17].reshape(-1), coef, size, root, hyper, adam)  # fmt: skip
    _adam_(b2a, shared[8], m[18], m[19], coef, size, root, hyper, adam)
    _adam_(b2b, shared[9], m[20], m[21], coef, size, root, hyper, adam)
    _adam_(w_out.reshape(-1), shared[10], m[22].reshape(-1), m[23].reshape(-1), coef, size, root, hyper, adam)  # fmt: skip
    _adam_(b_out, shared[11], m[24], m[25], coef, size, root, hyper, adam)


@jit
def _mtl_clip_(grads_beta: np.ndarray, shared: tuple, max_norm: float) -> float:  # type: ignore[type-arg]
    """Clip each well's task-vector gradient to ``max_norm`` in place (1e-12 as
    ``clip_per_well_``); returns the shared tensors' global-norm factor
    (``clip_grad_norm_``, 1e-6)."""
    for w in range(grads_beta.shape[0]):
        sq = 0.0
        for i in range(grads_beta.shape[1]):
            sq += grads_beta[w, i] * grads_beta[w, i]
        c = min(max_norm / (math.sqrt(sq) + 1e-12), 1.0)
        for i in range(grads_beta.shape[1]):
            grads_beta[w, i] *= c
    total = 0.0
    for t in range(len(shared)):
        total += np.sum(shared[t] * shared[t])
    return min(max_norm / (math.sqrt(total) + 1e-6), 1.0)


@jit
def _mtl_rows(  # noqa: PLR0913 - one step's rows
    params: tuple,  # type: ignore[type-arg]
    zn: np.ndarray,
    y: np.ndarray,
    has: np.ndarray,
    c0: int,
    width: int,
) -> tuple:  # type: ignore[type-arg]
    """The rows of columns ``[c0, c0 + width)`` that are samples, compacted: the network's
    inputs (the task vectors filled in), targets, wells, and the samples per well."""
    beta = params[0]
    n_wells, n_in, task = has.shape[0], zn.shape[2], beta.shape[1]
    n_data = np.zeros(n_wells)
    rows = 0
    for w in range(n_wells):
        for j in range(width):
            if has[w, c0 + j]:
                n_data[w] += 1.0
                rows += 1
    inp = np.zeros((rows, n_in + task))
    target = np.zeros(rows)
    well = np.zeros(rows, dtype=np.int64)
    r = 0
    for w in range(n_wells):
        for j in range(width):
            if has[w, c0 + j]:
                well[r] = w
                target[r] = y[w, c0 + j]
                for i in range(n_in):
                    inp[r, i] = zn[w, c0 + j, i]
                for i in range(task):
                    inp[r, n_in + i] = beta[w, i]
                r += 1
    return inp, target, well, n_data


@jit
def _mtl_penalty(params: tuple) -> float:  # type: ignore[type-arg]
    """The He prior of ``mtl``'s shared tensors (``MultiTask.prior_penalty``'s ``shared``)."""
    _, w_in, b_in, w1a, w1b, b1a, b1b, w2a, w2b, b2a, b2b, w_out, b_out = params
    shared = 0.0
    for wt in (w_in, w1a, w1b, w2a, w2b, w_out):
        shared += np.sum(wt * wt) / (2.0 / wt.shape[0])
    for bt in (b_in, b1a, b1b, b2a, b2b, b_out):
        shared += np.sum(bt * bt)
    return shared


@jit
def mtl_fit_steps(  # noqa: PLR0913, PLR0912, PLR0915 - the arrays of a training chunk
    params: tuple,  # type: ignore[type-arg]
    moments: tuple,  # type: ignore[type-arg]
    count: np.ndarray,
    steps: int,
    zn: np.ndarray,
    y: np.ndarray,
    has: np.ndarray,
    width: int,
    same: bool,
    n_full: np.ndarray,
    scale: np.ndarray,
    n_model: int,
    noise: float,
    hyper: tuple[float, float, float, float],
    max_norm: float,
    adam: bool,
    losses: np.ndarray,
    validate: bool,
    zv: np.ndarray,
    yv: np.ndarray,
    hv: np.ndarray,
    has_val: np.ndarray,
    val_out: np.ndarray,
) -> None:
    """``steps`` training steps of ``mtl`` with two residual blocks (``fit_batch``'s loop on
    a shared model), in place: step s on the columns ``[s width, (s + 1) width)`` of the
    normalised inputs ``zn`` (all of them each step when ``same``). Each step is the
    gradient of the MAP objective (:class:`vfm_core.learning.training.MapObjective` with
    ``MultiTask.rate_vjp``: the data term of each well's rows, its task vector's N(0, 1)
    prior, and the shared He prior spread over the ``n_model`` wells), the per-well clip of
    the task vectors, the global-norm clip of the shared tensors, one Adam or SGD step of
    all 13 tensors (``count[0]``, their common step count). ``losses`` [steps, W]: each
    well's objective before the step; with ``validate``, ``val_out[s]`` is the held-out
    error after step s summed over the wells of ``has_val`` (one early-stopping decision
    for the shared network)."""
    beta = params[0]
    weight, pull = _mtl_weights(n_full, noise, n_model)
    grads_beta = np.zeros_like(beta)
    for s in range(steps):
        c0 = 0 if same else s * width
        inp, target, well, n_data = _mtl_rows(params, zn, y, has, c0, width)
        sse = np.zeros(has.shape[0])
        grads_beta[:] = 0.0
        data = (inp, target, well, n_data, n_full, scale)
        shared = _mtl_data_gradients_(params, data, sse, grads_beta)
        penalty = _mtl_penalty(params) / n_model
        for w in range(has.shape[0]):
            if n_full[w] > 0:
                sq = 0.0
                for i in range(beta.shape[1]):
                    sq += beta[w, i] * beta[w, i]
                losses[s, w] = sse[w] / max(n_data[w], 1.0) + (sq + penalty) * weight[w]
            for i in range(beta.shape[1]):
                grads_beta[w, i] += 2.0 * weight[w] * beta[w, i]
        _mtl_shared_pull_(params, shared, pull)
        coef = _mtl_clip_(grads_beta, shared, max_norm)
        _mtl_adam_(params, moments, grads_beta, shared, coef, count, hyper, adam)
        if validate:
            _mtl_validation_(params, (zv, yv, hv, has_val, scale), sse, val_out, s)


@part
def _mtl_weights(n_full: np.ndarray, noise: float, n_model: int) -> tuple:  # type: ignore[type-arg]
    """Each well's prior weight noise^2 / n (0 without data) and the shared prior's pull,
    their sum over the ``n_model`` wells (each well carries 1/W of the shared prior)."""
    weight = np.zeros(n_full.shape[0])
    total_weight = 0.0
    for w in range(n_full.shape[0]):
        if n_full[w] > 0:
            weight[w] = noise**2 / max(n_full[w], 1.0)
        total_weight += weight[w]
    return weight, total_weight / n_model


@part
def _mtl_data_gradients_(
    params: tuple,  # type: ignore[type-arg]
    data: tuple,  # type: ignore[type-arg]
    sse: np.ndarray,
    grads_beta: np.ndarray,
) -> tuple:  # type: ignore[type-arg]
    """The data term of one step's rows (``data``: the network's inputs, targets, wells,
    rows per well, each well's full count, y_scale): each well's squared scaled errors
    into ``sse``, the task vectors' gradients into ``grads_beta``; returns the shared
    tensors' gradients (zeros without rows)."""
    inp, target, well, n_data, n_full, scale = data
    b_out = params[12]
    rows = target.shape[0]
    if rows == 0:
        return (
            np.zeros(params[1].size), np.zeros(params[2].size), np.zeros(params[3].size),
            np.zeros(params[4].size), np.zeros(params[5].size), np.zeros(params[6].size),
            np.zeros(params[7].size), np.zeros(params[8].size), np.zeros(params[9].size),
            np.zeros(params[10].size), np.zeros(params[11].size), np.zeros(params[12].size),
        )  # fmt: skip
    h0, u_a, h1, u_b, h2, out = _mtl_forward(params, inp)
    g = np.zeros((rows, 1))
    for r in range(rows):
        w = well[r]
        if n_full[w] > 0:
            e = (scale[w] * ((1.0 + out[r, 0]) + b_out[0]) - target[r]) / scale[w]
            sse[w] += e * e
            g[r, 0] = e * (2.0 / max(n_data[w], 1.0) / scale[w]) * scale[w]
    shared, d_beta = _mtl_backward(params, inp, h0, u_a, h1, u_b, h2, g)
    for r in range(rows):
        for i in range(grads_beta.shape[1]):
            grads_beta[well[r], i] += d_beta[r, i]
    return shared


@part
def _mtl_shared_pull_(params: tuple, shared: tuple, pull: float) -> None:  # type: ignore[type-arg]
    """The He prior's pull on the shared tensors' gradients (weights: 1 / fan-in; biases: 1)."""
    _, w_in, b_in, w1a, w1b, b1a, b1b, w2a, w2b, b2a, b2b, w_out, b_out = params
    for t, wt in ((0, w_in), (2, w1a), (3, w1b), (6, w2a), (7, w2b), (10, w_out)):
        _pull_(shared[t], wt.reshape(-1), 2.0 * pull / (2.0 / wt.shape[0]))
    for t, bt in ((1, b_in), (4, b1a), (5, b1b), (8, b2a), (9, b2b), (11, b_out)):
        _pull_(shared[t], bt, 2.0 * pull)


@part
def _mtl_validation_(
    params: tuple,  # type: ignore[type-arg]
    valid: tuple,  # type: ignore[type-arg]
    sse: np.ndarray,
    val_out: np.ndarray,
    s: int,
) -> None:
    """The held-out error after step s (``valid``: zv, yv, hv, has_val, y_scale), summed
    over the wells of has_val, into ``val_out[s]`` (left as it is without held-out rows)."""
    zv, yv, hv, has_val, scale = valid
    b_out = params[12]
    inp, target, well, n_val = _mtl_rows(params, zv, yv, hv, 0, hv.shape[1])
    if target.shape[0] > 0:
        out = _mtl_forward(params, inp)[5]
        sse[:] = 0.0
        for r in range(target.shape[0]):
            w = well[r]
            e = (scale[w] * (1.0 + (out[r, 0] + b_out[0])) - target[r]) / scale[w]
            sse[w] += e * e
        v = 0.0
        for w in range(sse.shape[0]):
            if has_val[w]:
                v += sse[w] / max(n_val[w], 1.0)
        val_out[s] = v


@jit
def _nn_val(  # noqa: PLR0913 - one well's network
    w1: np.ndarray,
    b1: np.ndarray,
    w2: np.ndarray,
    b2: np.ndarray,
    w3: np.ndarray,
    b3: np.ndarray,
    xv: np.ndarray,
    yv: np.ndarray,
    hv: np.ndarray,
    scale: float,
) -> float:
    """The mean squared scaled error of one well's ``nn`` on its held-out rows."""
    h1 = np.maximum(np.dot(np.ascontiguousarray(xv), w1) + b1, 0.0)
    h2 = np.maximum(np.dot(h1, w2) + b2, 0.0)
    o = np.dot(h2, w3)
    sse = 0.0
    n_val = 0
    for j in range(hv.shape[0]):
        if hv[j]:
            e = (scale * (1.0 + (o[j, 0] + b3[0])) - yv[j]) / scale
            sse += e * e
            n_val += 1
    return sse / max(float(n_val), 1.0)


@jit
def nn_fit_steps(  # noqa: PLR0913, PLR0915 - the arrays of a training chunk
    params: tuple,  # type: ignore[type-arg]
    moments: tuple,  # type: ignore[type-arg]
    counts: np.ndarray,
    todo: np.ndarray,
    xn: np.ndarray,
    y: np.ndarray,
    has: np.ndarray,
    width: int,
    same: bool,
    n_full: np.ndarray,
    scale: np.ndarray,
    noise: float,
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    max_norm: float,
    adam: bool,
    losses: np.ndarray,
    validate: bool,
    xv: np.ndarray,
    yv: np.ndarray,
    hv: np.ndarray,
    val_out: np.ndarray,
) -> None:
    """:func:`fit_steps` for ``nn`` with two hidden ReLU layers: q = y_scale (1 + o), o the
    network of the normalised inputs ``xn``; ``params`` (W1, b1, W2, b2, W3, b3) and
    ``moments`` ((m, v) of each, in that order), ``counts`` [6, W]. The products go to
    BLAS (np.dot), the rest is fused here: the gradient of the MAP objective (the data
    term and the He prior on every weight), the per-well clip and Adam or SGD; with
    ``validate``, the held-out error after each step, as :func:`fit_steps` (``xv``
    normalised)."""
    w1, b1, w2, b2, w3, b3 = params
    fan = (w1.shape[1], w2.shape[1], w3.shape[1])
    size = np.zeros(6)
    root = np.zeros(6)
    hyper = (lr, beta1, beta2, eps)
    for w in range(w1.shape[0]):
        n = n_full[w]
        weight = noise**2 / max(n, 1.0) if n > 0 else 0.0
        for s in range(todo[w]):
            c0, n_data, d_factor = _mini_batch(has, w, s, width, same, n, scale[w])
            x0 = np.ascontiguousarray(xn[w, c0 : c0 + width])
            a1, h1, a2, h2, o = _nn_forward(params, w, x0)
            delta = np.zeros((width, 1))
            sse = 0.0
            for j in range(width):
                if has[w, c0 + j]:
                    q = scale[w] * (1.0 + (o[j, 0] + b3[w, 0]))
                    e = (q - y[w, c0 + j]) / scale[w]
                    sse += e * e
                    delta[j, 0] = e * d_factor * scale[w]
            if n > 0:
                penalty = _nn_penalty(params, w, fan)
                losses[w] += sse / max(float(n_data), 1.0) + penalty * weight
            grads = _nn_backward(params, w, x0, (a1, h1, a2, h2), delta)
            sq = _nn_prior_pull_(params, w, grads, fan, weight)
            clip = min(max_norm / (math.sqrt(sq) + 1e-12), 1.0)
            if adam:
                _corrections_(counts, w, size, root, hyper)
            _nn_step_(params, moments, grads, w, clip, size, root, hyper, adam)
            if validate:
                val_out[w, s] = _nn_val(
                    w1[w], b1[w], w2[w], b2[w], w3[w], b3[w], xv[w], yv[w], hv[w], scale[w]
                )


@part
def _nn_forward(params: tuple, w: int, x0: np.ndarray) -> tuple:  # type: ignore[type-arg]
    """Well w's two-hidden-layer ``nn`` on the mini-batch ``x0`` (products in BLAS): the
    pre-activations and ReLU activations of both layers and the output before b3."""
    w1, b1, w2, b2, w3, _ = params
    a1 = np.dot(x0, w1[w])
    for j in range(a1.shape[0]):
        for k in range(a1.shape[1]):
            a1[j, k] += b1[w, k]
    h1 = np.maximum(a1, 0.0)
    a2 = np.dot(h1, w2[w])
    for j in range(a2.shape[0]):
        for k in range(a2.shape[1]):
            a2[j, k] += b2[w, k]
    h2 = np.maximum(a2, 0.0)
    return a1, h1, a2, h2, np.dot(h2, w3[w])


@part
def _nn_penalty(params: tuple, w: int, fan: tuple) -> float:  # type: ignore[type-arg]
    """Well w's He prior penalty before its weight (WellMLP.prior_penalty)."""
    w1, b1, w2, b2, w3, b3 = params
    penalty = 0.0
    for t in range(3):
        wt = (w1, w2, w3)[t][w]
        bt = (b1, b2, b3)[t][w]
        penalty += np.sum(wt * wt) / (2.0 / fan[t]) + np.sum(bt * bt)
    return penalty


@part
def _nn_backward(params: tuple, w: int, x0: np.ndarray, acts: tuple, delta: np.ndarray) -> tuple:  # type: ignore[type-arg]
    """Backpropagation of the output's gradient ``delta`` (as WellMLP.pullback): the
    gradients of W1, b1, W2, b2, W3, b3."""
    _, _, w2, _, w3, _ = params
    a1, h1, a2, h2 = acts
    g3 = np.dot(h2.T, delta)
    gb3 = delta.sum(0)
    d2 = np.dot(delta, w3[w].T)
    d2 = np.where(a2 > 0.0, d2, 0.0)
    g2 = np.dot(h1.T, d2)
    gb2 = d2.sum(0)
    d1 = np.dot(d2, w2[w].T)
    d1 = np.where(a1 > 0.0, d1, 0.0)
    g1 = np.dot(x0.T, d1)
    gb1 = d1.sum(0)
    return g1, gb1, g2, gb2, g3, gb3


@part
def _nn_prior_pull_(params: tuple, w: int, grads: tuple, fan: tuple, weight: float) -> float:  # type: ignore[type-arg]
    """The He prior's pull added to the gradients in place; their sum of squares (the clip)."""
    w1, b1, w2, b2, w3, b3 = params
    g1, gb1, g2, gb2, g3, gb3 = grads
    k1 = 2.0 / (2.0 / fan[0]) * weight
    k2 = 2.0 / (2.0 / fan[1]) * weight
    k3 = 2.0 / (2.0 / fan[2]) * weight
    kb = 2.0 * weight
    sq = _pull_(g1.reshape(-1), w1[w].reshape(-1), k1)
    sq += _pull_(gb1, b1[w], kb)
    sq += _pull_(g2.reshape(-1), w2[w].reshape(-1), k2)
    sq += _pull_(gb2, b2[w], kb)
    sq += _pull_(g3.reshape(-1), w3[w].reshape(-1), k3)
    sq += _pull_(gb3, b3[w], kb)
    return sq


@part
def _nn_step_(  # noqa: PLR0913 - one well's network and its state
    params: tuple,  # type: ignore[type-arg]
    moments: tuple,  # type: ignore[type-arg]
    grads: tuple,  # type: ignore[type-arg]
    w: int,
    clip: float,
    size: np.ndarray,
    root: np.ndarray,
    hyper: tuple,  # type: ignore[type-arg]
    adam: bool,
) -> None:
    """One Adam (row t of ``size``, ``root`` for the t-th tensor) or SGD step of well w's
    six tensors with the clipped gradients."""
    w1, b1, w2, b2, w3, b3 = params
    g1, gb1, g2, gb2, g3, gb3 = grads
    m1, v1, mb1, vb1, m2, v2, mb2, vb2, m3, v3, mb3, vb3 = moments
    _adam_(w1[w].reshape(-1), g1.reshape(-1), m1[w].reshape(-1), v1[w].reshape(-1),
           clip, size[0], root[0], hyper, adam)  # fmt: skip
    _adam_(b1[w], gb1, mb1[w], vb1[w], clip, size[1], root[1], hyper, adam)
    _adam_(w2[w].reshape(-1), g2.reshape(-1), m2[w].reshape(-1), v2[w].reshape(-1),
           clip, size[2], root[2], hyper, adam)  # fmt: skip
    _adam_(b2[w], gb2, mb2[w], vb2[w], clip, size[3], root[3], hyper, adam)
    _adam_(w3[w].reshape(-1), g3.reshape(-1), m3[w].reshape(-1), v3[w].reshape(-1),
           clip, size[4], root[4], hyper, adam)  # fmt: skip
    _adam_(b3[w], gb3, mb3[w], vb3[w], clip, size[5], root[5], hyper, adam)


@jit
def log_rate_grad(
    kind: int,
    state: np.ndarray,
    w: int,
    x: np.ndarray,
    a_max: float,
    pos: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    n_phys: int,
    x_mean: np.ndarray,
    x_std: np.ndarray,
    w1: np.ndarray,
    b1: np.ndarray,
    y_scale: np.ndarray,
    theta: np.ndarray,
    dq: np.ndarray,
    xn: np.ndarray,
    act: np.ndarray,
    H: np.ndarray,
    fx: tuple,  # type: ignore[type-arg]
    pe: np.ndarray,
    scratch: tuple,  # type: ignore[type-arg]
    j: int,
) -> float:
    """log h of one sample ``x`` of well ``w`` (log of the rate clamped at 1e-12) and its
    gradient H [D] with respect to the well's filter state ``state[w]``: the standardised
    physical parameters (``n_phys`` of them, theta[i] = mu[i] + sigma[i] state[w, pos[i]],
    or mu[i] where pos[i] < 0), the compiled effects' parameters (P of them, after the
    physical ones: the Sachdeva rate times their factor, :func:`effect_factor`), then for a
    hybrid the output layer of its network (the hidden weights W2, then the bias b2; W1,
    b1 below it stay as fitted). ``kind``: 0 ``mm``, 1 ``hem`` (rate + y_scale o), 2
    ``ham`` (C_D = C_D0 exp(o)). ``fx``, ``pe``, ``scratch``: the effects of sample ``j``
    (:func:`_factor_at`), P = 0 without effects."""
    n_eff = pe.shape[0]
    for i in range(6):
        theta[i] = mu[i] + sigma[i] * state[w, pos[i]] if pos[i] >= 0 else mu[i]
    for k in range(n_eff):
        pe[k] = fx[1][k] + fx[2][k] * state[w, n_phys + k]
    head = n_phys + n_eff  # where the network's output layer starts
    hidden = w1.shape[2]
    d_log_o = 0.0
    fxj = _factor_at(fx, pe, scratch, x[0], w, j)
    if kind == 0:
        plain = _rate_at(fx, pe, scratch, theta, x, a_max, dq)
        rate = plain * fxj
    else:
        for i in range(6):
            xn[i] = (x[i] - x_mean[w, i]) / x_std[w, i]
        o = state[w, head + hidden]
        for k in range(hidden):
            a = b1[w, k]
            for i in range(6):
                a += xn[i] * w1[w, i, k]
            act[k] = a if not a <= 0.0 else 0.0  # ReLU (a NaN passes, as torch's)
            o += act[k] * state[w, head + k]
        if kind == 2:
            theta[5] = mu[5] * math.exp(o)
            plain = _rate_at(fx, pe, scratch, theta, x, a_max, dq)
            rate = plain * fxj
            d_log_o = dq[5] * theta[5] * fxj  # dq / do, divided by the rate below
        else:
            plain = _rate_at(fx, pe, scratch, theta, x, a_max, dq)
            rate = plain * fxj + y_scale[w] * o
            d_log_o = y_scale[w]
    clamped = max(rate, 1e-12)
    ok = rate >= 1e-12  # torch.clamp's gradient: none below the floor
    for i in range(n_phys):
        H[i] = dq[i] * fxj * sigma[i] / clamped if ok else 0.0
    for k in range(n_eff):
        d_rate = plain * scratch[0][k] + scratch[2][k] * fxj
        H[n_phys + k] = d_rate * fx[2][k] / clamped if ok else 0.0
    if kind != 0:
        g = d_log_o / clamped if ok else 0.0
        for k in range(hidden):
            H[head + k] = g * act[k]
        H[head + hidden] = g
    return math.log(clamped)


@jit
def bayes(  # noqa: PLR0913, PLR0912, PLR0915 - one Kalman step, as BayesianFilter._update
    state: np.ndarray,
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
    kind: int,
    a_max: np.ndarray,
    pos: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    n_phys: int,
    x_mean: np.ndarray,
    x_std: np.ndarray,
    w1: np.ndarray,
    b1: np.ndarray,
    y_scale: np.ndarray,
    rules: tuple,  # type: ignore[type-arg]
    errors: tuple,  # type: ignore[type-arg]
    fx: tuple,  # type: ignore[type-arg]
) -> bool:
    """One step of ``BayesianFilter._update`` over every well's measurements, in place;
    True when the filter took one. ``rules``: the filter's constants (low, high,
    start_var, q, keep, fixed, huber, gate, adapt, calibrate, never, reset_after,
    noise_floor, z90, ns_per_year). ``errors`` (cal [W, 2, 3], counted [1], cap,
    discount): where cap > 0, each started well's well tests' squared standardised
    forecast errors (from its state before the batch) are learned into ``cal`` and
    counted (:func:`_forecast_error_`: ``BayesianFilter._forecast_errors`` and
    ``_learn_calibration``)."""
    d = state.shape[1]
    pe, scratch = np.zeros(fx[1].shape[0]), _scratch(fx)  # the effects (_factor_at)
    theta, dq, xn, act, H, gain = _bayes_scratch(d, w1.shape[2])
    filt = (state, P, last, noise, h, scale, started)
    tally = (run, updates, downweighted, refused_count, resets, changed)
    taken = False
    for w in range(y.shape[0]):
        # a started well's well tests' forecast errors (its state before the batch): in a
        # pass first (phase 0) if a well test follows its first measurement, else in that
        # one's own step; then (phase 1) its measurements in column order (the torch path
        # takes every well's k-th together: the wells do not interact)
        ahead = errors[2] > 0 and started[w] and _later_test(mask, ready, y, well_test, w)
        own = errors[2] > 0 and started[w] and not ahead
        for phase in range(0 if ahead else 1, 2):
            for j in range(y.shape[1]):
                if not (mask[w, j] and ready[w] and y[w, j] > 0) or (
                    phase == 0 and not well_test[w, j]
                ):
                    continue
                s, t = (1 if well_test[w, j] else 0), time_ns[w, j]
                # log h and its gradient H at the current parameters (_log_rate_and_gradient)
                log_h = log_rate_grad(
                    kind, state, w, x[w, j], a_max[w], pos, mu, sigma, n_phys, x_mean, x_std,
                    w1, b1, y_scale, theta, dq, xn, act, H, fx, pe, scratch, j,
                )  # fmt: skip
                _masked_(H, rules[4])  # by keep: h at this sample, as the update takes it
                log_y = math.log(y[w, j])
                if phase == 0 or (own and s == 1):  # (phase 1: the first measurement)
                    _forecast_error_(filt, rules, errors, H, w, t, log_y - log_h)
                if phase == 1:
                    sd_given = _bayes_arrival_(filt, rules, gain[3], H, w, s, t)
                    if _bayes_update_(filt, tally, rules, gain, H, w, s, log_y, log_h, sd_given):
                        taken = True
    if taken:  # model.project_() after an update: every well within its bounds
        _project_(state, rules[0], rules[1])
    return taken


@part
def _masked_(H: np.ndarray, keep: np.ndarray) -> None:
    """H [D] times ``keep`` [D] (1 where the filter learns a parameter, else 0), in place."""
    for i in range(H.shape[0]):
        H[i] = H[i] * keep[i]


@part
def _project_(state: np.ndarray, low: np.ndarray, high: np.ndarray) -> None:
    """Every well's state [W, D] within its bounds ``low``, ``high`` [D], in place."""
    for w in range(state.shape[0]):
        for i in range(state.shape[1]):
            state[w, i] = max(min(state[w, i], high[i]), low[i])


@part
def _bayes_scratch(d: int, hidden: int) -> tuple:  # type: ignore[type-arg]
    """The arrays :func:`bayes` works in: theta, dq, the normalised sample, the hidden
    activations, H [d]; and the gain's (K, u, v [d], P before the update, A P [d, d])."""
    gain = (np.zeros(d), np.zeros(d), np.zeros(d), np.zeros((d, d)), np.zeros((d, d)))
    return np.zeros(6), np.zeros(6), np.zeros(6), np.zeros(hidden), np.zeros(d), gain


@part
def _forecast_terms(h: np.ndarray, P: np.ndarray, q: np.ndarray, w: int) -> tuple[float, float]:
    """The two terms of well w's forecast variance of its log rate at a sample, h P h and
    h Q h with h [D] the sensitivity at that sample (the latter times the years since its
    last update gives the drift's share)."""
    hph = 0.0
    hqh = 0.0
    for a in range(h.shape[0]):
        hqh += h[a] ** 2 * q[a]
        for b in range(h.shape[0]):
            hph += h[a] * P[w, a, b] * h[b]
    return hph, hqh


@part
def _bayes_arrival_(
    filt: tuple,  # type: ignore[type-arg]
    rules: tuple,  # type: ignore[type-arg]
    Pg: np.ndarray,
    H: np.ndarray,
    w: int,
    s: int,
    t: int,
) -> float:
    """A measurement of well w from meter s arrives at ``t``: the start variance
    (``BayesianFilter._start_var``) if the well has no filter state yet, the spread the filter gave it before it arrived (``_spread`` with
    h = ``H``, the sensitivity at this sample; the return value), then P after the drift since the last update (``_grow``, kept in
    ``Pg`` too, in case the measurement is refused)."""
    _, P, last, noise, _, scale, started = filt
    start_var, q, never, ns_per_year = rules[2], rules[3], rules[10], rules[14]
    d = Pg.shape[0]
    if not started[w]:  # a model but no filter state yet: its start variance
        for a in range(d):
            for b in range(d):
                P[w, a, b] = 0.0
            P[w, a, a] = start_var[a]
        last[w] = t
        started[w] = True
    hph, hqh = _forecast_terms(H, P, q, w)
    dt = float(max(t - last[w], 0)) / ns_per_year if last[w] != never else 0.0
    var = hph + hqh * dt + noise[w, s] ** 2
    sd_given = math.sqrt(max(var, 0.0)) * math.exp(scale[w, s])
    if last[w] != never and t != never:
        dt = float(max(t - last[w], 0)) / ns_per_year
    else:
        dt = 0.0
    for a in range(d):
        P[w, a, a] = P[w, a, a] + q[a] * dt
    Pg[:, :] = P[w]
    last[w] = t
    return sd_given


@part
def _later_test(
    mask: np.ndarray, ready: np.ndarray, y: np.ndarray, well_test: np.ndarray, w: int
) -> bool:
    """Whether well w has a well test after its first measurement in this batch."""
    seen = False
    for j in range(y.shape[1]):
        if mask[w, j] and ready[w] and y[w, j] > 0:
            if seen and well_test[w, j]:
                return True
            seen = True
    return False


@part
def _forecast_error_(
    filt: tuple,  # type: ignore[type-arg]
    rules: tuple,  # type: ignore[type-arg]
    errors: tuple,  # type: ignore[type-arg]
    H: np.ndarray,
    w: int,
    t: int,
    error: float,
) -> None:
    """Learn from the squared standardised error z^2 of the forecast the filter gave for
    a well test of well w (at ``t``) before learning from it (``errors``: cal, counted,
    cap, discount): the log error ``error`` over the forecast's variance h (P + Q dt) h
    + s^2 with h = ``H``, the sensitivity at the well test's sample (``_spread`` of the well-test meter, without the intervals' factors), capped
    at ``cap`` (the gate's square: a refused error counts as one at the gate); the
    discounted count and sum of z^2 in cal[w, 1] grow by 1 and z^2 (the older ones
    discounted). An error that is not finite is not counted. A rate below the kernels'
    floor (1e-12 Sm3/h, where the update clamps its log) counts as one at the gate."""
    _, P, last, noise, _, _, _ = filt
    q, ns_per_year = rules[3], rules[14]
    cal, counted, cap, discount = errors
    hph, hqh = _forecast_terms(H, P, q, w)
    dt = float(max(t - last[w], 0)) / ns_per_year
    z2 = error**2 / (hph + hqh * dt + noise[w, 1] ** 2)
    if math.isfinite(z2):
        cal[w, 1, 0] = discount * cal[w, 1, 0] + 1.0
        cal[w, 1, 1] = discount * cal[w, 1, 1] + min(z2, cap)
        counted[0] += 1


@part
def _quadratic(H: np.ndarray, Pg: np.ndarray) -> float:
    """H P H^T, summed row by row."""
    hph = 0.0
    for a in range(H.shape[0]):
        for b in range(H.shape[0]):
            hph += H[a] * Pg[a, b] * H[b]
    return hph


@part
def _bayes_update_(  # noqa: PLR0913 - one measurement and the filter
    filt: tuple,  # type: ignore[type-arg]
    tally: tuple,  # type: ignore[type-arg]
    rules: tuple,  # type: ignore[type-arg]
    gain: tuple,  # type: ignore[type-arg]
    H: np.ndarray,
    w: int,
    s: int,
    log_y: float,
    log_h: float,
    sd_given: float,
) -> bool:
    """One measurement (log y) against the filter's log h and its gradient H (masked by
    ``keep`` already): the conformal calibration, the robust gate (Huber weight, refusal, a
    reset after a run of refusals), the Kalman gain and Joseph update, the bounded state,
    the adapted meter noise and the counts. False when the measurement is refused."""
    state, P, _, noise, h, scale, _ = filt
    run, updates, downweighted, refused_count, resets, changed = tally
    low, high, _, q, _, fixed, huber, gate, adapt, calibrate = rules[:10]
    reset_after, noise_floor, z90 = rules[11], rules[12], rules[13]
    d, K, Pg = H.shape[0], gain[0], gain[3]
    R = noise[w, s] ** 2
    if calibrate > 0:  # adaptive conformal calibration of this meter's intervals
        miss = 1.0 if abs(log_y - log_h) > z90 * sd_given else 0.0
        scale[w, s] += calibrate * (miss - 0.1)
    zz = abs(log_y - log_h) / math.sqrt(_quadratic(H, Pg) + R)
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
        return False
    if weight < 1:
        downweighted[w] += 1
    Rk = R / weight
    hph = _joseph_(P, w, H, gain, Rk)
    innov = log_y - log_h
    for i in range(d):
        state[w, i] = max(min(state[w, i] + K[i] * innov, high[i]), low[i])
        h[w, i] = H[i]
    if adapt > 0 and not fixed[s]:
        # the meter's noise follows the innovations (beyond the parameters')
        cap = (huber if huber != 0 else 3.0) ** 2 * (hph + R)
        sample = min(innov**2, cap) - hph
        new = (1.0 - adapt) * R + adapt * max(sample, noise_floor**2)
        noise[w, s] = max(math.sqrt(new), noise_floor)
    updates[w] += 1
    changed[w] = True
    return True


@part
def _joseph_(P: np.ndarray, w: int, H: np.ndarray, gain: tuple, Rk: float) -> float:  # type: ignore[type-arg]
    """The Kalman gain K (into ``gain``) and well w's P after the update in Joseph form:
    (I - K H) P (I - K H)^T + K K^T Rk, symmetrised. I - K H is the identity less a rank
    one, so each product is O(D^2): A P = P - K (H P), (A P) A^T = A P - (A P H) K^T.
    Returns H P H^T (P before the update)."""
    K, u, v, Pg, AP = gain
    d = H.shape[0]
    hph = _quadratic(H, Pg)
    S = hph + Rk
    for a in range(d):
        ph_a = 0.0
        for b in range(d):
            ph_a += Pg[a, b] * H[b]
        K[a] = ph_a / S
    for b in range(d):
        acc = 0.0
        for c in range(d):
            acc += H[c] * Pg[c, b]
        v[b] = acc
    for a in range(d):
        acc = 0.0
        for b in range(d):
            AP[a, b] = Pg[a, b] - K[a] * v[b]
            acc += AP[a, b] * H[b]
        u[a] = acc
    for a in range(d):
        for b in range(d):
            P[w, a, b] = AP[a, b] - u[a] * K[b] + K[a] * K[b] * Rk
    for a in range(d):
        for b in range(a + 1, d):
            mean = 0.5 * (P[w, a, b] + P[w, b, a])
            P[w, a, b] = mean
            P[w, b, a] = mean
    return hph


@jit
def bayes_spread(
    mean: np.ndarray,
    H: np.ndarray,
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
    h + s^2), h = H[w, j] [D] the sensitivity at the predicted sample, times the meter's calibration factor (NaN for a well without filter state),
    as std = rate sd and the central 90 % bounds rate exp(+-z90 sd)."""
    n_wells, n_samples = mean.shape
    for w in range(n_wells):
        for j in range(n_samples):
            rate = mean[w, j]
            if not started[w]:
                std[w, j] = np.nan
                p05[w, j] = np.nan
                p95[w, j] = np.nan
                continue
            s = 1 if well_test[w, j] else 0
            hph, hqh = _forecast_terms(H[w, j], P, q, w)
            dt = float(max(time_ns[w, j] - last[w], 0)) / ns_per_year if last[w] != never else 0.0
            var = hph + hqh * dt + noise[w, s] ** 2
            sd = math.sqrt(max(var, 0.0)) * math.exp(scale[w, s])
            std[w, j] = rate * sd
            p05[w, j] = rate * math.exp(-z90 * sd)
            p95[w, j] = rate * math.exp(z90 * sd)


@jit
def bayes_gradients(  # noqa: PLR0913 - the compiled filter's model and a batch
    state: np.ndarray,
    h: np.ndarray,
    keep: np.ndarray,
    x: np.ndarray,
    mask: np.ndarray,
    ready: np.ndarray,
    kind: int,
    a_max: np.ndarray,
    pos: np.ndarray,
    mu: np.ndarray,
    sigma: np.ndarray,
    n_phys: int,
    x_mean: np.ndarray,
    x_std: np.ndarray,
    w1: np.ndarray,
    b1: np.ndarray,
    y_scale: np.ndarray,
    fx: tuple,  # type: ignore[type-arg]
    out: np.ndarray,
) -> None:
    """The sensitivity h [W, N, D] (into ``out``) of every sample's log rate to the
    filtered parameters, masked by ``keep``, for :func:`bayes_spread`: the gradient
    :func:`log_rate_grad` gives at the well's current state (``state`` [W, D]); the
    filter's stored h [W, D] where there is no sample or no model."""
    d = state.shape[1]
    pe, scratch = np.zeros(fx[1].shape[0]), _scratch(fx)
    theta, dq, xn, act, H, _ = _bayes_scratch(d, w1.shape[2])
    for w in range(x.shape[0]):
        for j in range(x.shape[1]):
            if not (mask[w, j] and ready[w]):
                out[w, j, :] = h[w]
                continue
            log_rate_grad(
                kind, state, w, x[w, j], a_max[w], pos, mu, sigma, n_phys, x_mean, x_std,
                w1, b1, y_scale, theta, dq, xn, act, H, fx, pe, scratch, j,
            )  # fmt: skip
            for i in range(d):
                out[w, j, i] = H[i] * keep[i]


def _made_up_sample() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One made-up sample of one well for the warm-ups: inputs [1, 1, 6], its weight and mask."""
    x = np.array([[[0.5, 50.0, 20.0, 60.0, 0.1, 0.5]]])
    return x, np.ones((1, 1)), np.ones((1, 1), dtype=bool)


def _made_up_mtl() -> tuple[np.ndarray, ...]:
    """Made-up ``mtl`` tensors (task dimension 4, width 4) for the warm-ups."""
    return (
        np.zeros((1, 4)), np.ones((10, 4)), np.ones(4), np.ones((4, 4)), np.ones((4, 4)),
        np.ones(4), np.ones(4), np.ones((4, 4)), np.ones((4, 4)), np.ones(4), np.ones(4),
        np.ones((4, 1)), np.ones(1),
    )  # fmt: skip


def no_effects() -> tuple[np.ndarray, ...]:
    """The effects (``fx`` of :func:`_factor_at`) of a model without compiled effects."""
    return (
        np.zeros((0, 6), dtype=np.int64), np.zeros(0), np.zeros(0), np.zeros((1, 1, 0)),
        np.zeros((1, 1), dtype=bool), np.ones((1, 1), np.int64), np.ones(1),
    )  # fmt: skip


def no_effect_state() -> tuple[np.ndarray, ...]:
    """The effects' parameters, moments, rows and bounds (``eff`` of :func:`effect_online`
    and :func:`hybrid_online`) of a model without effects."""
    none = np.zeros((1, 0))
    return none, none.copy(), none.copy(), np.zeros(0, np.int64), np.zeros(0), np.zeros(0)


def warm_effects() -> None:
    """Run the effect kernels once on a made-up sample, every effect code in one model."""
    x, ones, yes = _made_up_sample()
    mu = np.array([840.0, 1017.5, 1.28, 0.0205, 0.55, 0.825])
    one = np.ones(6)
    # erosion with a step, valve (2 knots), a valve family, a meter bias, real gas, slip,
    # a suggested correction, the critical ratio: 11 parameters
    terms = np.array(
        [[FX_EROSION, 0, 2, 0, 1, 0], [FX_VALVE, 2, 2, 0, 2, 0], [FX_FAMILY, 4, 1, 0, 1, 0],
         [FX_BIAS, 5, 2, 0, 0, 0], [FX_GAS, 7, 1, 0, 0, 0], [FX_SLIP, 8, 1, 0, 0, 0],
         [FX_SUGGEST, 9, 1, 0, 0, 0], [FX_CRITICAL, 10, 1, 0, 0, 0]],
        dtype=np.int64,
    )  # fmt: skip
    p = 11
    fx = (terms, np.zeros(p), np.ones(p), np.ones((1, 1, 2)), np.zeros((1, 1), dtype=bool),
          np.ones((1, 1), np.int64), np.ones(1) / 2)  # fmt: skip
    ze = np.zeros((1, p))
    effect_rates(np.zeros((1, 6)), x, np.ones(1), mu, one, ze, fx, np.zeros((1, 1)))
    eff = (ze.copy(), np.zeros((1, p)), np.zeros((1, p)),
           np.array([1, 1, 2, 2, 3, 4, 4, 5, 6, 7, 8]), -np.ones(p), np.ones(p))  # fmt: skip
    effect_online(
        np.zeros((1, 6)), np.zeros((1, 6)), np.zeros((1, 6)), np.zeros((9, 1)),
        np.zeros(1, dtype=bool), x, ones, yes, np.ones(1), np.ones(1), mu, one, (-one, one),
        0.05, (1e-3, 0.9, 0.999, 1e-8), 1.0, 1, True, eff, fx,
    )  # fmt: skip


def warm_up() -> None:
    """Run each kernel once on a made-up sample (compiles it, or loads it from the cache)."""
    one = np.ones((1, 6))
    mu = np.array([840.0, 1017.5, 1.28, 0.0205, 0.55, 0.825])
    x, ones, yes = _made_up_sample()
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
            area_model, np.zeros((1, 1)), np.zeros((1, 0)), no_effects(),
        )  # fmt: skip
    for kind in (1, 2):
        net = [np.ones((1, 6, 4)), np.ones((1, 4)), np.ones((1, 4, 1)), np.ones((1, 1))]
        moments = [np.zeros_like(a) for a in [np.zeros((1, 6)), *net] for _ in range(2)]
        hybrid_online(  # type: ignore[call-arg]
            kind, np.zeros((1, 6)), *net, *moments, np.zeros((5, 1)), np.zeros(1, dtype=bool),  # type: ignore[arg-type]
            x, ones, yes, np.ones(1), np.ones(1), pos, mu, one[0], np.zeros((1, 6)), one,
            -one[0], one[0], 0.05, 1e-3, 0.9, 0.999, 1e-8, 1.0, 1, True, no_effect_state(),
            no_effects(),
        )  # fmt: skip
    count = np.zeros(1, dtype=np.int64)
    for kind, hidden in ((0, 0), (1, 4), (2, 4)):
        d = 6 + (hidden + 1 if kind else 0)
        bayes(
            np.zeros((1, d)), np.zeros((1, d, d)), np.zeros(1, dtype=np.int64), np.ones((1, 2)),
            np.zeros((1, d)), np.zeros((1, 2)), np.zeros(1, dtype=bool), count.copy(),
            count.copy(), count.copy(), count.copy(), count.copy(), np.zeros(1, dtype=bool),
            x, ones, yes, np.ones((1, 1), dtype=np.int64), yes, np.ones(1, dtype=bool),
            kind, np.ones(1), pos, mu, one[0], 6, np.zeros((1, 6)), one,
            np.ones((1, 6, hidden)), np.ones((1, hidden)), np.ones(1),
            (-np.ones(d), np.ones(d), np.ones(d), np.ones(d), np.ones(d), np.zeros(2, dtype=bool),
             3.0, 6.0, 0.02, 0.05, -1, 3, 0.002, 1.645, 3.15e16),
            (np.zeros((1, 2, 3)), np.zeros(1, dtype=np.int64), 36.0, 0.99), no_effects(),
        )  # fmt: skip
    warm_effects()
    out = [np.zeros((1, 1)) for _ in range(3)]
    for kind, hidden in ((0, 0), (1, 4), (2, 4)):
        d = 6 + (hidden + 1 if kind else 0)
        bayes_gradients(
            np.zeros((1, d)), np.zeros((1, d)), np.ones(d), x, yes, np.ones(1, dtype=bool),
            kind, np.ones(1), pos, mu, one[0], 6, np.zeros((1, 6)), one,
            np.ones((1, 6, hidden)), np.ones((1, hidden)), np.ones(1), no_effects(),
            np.zeros((1, 1, d)),
        )  # fmt: skip
    bayes_spread(
        ones, np.zeros((1, 1, 6)), np.zeros((1, 6, 6)), one[0], np.zeros(1, dtype=np.int64),
        np.ones((1, 2)), np.zeros((1, 2)), np.ones(1, dtype=bool),
        np.ones((1, 1), dtype=np.int64), yes, -1, 1.645, 3.15e16, *out,
    )  # fmt: skip


# -- the training loops' kernels: compiled on first use (kernels._lazy), not at start-up ----
def warm_fit_steps() -> None:
    """Run :func:`fit_steps` once per kind on a made-up sample (compiles it, or loads it)."""
    one = np.ones((1, 6))
    mu = np.array([840.0, 1017.5, 1.28, 0.0205, 0.55, 0.825])
    pos = np.arange(6)
    x, ones, yes = _made_up_sample()
    for kind, hidden in ((0, 0), (1, 4), (2, 4)):
        net = [
            np.ones((1, 6, hidden)),
            np.ones((1, hidden)),
            np.ones((1, hidden, 1)),
            np.ones((1, 1)),
        ]
        z6 = np.zeros((1, 6))
        moments = tuple(np.zeros_like(a) for a in [z6, *net] for _ in range(2))
        fit_steps(  # type: ignore[call-arg]
            kind, z6, *net, moments, np.zeros((5, 1)), np.ones(1, dtype=np.int64), x, ones,  # type: ignore[arg-type]
            yes, 1, False, np.ones(1), np.ones(1), np.ones(1), pos, mu, one[0], np.zeros((1, 6)),
            one, -one[0], one[0], 0.05, 1e-3, 0.9, 0.999, 1e-8, 1.0, True, np.zeros(1), True,
            x, ones, yes, np.zeros((1, 1)),
        )  # fmt: skip


def warm_nn_fit_steps() -> None:
    """Run :func:`nn_fit_steps` once on a made-up sample."""
    x, ones, yes = _made_up_sample()
    net: tuple[np.ndarray, ...] = (
        np.ones((1, 6, 4)),
        np.ones((1, 4)),
        np.ones((1, 4, 4)),
        np.ones((1, 4)),
    )
    net += (np.ones((1, 4, 1)), np.ones((1, 1)))
    nn_fit_steps(
        net, tuple(np.zeros_like(a) for a in net for _ in range(2)), np.zeros((6, 1)),
        np.ones(1, dtype=np.int64), x, ones, yes, 1, False, np.ones(1), np.ones(1), 0.05, 1e-3,
        0.9, 0.999, 1e-8, 1.0, True, np.zeros(1), True, x, ones, yes, np.zeros((1, 1)),
    )  # fmt: skip


def warm_lr_fit_steps() -> None:
    """Run :func:`lr_fit_steps` once on a made-up sample."""
    x, ones, yes = _made_up_sample()
    lin = (np.zeros((1, 6)), np.ones(1))
    lr_fit_steps(
        lin, tuple(np.zeros_like(a) for a in lin for _ in range(2)), np.zeros((2, 1)),
        np.ones(1, dtype=np.int64), x, ones, yes, 1, False, np.ones(1), np.ones(1), 0.05, 1e-3,
        0.9, 0.999, 1e-8, 1.0, True, np.zeros(1), True, x, ones, yes, np.zeros((1, 1)),
        np.ones((1, 6)),
    )  # fmt: skip


def warm_mtl_online() -> None:
    """Run :func:`mtl_online` once on a made-up sample."""
    x, ones, yes = _made_up_sample()
    mtl = _made_up_mtl()
    mtl_online(
        mtl, tuple(np.zeros_like(a) for a in mtl for _ in range(2)), np.zeros(1),
        np.zeros(1, dtype=bool), x, ones, yes, np.ones(1), 1, 0.9, 0.999, 1e-8, 1e-3, 1.0,
    )  # fmt: skip


def warm_mtl_fit_steps() -> None:
    """Run :func:`mtl_fit_steps` once on made-up samples, with the held-out error."""
    x, ones, yes = _made_up_sample()
    mtl = _made_up_mtl()
    mtl_fit_steps(
        mtl, tuple(np.zeros_like(a) for a in mtl for _ in range(2)), np.zeros(1), 1, x, ones,
        yes, 1, True, np.ones(1), np.ones(1), 1, 0.05, (1e-3, 0.9, 0.999, 1e-8), 1.0, True,
        np.zeros((1, 1)), True, x, ones, yes, yes[0], np.zeros(1),
    )  # fmt: skip


def warm_effect_fit_steps() -> None:
    """Run :func:`effect_fit_steps` once on a made-up sample, every effect code in one model,
    with the held-out error."""
    x, ones, yes = _made_up_sample()
    mu = np.array([840.0, 1017.5, 1.28, 0.0205, 0.55, 0.825])
    one = np.ones(6)
    terms = np.array(
        [[FX_EROSION, 0, 2, 0, 1, 0], [FX_VALVE, 2, 2, 0, 2, 0], [FX_FAMILY, 4, 1, 0, 1, 0],
         [FX_BIAS, 5, 2, 0, 0, 0], [FX_GAS, 7, 1, 0, 0, 0], [FX_SLIP, 8, 1, 0, 0, 0],
         [FX_SUGGEST, 9, 1, 0, 0, 0], [FX_CRITICAL, 10, 1, 0, 0, 0]],
        dtype=np.int64,
    )  # fmt: skip
    p = 11
    fx = (terms, np.zeros(p), np.ones(p), np.ones((1, 1, 2)), np.zeros((1, 1), dtype=bool),
          np.ones((1, 1), np.int64), np.ones(1) / 2)  # fmt: skip
    eff = (np.zeros((1, p)), np.zeros((1, p)), np.zeros((1, p)),
           np.array([1, 1, 2, 2, 3, 4, 4, 5, 6, 7, 8]), -np.ones(p), np.ones(p))  # fmt: skip
    effect_fit_steps(
        np.zeros((1, 6)), (np.zeros((1, 6)), np.zeros((1, 6))), np.zeros((9, 1)),
        np.ones(1, dtype=np.int64), (x, ones, yes, 1, False), np.ones(1),
        (np.ones(1), np.ones(1), mu, one, -one, one), 0.05, (1e-3, 0.9, 0.999, 1e-8), 1.0, True,
        np.zeros(1), eff, fx, (True, x, ones, yes, fx, np.zeros((1, 1))),
    )  # fmt: skip


def warm_hybrid_effect_fit_steps() -> None:
    """Run :func:`hybrid_effect_fit_steps` once per kind on a made-up sample with one
    effect, with the held-out error."""
    x, ones, yes = _made_up_sample()
    mu = np.array([840.0, 1017.5, 1.28, 0.0205, 0.55, 0.825])
    one = np.ones(6)
    fx = (np.array([[FX_SLIP, 0, 1, 0, 0, 0]], dtype=np.int64), np.zeros(1), np.ones(1),
          np.ones((1, 1, 2)), np.zeros((1, 1), dtype=bool), np.ones((1, 1), np.int64),
          np.ones(1) / 2)  # fmt: skip
    for kind in (1, 2):
        params = (np.zeros((1, 6)), np.ones((1, 6, 4)), np.ones((1, 4)), np.ones((1, 4, 1)),
                  np.ones((1, 1)))  # fmt: skip
        moments = tuple(np.zeros_like(a) for a in params for _ in range(2))
        eff = (np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1)), np.array([5]),
               -np.ones(1), np.ones(1))  # fmt: skip
        model = (np.ones(1), np.ones(1), np.arange(6), mu, one, np.zeros((1, 6)), np.ones((1, 6)),
                 -one, one)  # fmt: skip
        hybrid_effect_fit_steps(
            kind, params, moments, np.zeros((6, 1)), np.ones(1, dtype=np.int64),
            (x, ones, yes, 1, False), np.ones(1), model, 0.05, (1e-3, 0.9, 0.999, 1e-8), 1.0,
            True, np.zeros(1), eff, fx, (True, x, ones, yes, fx, np.zeros((1, 1))),
        )  # fmt: skip
