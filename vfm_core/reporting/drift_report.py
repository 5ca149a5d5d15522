"""The drift report: one self-contained HTML page of ``vfm drift`` (Hotelling T^2 per well).

Owns how the result of :func:`vfm_core.jobs.drift_period.drift_study` is shown: the settings, the
median estimated retraining period, a table per well and the T^2 statistic over time with
the detections coloured (as in the paper's appendix A figures). The page is
``templates/drift.html.j2`` on the shared layout of :mod:`vfm_core.reporting.page`, which
escapes every text taken from the data (well names, the data path).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from vfm_core.reporting import page
from vfm_core.reporting.page import Png

__all__ = ["build_report"]


def _naive_utc(value: Any) -> pd.Timestamp:
    stamp = pd.Timestamp(value)
    return stamp.tz_convert("UTC").tz_localize(None) if stamp.tzinfo else stamp


def _figure(result: dict[str, Any]) -> Png | None:
    """T^2 of every observation after the reference window, per well (log scale)."""
    wells = [(w, e) for w, e in result["wells"].items() if e.get("t2")]
    if not wells:
        return None
    cols = min(2, len(wells))
    rows = (len(wells) + cols - 1) // cols
    fig = Figure(figsize=(6 * cols, 2.6 * rows))
    axes = fig.subplots(rows, cols, squeeze=False, sharey=False)
    split = _naive_utc(result["split"])
    for ax, (well, e) in zip(axes.ravel(), wells, strict=False):
        t = pd.to_datetime(e["times"])
        t2 = np.asarray(e["t2"])
        det = np.asarray(e["detected"])
        ax.scatter(t[~det], t2[~det], s=3, color="#1f77b4", label="no shift")
        ax.scatter(t[det], t2[det], s=3, color="#d62728", label="shift detected (SD)")
        ax.axhline(
            e["t2_critical"],
            color="k",
            lw=0.8,
            ls="--",
            label=f"critical value, alpha={result['alpha']}",
        )
        ax.axvline(split, color="grey", lw=1, label="split")
        if e.get("first_shift"):
            ax.axvline(
                _naive_utc(e["first_shift"]),
                color="#ff7f0e",
                lw=1.2,
                label="first confirmed shift",
            )
        ax.set_yscale("log")
        # A well name is text, never mathtext ($...$); the log axis' labels are mathtext.
        ax.set_title(f"{well}: Hotelling T² vs reference window", fontsize=9, parse_math=False)
        ax.set_ylabel("T² (-)")
        ax.tick_params(labelsize=7)
        page.date_axis(ax)
    for ax in axes.ravel()[len(wells) :]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7, loc="upper left", markerscale=3)
    fig.tight_layout()
    return page.png(fig)


def _rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    return [
        {
            "well": str(well),
            "n_train": e.get("n_train", 0),
            "period_days": e.get("period_days"),
            "first_shift": str(e.get("first_shift") or e.get("error") or "none"),
            "share_after_split": e.get("share_detected_after_split"),
        }
        for well, e in result["wells"].items()
    ]


def build_report(
    result: dict[str, Any], path: str | os.PathLike[str], data_path: str | os.PathLike[str]
) -> Path:
    """Write the drift result as one self-contained HTML page at ``path`` (written
    atomically) and return the path; ``data_path`` names the observation file."""
    image = _figure(result)
    html = page.render(
        "drift.html.j2",
        result=result,
        data_path=str(data_path),
        rows=_rows(result),
        image=image,
    )
    return page.write_page(path, html)
