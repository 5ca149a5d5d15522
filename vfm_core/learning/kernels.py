"""Compiled online steps of the plain Sachdeva model (``mm`` without effects), with numba.

An ``ol`` update of ``mm`` is E optimiser steps, each the closed-form gradient of the MAP
objective (:class:`vfm_core.learning.training.MapObjective` with
:meth:`vfm_core.models.Mechanistic.rate_vjp`), the per-well gradient clip, one Adam (or
SGD) step and the projection into the priors' bounds. In torch that is some 245 tensor
operations per step on tensors of a few numbers, each a microsecond or two of dispatch:
4 ms for one well's update, while the arithmetic is a few hundred floating-point
operations. :func:`mm_online_steps` runs the same arithmetic, in the same order, as one
compiled loop over wells, steps and samples (numba, compiled once and cached on disk).

It is the same algorithm, not a new one: ``tests/test_kernels.py`` checks it against the
torch path (parameters, Adam moments and step counts to 1e-10 relative after many
updates, and the gradient of one step against autograd). Anything else (effects, the
hybrids, another optimiser or a schedule) runs the torch path.

``VFM_KERNELS=0`` in the environment turns the kernel off (the torch path then runs), for a
comparison side by side or where numba cannot compile.
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from vfm_core import physics as ph
from vfm_core.units import KELVIN_OFFSET, PA_PER_BAR

logger = logging.getLogger(__name__)

__all__ = ["kernels_enabled", "mm_online_steps", "mm_online_applies", "warm"]

_SECONDS_PER_HOUR = 3600.0
#: the order of the parameters in ``PhysicalParameters.z`` of ``mm`` (PHYSICAL_NAMES)
_NAMES = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr", "c_d")

_KERNEL: Callable[..., None] | None = None
_FAILED: str | None = None
_LOCK = threading.Lock()  # one compilation, whichever thread asks first


def kernels_enabled() -> bool:
    """False when ``VFM_KERNELS=0`` or numba is missing or could not compile the kernel."""
    return os.environ.get("VFM_KERNELS", "1") != "0" and _kernel() is not None


def _kernel() -> Callable[..., None] | None:
    global _KERNEL, _FAILED
    if _KERNEL is None and _FAILED is None:
        with _LOCK:
            if _KERNEL is None and _FAILED is None:
                try:
                    _KERNEL = _build()
                except Exception as exc:  # pragma: no cover - numba missing or broken here
                    _FAILED = f"{type(exc).__name__}: {exc}"
                    logger.warning(
                        "The compiled mm online step is off (%s); the torch path runs instead.",
                        _FAILED,
                    )
    return _KERNEL


def warm() -> bool:
    """Compile (or load from numba's cache) the kernel now, so that a service's first
    measurement does not wait for it (about 1.5 s the first time on this machine, 0.4 s from
    the cache). Returns whether the kernel is enabled."""
    return kernels_enabled()


def mm_online_applies(model: Any) -> bool:
    """True when :func:`mm_online_steps` computes ``model``'s online steps: exactly the
    plain ``mm`` (no effects, no subclass), in float64, and the kernel is enabled."""
    from vfm_core.models.physical import PHYSICAL_NAMES, Mechanistic

    return (
        type(model) is Mechanistic
        and not model.effects
        and tuple(model.phys.names) == PHYSICAL_NAMES == _NAMES
        and model.phys.z.dtype == torch.float64
        and kernels_enabled()
    )


def mm_online_steps(
    model: Any,
    batch: Any,
    moments: tuple[torch.Tensor, torch.Tensor] | None,
    counts: np.ndarray,
    hold: np.ndarray,
    *,
    steps: int,
    noise: float,
    lr: float,
    betas: tuple[float, float],
    eps: float,
    max_norm: float,
) -> None:
    """E steps of ``ol`` on ``model`` (``mm``, see :func:`mm_online_applies`) and ``batch``,
    in place: ``model.phys.z`` [W, 6]; with Adam (``moments`` its exp_avg and exp_avg_sq
    [W, 6]) the moments, and ``counts`` [W] (each well's step count before, as floats) is
    advanced by ``steps``; ``moments`` None is SGD. A well in ``hold`` [W] keeps its
    parameters (its moments still move, as torch's optimiser moves them), as
    ``OnlineLearning`` holds wells without a new measurement."""
    kernel = _kernel()
    assert kernel is not None
    z_t = model.phys.z
    with torch.no_grad():
        z = z_t.detach().numpy().copy()
        if moments is None:
            m = np.zeros_like(z)
            v = np.zeros_like(z)
        else:
            m = moments[0].numpy().copy()
            v = moments[1].numpy().copy()
        kernel(
            z,
            m,
            v,
            counts,
            hold,
            np.ascontiguousarray(batch.x.numpy()),
            np.ascontiguousarray(batch.y.numpy()),
            np.ascontiguousarray(batch.mask.numpy()),
            model.a_max.numpy(),
            model.y_scale.numpy(),
            model.phys.mu.numpy(),
            model.phys.sigma.numpy(),
            model.phys.z_low.numpy(),
            model.phys.z_high.numpy(),
            float(noise),
            float(lr),
            float(betas[0]),
            float(betas[1]),
            float(eps),
            float(max_norm),
            int(steps),
            moments is not None,
        )
        # written back through torch, so that the tensors' versions move as an in-place
        # torch update moves them
        z_t.copy_(torch.from_numpy(z))
        if moments is not None:
            moments[0].copy_(torch.from_numpy(m))
            moments[1].copy_(torch.from_numpy(v))


def _build() -> Callable[..., None]:
    import numba

    r_gas, p_sc, t_sc = ph.R_GAS, ph.P_SC, ph.T_SC
    pa_per_bar, kelvin = PA_PER_BAR, KELVIN_OFFSET
    per_hour = _SECONDS_PER_HOUR

    @numba.njit(cache=True, nogil=True)
    def kernel(  # noqa: PLR0913 - the arrays of one update
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
                rho_sc = p_sc * m_gas / (r_gas * t_sc)
                for j in range(n_samples):
                    if not mask[w, j]:
                        continue  # torch: a zero gradient there
                    u = x[w, j, 0]
                    p1 = x[w, j, 1] * pa_per_bar
                    p2 = x[w, j, 2] * pa_per_bar
                    t1 = x[w, j, 3] + kelvin
                    xg = x[w, j, 4]
                    eo = x[w, j, 5]
                    # physics._flux, z = 1, no slip
                    ratio = p2 / p1
                    pr = max(ratio, p_cr_used)
                    rho_g1 = p1 * m_gas / (r_gas * t1)
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
                    unit_area = a_max[w] * u
                    area = c_d * unit_area
                    q = area * flux * per_kg * per_hour
                    e = (q - y[w, j]) / scale[w]
                    g = e * d_factor
                    # models.physical._sachdeva_vjp's pullback with physics.flux_vjp
                    g_flux = g * area * per_kg * per_hour
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
                    d_rho_g1 = (
                        g_e * (-xg * k / (k - 1.0) * expansion / rho_g1**2) - g_m * gas / rho_g1
                    )
                    d_pr = g_e * (-v_liq - xg * pra / pr / rho_g1) - g_m * gas / (k * pr)
                    d_k = (
                        g_e
                        * (
                            -xg
                            * (expansion / (k - 1.0) ** 2 + pra * log_pr / (k * (k - 1.0)))
                            / rho_g1
                        )
                        + g_m * gas * log_pr / k**2
                    )
                    if p_cr_used > ratio:
                        at_cr = 1.0
                    elif p_cr_used == ratio:
                        at_cr = 0.5
                    else:
                        at_cr = 0.0
                    g_kg = g * area * flux * per_hour
                    grad[0] += d_v * (-eo / rho_oil**2) - g_kg * eo / rho_oil**2
                    grad[1] += d_v * (-eta_wat / rho_wat**2) - g_kg * eta_wat / rho_wat**2
                    grad[2] += d_k
                    grad[3] += d_rho_g1 * rho_g1 / m_gas - g_kg * gas_sc / m_gas
                    grad[4] += d_pr * at_cr * inside
                    grad[5] += g * (flux * per_kg * per_hour) * unit_area
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

    # compiled here, on one made-up sample: a machine where numba cannot compile it falls
    # back to the torch path (kernels_enabled() is then False), not fails at a measurement
    one = np.ones((1, 6))
    x = np.array([[[0.5, 50.0, 20.0, 60.0, 0.1, 0.5]]])
    kernel(
        np.zeros((1, 6)), np.zeros((1, 6)), np.zeros((1, 6)), np.zeros(1), np.zeros(1, dtype=bool),
        x, np.ones((1, 1)), np.ones((1, 1), dtype=bool), np.ones(1), np.ones(1),
        np.array([840.0, 1017.5, 1.28, 0.0205, 0.55, 0.825]), one[0], -one[0], one[0],
        0.05, 1e-3, 0.9, 0.999, 1e-8, 1.0, 1, True,
    )  # fmt: skip
    return kernel  # type: ignore[no-any-return]
