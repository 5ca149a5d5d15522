"""Observation frames as padded, per-well tensors: the shape every model and learner works on.

All wells of a field are processed together: well j's samples sit in row j of a
``[wells, samples, ...]`` tensor, padded at the end and masked. Models keep one set of
parameters per well (or shared ones, for ``mtl``), so one vectorised step updates every
well at once; that is what makes the whole study fast on two cores.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from vfm_core.errors import ConfigError, DataError
from vfm_core.physics import DTYPE
from vfm_core.schema import INPUT_COLUMNS, MPFM, SOURCE, TARGET, TIME, WELL, WELL_TEST

__all__ = ["TARGET_CASES", "Batch", "target_mask", "make_batch", "DTYPE"]


#: Which measurements count as targets: the paper's case 1 (MPFM and well tests) and
#: case 2 (well tests only), with their default split dates.
TARGET_CASES: dict[str, tuple[tuple[str, ...], str]] = {
    "all": ((MPFM, WELL_TEST), "2019-01-01"),
    "well_test": ((WELL_TEST,), "2020-01-01"),
}


def target_mask(frame: pd.DataFrame, targets: str) -> np.ndarray:
    """Rows of ``frame`` that hold a measured rate of the case ``targets``."""
    try:
        sources = TARGET_CASES[targets][0]
    except KeyError:
        raise ConfigError(
            f"Unknown target case '{targets}'; choose one of {sorted(TARGET_CASES)}."
        ) from None
    return (frame[SOURCE].isin(sources) & frame[TARGET].notna()).to_numpy()


@dataclass
class Batch:
    """Padded per-well samples.

    ``x``: inputs [W, N, 6] in file units (fraction, bar, bar, degC, -, -);
    ``y``: measured total rate [W, N] in Sm3/h (0 where padded);
    ``mask``: [W, N] True where a real sample sits;
    ``time_ns``: [W, N] int64 epoch nanoseconds (padded with int64 max);
    ``row``: [W, N] int64 index of the sample in the source frame (-1 where padded);
    ``well_test``: [W, N] True where the measurement is a well test (else MPFM or none);
    ``extra``: [W, N, k] further per-sample features named by ``extra_names`` (e.g. the
    ones a diagnosis effect needs, such as cumulative throughput), empty by default.
    """

    wells: list[str]
    x: torch.Tensor
    y: torch.Tensor
    mask: torch.Tensor
    time_ns: torch.Tensor
    row: torch.Tensor
    well_test: torch.Tensor | None = None
    extra: torch.Tensor | None = None
    extra_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.well_test is None:
            self.well_test = torch.zeros_like(self.mask)
        if self.extra is None:
            self.extra = torch.zeros(*self.mask.shape, 0, dtype=DTYPE)

    def column(self, k: int) -> Batch:
        """The k-th sample of every well, as a batch of one sample per well."""
        sl = slice(k, k + 1)
        assert self.well_test is not None and self.extra is not None
        return Batch(
            self.wells,
            self.x[:, sl],
            self.y[:, sl],
            self.mask[:, sl],
            self.time_ns[:, sl],
            self.row[:, sl],
            self.well_test[:, sl],
            self.extra[:, sl],
            self.extra_names,
        )

    @property
    def n_wells(self) -> int:
        return len(self.wells)

    def count(self) -> torch.Tensor:
        """Samples per well, [W]."""
        return self.mask.sum(dim=1)

    def select(self, keep: torch.Tensor) -> Batch:
        """A new batch with only the samples where ``keep`` [W, N] is True, left-aligned."""
        keep = keep & self.mask
        counts = keep.sum(dim=1)
        n = int(counts.max()) if counts.numel() else 0
        order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)[:, :n]
        new_mask = torch.gather(keep, 1, order)
        assert self.well_test is not None and self.extra is not None
        x = torch.gather(self.x, 1, order.unsqueeze(-1).expand(-1, -1, self.x.shape[-1]))
        y = torch.gather(self.y, 1, order)
        t = torch.gather(self.time_ns, 1, order)
        r = torch.gather(self.row, 1, order)
        wt = torch.gather(self.well_test, 1, order)
        ex = torch.gather(self.extra, 1, order.unsqueeze(-1).expand(-1, -1, self.extra.shape[-1]))
        return Batch(
            self.wells,
            torch.where(new_mask.unsqueeze(-1), x, self.x[:, :1].expand_as(x)),
            torch.where(new_mask, y, torch.zeros_like(y)),
            new_mask,
            torch.where(new_mask, t, torch.full_like(t, torch.iinfo(torch.int64).max)),
            torch.where(new_mask, r, torch.full_like(r, -1)),
            wt & new_mask,
            torch.where(new_mask.unsqueeze(-1), ex, self.extra[:, :1].expand_as(ex)),
            self.extra_names,
        )


def make_batch(
    frame: pd.DataFrame,
    wells: Sequence[str],
    rows: np.ndarray | None = None,
    extra_columns: Sequence[str] = (),
) -> Batch:
    """Pack rows of an observation frame into a padded per-well :class:`Batch`.

    ``rows`` (positional indices into ``frame``) selects which rows to pack; default all.
    Within a well the samples keep the frame's order (the loader sorts by time). Padding
    repeats the well's first sample so that padded entries stay finite through the physics.
    """
    sub = frame if rows is None else frame.iloc[rows]
    positions = np.arange(len(frame)) if rows is None else np.asarray(rows)
    well_index = {w: i for i, w in enumerate(wells)}
    codes = sub[WELL].map(well_index)
    if codes.isna().any():
        unknown = sorted(set(sub[WELL][codes.isna()]))
        raise DataError(f"Wells {unknown} are not part of this model's field {list(wells)}.")
    codes_np = codes.to_numpy(dtype=np.int64)
    n_w = len(wells)
    counts = np.bincount(codes_np, minlength=n_w)
    n = int(counts.max()) if len(codes_np) else 0
    # rank of each row within its well, preserving order
    order = np.argsort(codes_np, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ranks = np.empty_like(codes_np)
    ranks[order] = np.arange(len(codes_np)) - np.repeat(starts, counts)

    missing = [c for c in extra_columns if c not in sub.columns]
    if missing:
        raise DataError(f"The frame lacks the feature column(s) {missing} that this model needs.")
    xs = sub[list(INPUT_COLUMNS)].to_numpy(dtype=np.float64)
    exs = sub[list(extra_columns)].to_numpy(dtype=np.float64).reshape(len(sub), len(extra_columns))
    wts = (sub[SOURCE] == WELL_TEST).to_numpy()
    ys = sub[TARGET].to_numpy(dtype=np.float64)
    ts = pd.DatetimeIndex(sub[TIME]).as_unit("ns").asi8

    x = np.zeros((n_w, n, len(INPUT_COLUMNS)))
    y = np.zeros((n_w, n))
    mask = np.zeros((n_w, n), dtype=bool)
    t = np.full((n_w, n), np.iinfo(np.int64).max, dtype=np.int64)
    r = np.full((n_w, n), -1, dtype=np.int64)
    ex = np.zeros((n_w, n, len(extra_columns)))
    wt = np.zeros((n_w, n), dtype=bool)
    ex[codes_np, ranks] = exs
    wt[codes_np, ranks] = wts
    x[codes_np, ranks] = xs
    y[codes_np, ranks] = np.nan_to_num(ys, nan=0.0)
    mask[codes_np, ranks] = True
    t[codes_np, ranks] = ts
    r[codes_np, ranks] = positions
    # pad with each well's first real sample (or a harmless default for empty wells)
    default = np.array([0.5, 100.0, 30.0, 60.0, 0.1, 0.6])
    first = np.where(counts[:, None] > 0, x[:, 0, :], default)
    x = np.where(mask[..., None], x, first[:, None, :])
    ex = np.where(mask[..., None], ex, ex[:, :1, :])
    return Batch(
        list(wells),
        torch.from_numpy(x).to(DTYPE),
        torch.from_numpy(y).to(DTYPE),
        torch.from_numpy(mask),
        torch.from_numpy(t),
        torch.from_numpy(r),
        torch.from_numpy(wt),
        torch.from_numpy(ex).to(DTYPE),
        tuple(extra_columns),
    )
