"""What a learning method retrains on: the measurements seen so far, as batches.

A :class:`Memory` answers one question, ``batch(until_ns, window_ns)``: every measured row
before ``until_ns`` (and, with a window, not older than ``until_ns - window_ns``) as a
:class:`vfm_core.data.Batch` for the model's wells. The prequential study reads them from
the observation frame (:class:`FrameMemory`); the streaming learner keeps one well's rows
as they arrive (:class:`WellMemory`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
import pandas as pd
import torch

from vfm_core.data import DTYPE, Batch, make_batch
from vfm_core.schema import TIME, WELL

__all__ = ["Memory", "FrameMemory", "WellMemory", "N_INPUTS"]

N_INPUTS = 6


class Memory(Protocol):
    """The rows a retrain may use (see the module docstring)."""

    def batch(self, until_ns: int, window_ns: int | None = None) -> Batch: ...


class FrameMemory:
    """The measured rows of an observation frame (the study): ``is_target`` rows of ``wells``."""

    def __init__(
        self,
        frame: pd.DataFrame,
        is_target: np.ndarray,
        wells: Sequence[str],
        extra_columns: Sequence[str] = (),
    ) -> None:
        self.frame = frame
        self.wells = list(wells)
        self.extra_columns = tuple(extra_columns)
        self._time_ns = pd.DatetimeIndex(frame[TIME]).as_unit("ns").asi8
        known = frame[WELL].astype(str).isin(self.wells).to_numpy()
        self._rows = np.asarray(is_target, dtype=bool) & known

    def batch(self, until_ns: int, window_ns: int | None = None) -> Batch:
        keep = self._rows & (self._time_ns < until_ns)
        if window_ns is not None:
            keep &= self._time_ns >= until_ns - window_ns
        return make_batch(
            self.frame, self.wells, rows=np.flatnonzero(keep), extra_columns=self.extra_columns
        )


class WellMemory:
    """One well's measured rows, appended as they arrive (the streaming learner).

    Each row: the six inputs, the measured rate (Sm3/h), its time (epoch ns), whether it is
    a well test, and the standard features at that row (``feature_names``). Rows learned
    one at a time wait in a tail and are joined when read, so appending never copies the
    whole history. ``extra_columns`` are the features the model reads (a subset).
    """

    def __init__(
        self,
        well: str,
        feature_names: Sequence[str],
        extra_columns: Sequence[str] = (),
        max_rows: int | None = None,
    ) -> None:
        self.well = well
        #: keep at most the latest ``max_rows`` rows (None: all); see :meth:`set_max_rows`
        self.max_rows = max_rows
        self._n_tail = 0
        self.feature_names = tuple(feature_names)
        self.extra_columns = tuple(extra_columns)
        self._cols = [self.feature_names.index(c) for c in self.extra_columns]
        k = len(self.feature_names)
        self._parts: list[torch.Tensor] = [
            torch.empty(0, N_INPUTS, dtype=DTYPE),
            torch.empty(0, dtype=DTYPE),
            torch.empty(0, dtype=torch.int64),
            torch.empty(0, dtype=torch.bool),
            torch.empty(0, k, dtype=DTYPE),
        ]
        self._tail: list[tuple[torch.Tensor, ...]] = []

    def _joined(self) -> list[torch.Tensor]:
        if self._tail:
            columns = list(zip(*self._tail, strict=True))
            self._parts = [torch.cat([p, *c]) for p, c in zip(self._parts, columns, strict=True)]
            self._tail, self._n_tail = [], 0
        return self._parts

    def set_max_rows(self, max_rows: int | None) -> None:
        """Keep at most the latest ``max_rows`` rows from now on (None: every row).

        A long-running service remembers every measurement for retrains and model changes,
        and each checkpoint stores them: without a bound both grow for ever. Appending lets
        the rows overshoot the bound by a tenth before it cuts back to ``max_rows`` (one
        copy per tenth, not one per row); reading and restoring cut at once."""
        self.max_rows = max_rows
        self._trim(0)

    def _trim(self, slack: int) -> None:
        m = self.max_rows
        if m is not None and len(self) > m + slack:
            self._parts = [p[-m:].clone() for p in self._joined()]

    @property
    def x(self) -> torch.Tensor:
        """Inputs [N, 6] in file units."""
        return self._joined()[0]

    @property
    def y(self) -> torch.Tensor:
        """Measured rates [N], Sm3/h."""
        return self._joined()[1]

    @property
    def t(self) -> torch.Tensor:
        """Times [N], epoch ns."""
        return self._joined()[2]

    @property
    def well_test(self) -> torch.Tensor:
        """[N] True for well tests (else MPFM readings)."""
        return self._joined()[3]

    @property
    def features(self) -> torch.Tensor:
        """Standard features [N, k] in ``feature_names`` order."""
        return self._joined()[4]

    def __len__(self) -> int:
        return int(self._parts[1].shape[0]) + self._n_tail

    def append(
        self,
        x: torch.Tensor,
        y: torch.Tensor,
        t: torch.Tensor,
        well_test: torch.Tensor | None = None,
        features: torch.Tensor | None = None,
    ) -> None:
        """Add rows: inputs [n, 6], rates [n], times [n] (epoch ns), flags [n], features [n, k]."""
        x = x.reshape(-1, N_INPUTS).to(DTYPE)
        n = int(x.shape[0])
        k = len(self.feature_names)
        w = torch.zeros(n, dtype=torch.bool) if well_test is None else well_test.reshape(n).bool()
        e = torch.zeros(n, k, dtype=DTYPE) if features is None else features.reshape(n, k)
        self._tail.append((x, y.reshape(n).to(DTYPE), t.reshape(n), w, e.to(DTYPE)))
        self._n_tail += n
        if self.max_rows is not None:
            self._trim(max(1, self.max_rows // 10))

    def replace(self, rows: torch.Tensor) -> None:
        """Keep only ``rows`` (indices or a mask), e.g. to copy another memory's selection."""
        self._parts = [p[rows] for p in self._joined()]

    def copy_from(self, other: WellMemory, rows: torch.Tensor | None = None) -> None:
        """Take ``other``'s rows (all, or the given indices), sorted by time."""
        parts = other._joined()
        if rows is None:
            rows = torch.arange(int(parts[1].shape[0]))
        rows = rows[torch.argsort(parts[2][rows], stable=True)]
        self._parts = [p[rows].clone() for p in parts]
        self._tail, self._n_tail = [], 0
        self._trim(0)

    def rows(self, keep: torch.Tensor | None = None) -> Batch:
        """The rows (all, or where ``keep``) as a one-well batch with the model's features."""
        x, y, t, w, e = self._joined()
        if keep is not None:
            x, y, t, w, e = x[keep], y[keep], t[keep], w[keep], e[keep]
        n = int(x.shape[0])
        return Batch(
            [self.well],
            x.reshape(1, n, N_INPUTS),
            y.reshape(1, n),
            torch.ones(1, n, dtype=torch.bool),
            t.reshape(1, n),
            torch.arange(n).reshape(1, n),
            w.reshape(1, n),
            e[:, self._cols].reshape(1, n, len(self._cols)),
            self.extra_columns,
        )

    def batch(self, until_ns: int, window_ns: int | None = None) -> Batch:
        t = self.t
        keep = t < until_ns
        if window_ns is not None:
            keep &= t >= until_ns - window_ns
        return self.rows(keep)

    def state(self) -> dict[str, torch.Tensor]:
        """The rows as tensors (for checkpoints)."""
        x, y, t, w, e = self._joined()
        return {"x": x, "y": y, "t": t, "w": w, "e": e}

    def load(self, state: dict[str, torch.Tensor]) -> None:
        self._parts = [state["x"], state["y"], state["t"], state["w"], state["e"]]
        self._tail, self._n_tail = [], 0
        self._trim(0)
