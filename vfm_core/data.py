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
from vfm_core.schema import INPUT_COLUMNS, MPFM, SOURCE, TARGET, TIME, WELL, WELL_TEST

__all__ = ["TARGET_CASES", "Batch", "target_mask", "make_batch", "DTYPE"]

DTYPE = torch.float64

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
    ``row``: [W, N] int64 index of the sample in the source frame (-1 where padded).
    """

    wells: list[str]
    x: torch.Tensor
    y: torch.Tensor
    mask: torch.Tensor
    time_ns: torch.Tensor
    row: torch.Tensor

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
        x = torch.gather(self.x, 1, order.unsqueeze(-1).expand(-1, -1, self.x.shape[-1]))
        y = torch.gather(self.y, 1, order)
        t = torch.gather(self.time_ns, 1, order)
        r = torch.gather(self.row, 1, order)
        return Batch(
            self.wells,
            torch.where(new_mask.unsqueeze(-1), x, self.x[:, :1].expand_as(x)),
            torch.where(new_mask, y, torch.zeros_like(y)),
            new_mask,
            torch.where(new_mask, t, torch.full_like(t, torch.iinfo(torch.int64).max)),
            torch.where(new_mask, r, torch.full_like(r, -1)),
        )


def make_batch(frame: pd.DataFrame, wells: Sequence[str], rows: np.ndarray | None = None) -> Batch:
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

    xs = sub[list(INPUT_COLUMNS)].to_numpy(dtype=np.float64)
    ys = sub[TARGET].to_numpy(dtype=np.float64)
    ts = pd.DatetimeIndex(sub[TIME]).as_unit("ns").asi8

    x = np.zeros((n_w, n, len(INPUT_COLUMNS)))
    y = np.zeros((n_w, n))
    mask = np.zeros((n_w, n), dtype=bool)
    t = np.full((n_w, n), np.iinfo(np.int64).max, dtype=np.int64)
    r = np.full((n_w, n), -1, dtype=np.int64)
    x[codes_np, ranks] = xs
    y[codes_np, ranks] = np.nan_to_num(ys, nan=0.0)
    mask[codes_np, ranks] = True
    t[codes_np, ranks] = ts
    r[codes_np, ranks] = positions
    # pad with each well's first real sample (or a harmless default for empty wells)
    default = np.array([0.5, 100.0, 30.0, 60.0, 0.1, 0.6])
    first = np.where(counts[:, None] > 0, x[:, 0, :], default)
    x = np.where(mask[..., None], x, first[:, None, :])
    return Batch(
        list(wells),
        torch.from_numpy(x).to(DTYPE),
        torch.from_numpy(y).to(DTYPE),
        torch.from_numpy(mask),
        torch.from_numpy(t),
        torch.from_numpy(r),
    )
