"""Hotelling's T-squared drift test on the model inputs (paper appendix A).

- :func:`hotelling_two_sample`: the two-sample test of equal mean vectors with its exact
  F-distribution p-value, for any dimension d and sample sizes with n1 + n2 - d - 1 > 0.
  The covariance is pooled, ((n1-1) S1 + (n2-1) S2) / (n1+n2-2), which is what makes
  T^2 (n1+n2-d-1) / (d (n1+n2-2)) follow F(d, n1+n2-d-1) exactly under Gaussian inputs;
  it also covers the paper's case of a single new observation (n2 = 1, where S2 does not
  exist). The paper's unpooled (S1/n1 + S2/n2) form agrees for large samples.
- :func:`estimate_update_period`: Algorithm A.1: a reference window of the training data
  against each following observation; the first *confirmed* shift (``confirm``
  consecutive detections, the paper's remedy against false detections) gives the period.
  (The paper's listing writes ``F_k < F_crit`` for a detection; a shift is detected when
  the statistic exceeds the critical value, i.e. p < alpha.)
- :class:`StreamingHotelling`: the same test as a streaming detector for the service and
  for ``pbl:auto``: ``update(x)`` per sample, ``drift_detected``, ``statistic``,
  ``p_value``, ``reset()``.

Inputs that do not move in the reference window (a choke held fully open, a constant
fraction) make the covariance singular. The two-sample function says so and names them;
the streaming detector tests in the subspace that does move and reports the dropped
directions in ``degenerate``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from vfm_core.errors import ConfigError, DataError

__all__ = [
    "HotellingResult",
    "hotelling_two_sample",
    "estimate_update_period",
    "StreamingHotelling",
    "UpdatePeriod",
]

_REL_TOL = 1e-10


@dataclass(frozen=True)
class HotellingResult:
    """T^2, the F statistic with its degrees of freedom, and the p-value of equal means."""

    t2: float
    f: float
    df1: int
    df2: int
    p_value: float

    def detected(self, alpha: float) -> bool:
        return self.p_value < alpha


def _pooled(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    n1, n2 = len(x1), len(x2)
    s = (n1 - 1) * np.cov(x1, rowvar=False, ddof=1).reshape(x1.shape[1], -1)
    if n2 > 1:
        s = s + (n2 - 1) * np.cov(x2, rowvar=False, ddof=1).reshape(x2.shape[1], -1)
    return s / (n1 + n2 - 2)


def _as_2d(x: np.ndarray | Sequence[Sequence[float]], name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise DataError(f"{name} must be a 2-D array of samples x inputs, got shape {a.shape}.")
    if not np.isfinite(a).all():
        raise DataError(f"{name} holds NaN or infinite values; filter them first.")
    return a


def hotelling_two_sample(
    x1: np.ndarray | Sequence[Sequence[float]],
    x2: np.ndarray | Sequence[Sequence[float]],
    *,
    names: Sequence[str] | None = None,
) -> HotellingResult:
    """Two-sample Hotelling T^2 test that samples x1 [n1, d] and x2 [n2, d] share a mean.

    Raises :class:`DataError` when the sizes leave no degrees of freedom or when the
    pooled covariance is singular (naming the inputs that do not vary).
    """
    a, b = _as_2d(x1, "x1"), _as_2d(x2, "x2")
    if a.shape[1] != b.shape[1]:
        raise DataError(f"x1 has {a.shape[1]} inputs but x2 has {b.shape[1]}; they must match.")
    n1, n2, d = len(a), len(b), a.shape[1]
    df2 = n1 + n2 - d - 1
    if n1 < 2 or n2 < 1 or df2 < 1:
        raise DataError(
            f"Hotelling's test needs n1 + n2 - d - 1 >= 1 with n1 >= 2 (got n1={n1}, n2={n2}, d={d}); "
            "use a longer reference window or fewer inputs."
        )
    s = _pooled(a, b)
    w, v = np.linalg.eigh(s)
    if w.max() <= 0 or w.min() <= _REL_TOL * w.max():
        labels = list(names) if names is not None else [f"input {i}" for i in range(d)]
        flat = [labels[i] for i in range(d) if s[i, i] <= _REL_TOL * max(np.trace(s), 1e-300)]
        what = (
            f"inputs {flat} do not vary" if flat else "some inputs are exact combinations of others"
        )
        raise DataError(
            f"The pooled covariance is singular: {what} in these samples. Drop those inputs, "
            "or use StreamingHotelling, which tests in the subspace that varies."
        )
    diff = a.mean(0) - b.mean(0)
    proj = v.T @ diff
    t2 = float(n1 * n2 / (n1 + n2) * np.sum(proj**2 / w))
    f = t2 * df2 / (d * (n1 + n2 - 2))
    return HotellingResult(t2, f, d, df2, float(stats.f.sf(f, d, df2)))


@dataclass(frozen=True)
class UpdatePeriod:
    """Result of Algorithm A.1 for one well.

    ``index`` is the position (in the given samples) of the first confirmed shift, or
    None; ``period`` is the time from the end of the reference window to it.
    """

    index: int | None
    period: np.timedelta64 | None
    statistics: np.ndarray
    p_values: np.ndarray
    detected: np.ndarray
    reference_end: int


def estimate_update_period(
    x: np.ndarray,
    times: np.ndarray | None = None,
    *,
    reference: int | float = 0.5,
    alpha: float = 0.05,
    confirm: int = 3,
) -> UpdatePeriod:
    """Algorithm A.1: reference window vs each following observation.

    ``reference``: the number of leading samples in the reference window, or a fraction of
    all samples. A shift counts once ``confirm`` consecutive observations are detected.
    All statistics are returned, for the paper's T^2-over-time figure.
    """
    data = _as_2d(x, "x")
    n = len(data)
    t1 = int(round(reference * n)) if isinstance(reference, float) else int(reference)
    if not 2 <= t1 < n:
        raise ConfigError(f"The reference window must hold 2..{n - 1} samples; got {t1}.")
    det = StreamingHotelling(reference_size=t1, alpha=alpha, confirm=confirm)
    stats_, pvals, flags = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, dtype=bool)
    first: int | None = None
    for i, row in enumerate(data):
        det.update(row)
        if i >= t1:
            stats_[i], pvals[i], flags[i] = det.statistic, det.p_value, det.last_detected
            if det.drift_detected and first is None:
                first = i
    period = None
    if first is not None and times is not None:
        t = np.asarray(times).astype("datetime64[ns]")
        period = t[first] - t[t1 - 1]
    return UpdatePeriod(first, period, stats_, pvals, flags, t1)


class StreamingHotelling:
    """Streaming drift detector on input vectors (river-style: ``update`` + ``drift_detected``).

    The first ``reference_size`` samples after construction or :meth:`reset` form the
    reference window. Each later sample is tested against it (single-observation
    Hotelling test, F(d, n1 - d)); ``last_detected`` says whether this sample was a
    detection at level ``alpha``; ``drift_detected`` turns True once ``confirm``
    consecutive samples were detections, and stays True until :meth:`reset`.

    With i.i.d. inputs the chance that a given sample is a detection is alpha, and that a
    run of ``confirm`` begins at a given sample is about alpha^confirm.
    """

    def __init__(self, reference_size: int = 200, alpha: float = 0.05, confirm: int = 3) -> None:
        if reference_size < 3:
            raise ConfigError(f"reference_size must be at least 3, got {reference_size}.")
        if not 0.0 < alpha < 1.0:
            raise ConfigError(f"alpha must lie in (0, 1), got {alpha}.")
        if confirm < 1:
            raise ConfigError(f"confirm must be at least 1, got {confirm}.")
        self.reference_size = reference_size
        self.alpha = alpha
        self.confirm = confirm
        self.reset()

    def reset(self, reference: np.ndarray | None = None) -> None:
        """Start over; optionally with a ready reference window [n, d] (e.g. the latest samples)."""
        self._ref: deque[np.ndarray] = deque(maxlen=self.reference_size)
        self._fitted = False
        self.statistic = float("nan")
        self.p_value = float("nan")
        self.last_detected = False
        self.drift_detected = False
        self.run = 0
        self.n_seen = 0
        self.degenerate = 0
        if reference is not None:
            for row in np.asarray(reference, dtype=float)[-self.reference_size :]:
                self._ref.append(row)
            if len(self._ref) == self.reference_size:
                self._fit()

    def _fit(self) -> None:
        ref = np.asarray(self._ref)
        self._mean = ref.mean(0)
        cov = np.atleast_2d(np.cov(ref, rowvar=False, ddof=1))
        w, v = np.linalg.eigh(cov)
        keep = w > _REL_TOL * max(w.max(), 1e-300)
        self.degenerate = int((~keep).sum())
        self._w, self._v = w[keep], v[:, keep]
        self._d = int(keep.sum())
        self._fitted = True

    def update(self, x: Sequence[float] | np.ndarray) -> bool:
        """Feed one sample; returns ``drift_detected``."""
        row = np.asarray(x, dtype=float).ravel()
        self.n_seen += 1
        if not self._fitted:
            self._ref.append(row)
            if len(self._ref) == self.reference_size:
                self._fit()
            return self.drift_detected
        n1, d = self.reference_size, self._d
        if d == 0 or n1 - d < 1:
            self.last_detected = False
            return self.drift_detected
        proj = self._v.T @ (row - self._mean)
        t2 = n1 / (n1 + 1) * float(np.sum(proj**2 / self._w))
        f = t2 * (n1 - d) / (d * (n1 - 1))
        self.statistic = t2
        self.p_value = float(stats.f.sf(f, d, n1 - d))
        self.last_detected = self.p_value < self.alpha
        self.run = self.run + 1 if self.last_detected else 0
        if self.run >= self.confirm:
            self.drift_detected = True
        return self.drift_detected

    def state_dict(self) -> dict[str, object]:
        """Plain values and lists (JSON-safe) to resume the detector."""
        return {
            "reference_size": self.reference_size,
            "alpha": self.alpha,
            "confirm": self.confirm,
            "reference": [list(map(float, r)) for r in self._ref],
            "drift_detected": self.drift_detected,
            "run": self.run,
            "n_seen": self.n_seen,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.__init__(int(state["reference_size"]), float(state["alpha"]), int(state["confirm"]))  # type: ignore[misc]
        ref = state.get("reference") or []
        self.reset(np.asarray(ref) if len(ref) else None)
        self.drift_detected = bool(state["drift_detected"])
        self.run = int(state["run"])
        self.n_seen = int(state["n_seen"])
