"""``vfm drift DATA --out DIR``: the retraining period per well (Algorithm A.1 of
:mod:`vfm_core.hotelling`), and the T^2 statistic over time.

For each well, the reference window is the first part of its data before the split
(``--reference``, a fraction); every later observation is tested against it with the
single-observation Hotelling test. The first confirmed shift in the training data gives
the estimated retraining period (paper appendix A); the statistic over the whole history
is plotted with detections coloured, as in the paper's Hotelling T^2 figures.
Outputs: ``DIR/drift.json`` (periods per well) and ``DIR/report.html``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from vfm_core.data import target_mask
from vfm_core.fileio import staging_dir
from vfm_core.hotelling import estimate_update_period
from vfm_core.jobs.study import resolve_split
from vfm_core.schema import INPUT_COLUMNS, TIME, WELL

__all__ = ["drift_study", "register"]


def drift_study(
    frame: pd.DataFrame,
    *,
    targets: str = "all",
    split: str | None = None,
    reference: float = 0.5,
    alpha: float = 0.05,
    confirm: int = 3,
) -> dict[str, Any]:
    """Per well: the estimated period from the training data and the statistics over time."""
    split_ts = resolve_split(targets, split)
    rows = frame[target_mask(frame, targets)]
    wells: dict[str, Any] = {}
    for well, g in rows.groupby(WELL, sort=False):
        g = g.sort_values(TIME)
        train = g[g[TIME] < split_ts]
        n_ref = int(round(reference * len(train)))
        entry: dict[str, Any] = {"n_train": len(train), "reference": n_ref}
        if n_ref < len(INPUT_COLUMNS) + 3:
            entry["error"] = "too few observations before the split for a reference window"
            wells[str(well)] = entry
            continue
        x = g[list(INPUT_COLUMNS)].to_numpy(dtype=float)
        times = (
            g[TIME].to_numpy().astype("datetime64[ns]")
            if g[TIME].dt.tz is None
            else g[TIME].dt.tz_convert("UTC").dt.tz_localize(None).to_numpy()
        )
        res = estimate_update_period(x, times, reference=n_ref, alpha=alpha, confirm=confirm)
        in_train = res.index is not None and res.index < len(train)
        entry.update(
            {
                "reference_end": str(pd.Timestamp(times[n_ref - 1])),
                "first_shift": str(pd.Timestamp(times[res.index]))
                if res.index is not None
                else None,
                "period_days": float(res.period / np.timedelta64(1, "D"))
                if res.period is not None
                else None,
                "shift_in_training_data": bool(in_train),
                "share_detected_after_split": float(np.mean(res.detected[len(train) :]))
                if len(g) > len(train)
                else None,
                "times": [str(pd.Timestamp(t)) for t in times[n_ref:]],
                "t2": [float(v) for v in res.statistics[n_ref:]],
                "detected": [bool(v) for v in res.detected[n_ref:]],
            }
        )
        d = len(INPUT_COLUMNS)
        entry["t2_critical"] = float(
            stats.f.isf(alpha, d, n_ref - d) * d * (n_ref - 1) / (n_ref - d) * (n_ref + 1) / n_ref
        )
        wells[str(well)] = entry
    periods = [w["period_days"] for w in wells.values() if w.get("period_days") is not None]
    return {
        "targets": targets,
        "split": split_ts.isoformat(),
        "alpha": alpha,
        "confirm": confirm,
        "reference_fraction": reference,
        "median_period_days": float(np.median(periods)) if periods else None,
        "wells": wells,
    }


def write_drift(result: dict[str, Any], out: Path, data_path: str) -> list[Path]:
    """drift.json and report.html in ``out``, both or neither (written in a staging folder)."""
    # Imported here: matplotlib and the templates are only needed for the report.
    from vfm_core.reporting.drift_report import build_report

    with staging_dir(out) as staging:
        (staging / "drift.json").write_text(json.dumps(result, indent=1))
        build_report(result, staging / "report.html", data_path)
    return [out / "drift.json", out / "report.html"]


def _cmd_drift(args: argparse.Namespace) -> int:
    from vfm_core.observations import load_observations

    loaded = load_observations(args.data)
    result = drift_study(
        loaded.frame,
        targets=args.targets,
        split=args.split,
        reference=args.reference,
        alpha=args.alpha,
        confirm=args.confirm,
    )
    written = write_drift(result, Path(args.out), str(args.data))
    for well, e in result["wells"].items():
        period = (
            "no confirmed shift" if e.get("period_days") is None else f"{e['period_days']:.0f} days"
        )
        print(f"  {well:12s} estimated period: {period}")
    print(f"Wrote {', '.join(str(p) for p in written)}.")
    return 0


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("drift", help="Hotelling T^2 drift test: retraining period per well")
    p.add_argument("data", help="observation file")
    p.add_argument("--out", required=True, help="output folder (drift.json, report.html)")
    p.add_argument("--targets", default="all", help="all or well_test (default all)")
    p.add_argument("--split", default=None)
    p.add_argument(
        "--reference", type=float, default=0.5, help="reference window: fraction of pre-split data"
    )
    p.add_argument("--alpha", type=float, default=0.05, help="significance level (default 0.05)")
    p.add_argument(
        "--confirm", type=int, default=3, help="consecutive detections that confirm a shift"
    )
    p.set_defaults(handler=_cmd_drift)
