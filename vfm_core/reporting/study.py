"""The study report: one self-contained HTML page with the paper's tables and figures.

Owns what the study page shows and computes: :func:`build_report` renders a
:class:`vfm_core.jobs.results.StudyResult` for a production engineer: a computed summary
in plain words, the mean MAPE table (the paper's Tables 2/3), the per-well MAPE table
(Table C1/C2), per-well MAPE box plots, the 14-day rolling error against time, the days
between well tests (Figure and Table C3), predicted against measured rates per well and,
when tracked, the discharge coefficient over time.

This module shapes the numbers and draws the figures; the page itself is the template
``templates/study.html.j2`` on the shared layout of :mod:`vfm_core.reporting.page`, which
escapes every text taken from the data. Tables use every scored observation; only the
figures thin their points to keep the file small. Rates are in Sm3/h, errors in percent.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.artist import Artist
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from vfm_core.jobs.results import StudyResult
from vfm_core.jobs.study import probabilistic_scores
from vfm_core.reporting import page
from vfm_core.reporting.page import Png

__all__ = ["build_report", "calibration_curve", "BENCHMARK"]

#: The benchmark model: it repeats the most recent measured rate (the paper's Benchmark).
BENCHMARK = "last"

#: Most points drawn per panel in the time-series grids (tables never subsample).
_MAX_POINTS_PER_PANEL = 1500

_MODEL_NAMES: dict[str, str] = {
    "last": "benchmark: the last measured rate",
    "lr": "linear regression",
    "nn": "feed-forward neural network",
    "mtl": "multi-task neural network, shared across wells",
    "mm": "mechanistic choke model",
    "hem": "hybrid error model: mechanistic model plus a network for its error",
    "ham": "hybrid area-function model: a network for the choke opening area",
}
_TARGET_NAMES: dict[str, str] = {
    "all": "MPFM and well-test measurements (the paper's case 1)",
    "well_test": "well-test measurements only (the paper's case 2)",
}
_SPAN_UNITS: dict[str, str] = {"d": "days", "w": "weeks", "m": "months", "y": "years", "h": "hours"}
_METHOD_COLOURS: tuple[str, ...] = (
    "#1f77b4",  # blue
    "#d62728",  # red
    "#2ca02c",  # green
    "#9467bd",  # purple
    "#ff7f0e",  # orange
    "#8c564b",  # brown
    "#e377c2",  # pink
    "#17becf",  # cyan
)
#: Bins of the days between two chronological well tests (the paper's Table C3).
_GAP_EDGES_DAYS: tuple[float, ...] = (0.0, 14.0, 30.0, 61.0, 91.0, 182.0, 273.0, 365.0, math.inf)
_GAP_LABELS: tuple[str, ...] = (
    "< 2w",
    "2w-1m",
    "1m-2m",
    "2m-3m",
    "3m-6m",
    "6m-9m",
    "9m-1y",
    "> 1y",
)
#: Off-scale wells named in the box plot's caption (the rest are counted).
_MAX_OFF_SCALE_NAMED = 12


# --------------------------------------------------------------------------- small helpers


def _natural_key(text: str) -> list[Any]:
    """Sort key so that W2 comes before W10."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", text)]


def _to_float(value: Any) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return math.nan
    return out if np.isfinite(out) else math.nan


def _method_label(method: str) -> str:
    """A method name in words, e.g. ``pbl:14d`` -> periodic batch learning every 14 days."""
    if method == "ol":
        return "online learning: update with every new measurement"
    m = re.fullmatch(r"pbl:(\d+)([a-z])(?::window=(\d+)([a-z]))?", method)
    if m:
        text = f"periodic batch learning: retrain every {m[1]} {_SPAN_UNITS.get(m[2], m[2])}"
        if m[3]:
            text += f" on the last {m[3]} {_SPAN_UNITS.get(m[4], m[4])} of data"
        return text
    return method


def _model_label(model: str) -> str:
    return _MODEL_NAMES.get(model, model)


def _naive_utc(values: Any) -> Any:
    """Datetimes as timezone-naive UTC (what matplotlib's date axis expects)."""
    index = pd.DatetimeIndex(pd.to_datetime(values, utc=True))
    return index.tz_convert("UTC").tz_localize(None)


def _thin_index(n: int, limit: int) -> np.ndarray:
    """Evenly spaced row positions, at most ``limit`` of them, keeping the first and last."""
    if n <= limit:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max(limit, 2)).round().astype(int))


def _break_gaps(times: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Insert NaN where the data pause, so a line is not drawn across a shut-in or data gap.

    A gap is longer than 7 days or three times the typical spacing, whichever is longer.
    ``times`` are naive datetime64.
    """
    if len(times) < 3:
        return times, values
    step = np.diff(times).astype("timedelta64[s]").astype(float)
    limit = max(7 * 86400.0, 3.0 * float(np.median(step)))
    cut = np.flatnonzero(step > limit) + 1
    if cut.size == 0:
        return times, values
    gap_times = times[cut - 1] + (times[cut] - times[cut - 1]) / 2
    return (
        np.insert(times, cut, gap_times),
        np.insert(values.astype(float), cut, np.nan),
    )


def _axis_top(values: Iterable[float], typical: Iterable[float]) -> float | None:
    """Upper y limit that shows the data but not a diverged model's astronomical errors.

    ``typical`` are central values (medians of boxes or lines). Values above
    ``max(100 %, 10 x the median of typical)`` count as diverged and are left off the scale,
    so one blow-up cannot flatten every other box or line; the caller marks them.
    ``None`` when nothing is left (the caller then lets matplotlib choose).
    """
    vals = np.asarray([v for v in values if np.isfinite(v)], dtype=float)
    typ = np.asarray([v for v in typical if np.isfinite(v)], dtype=float)
    if vals.size == 0:
        return None
    threshold = max(100.0, 10.0 * float(np.median(typ))) if typ.size else 100.0
    kept = vals[vals <= threshold]
    if kept.size == 0:
        return None
    top = 1.1 * float(kept.max())
    return top if top > 0 else 1.0


def _date_axes_below(axes: np.ndarray, n_panels: int) -> None:
    """Readable dates under the bottom row of a grid of ``n_panels`` panels sharing x.

    With an odd number of panels the hidden last cell leaves the one above it without
    dates, so that one gets its own labels.
    """
    for ax in axes[-1, :]:
        ax.set_xlabel("time (UTC)")
        page.date_axis(ax)
    ncols = axes.shape[1]
    if n_panels % ncols and axes.shape[0] > 1:
        ax = axes[-2, -1]
        ax.xaxis.set_tick_params(labelbottom=True)
        ax.set_xlabel("time (UTC)")


# --------------------------------------------------------------------------- data shaping

#: Keys of a record that mark a score other than the default one (total, ordinary protocol).
_SCORE_KEYS: tuple[str, ...] = ("target", "outage")
#: The total's name in the target column of the protocol tables.
_TOTAL = "q_total"
_TARGET_LABELS: dict[str, str] = {
    "q_total": "total",
    "q_gas": "gas",
    "q_oil": "oil",
    "q_water": "water",
}


def _default_rows(frame: pd.DataFrame) -> pd.DataFrame:
    """The rows of a records or summary frame without ``target`` (or with the total) and
    without ``outage``: the ordinary protocol on the total rate."""
    keep = np.ones(len(frame), dtype=bool)
    if "target" in frame.columns:
        target = frame["target"]
        keep &= (target.isna() | (target.astype(str) == _TOTAL)).to_numpy()
    if "outage" in frame.columns:
        keep &= frame["outage"].isna().to_numpy()
    return frame[keep].reset_index(drop=True)


def _protocol_frame(frame: pd.DataFrame) -> pd.DataFrame:
    """Records or summary rows with explicit ``protocol`` (``ordinary`` or the outage
    length) and ``target`` (``q_total`` for the total) columns."""
    # object dtype: filling a float column of NaN with a string is deprecated in pandas
    absent = pd.Series(np.nan, frame.index, dtype=object)
    outage = frame["outage"] if "outage" in frame.columns else absent
    target = frame["target"] if "target" in frame.columns else absent
    return frame.assign(
        protocol=outage.fillna("ordinary").astype(str),
        target=target.fillna(_TOTAL).astype(str),
    )


class _Study:
    """The result's tables in the shapes the report needs (no subsampling)."""

    def __init__(self, result: StudyResult) -> None:
        self.result = result
        preds = result.predictions
        if preds is None or not isinstance(preds, pd.DataFrame):
            preds = pd.DataFrame()
        for col in ("time", "well", "model", "method", "predicted", "measured"):
            if col not in preds.columns:
                preds = preds.assign(**{col: pd.Series(dtype=float)})
        if "source" not in preds.columns:
            preds = preds.assign(source="mpfm")
        self.preds = preds
        records = pd.DataFrame(list(result.records or []))
        if records.empty:
            records = pd.DataFrame(columns=["model", "method", "well", "mape", "n"])
        # phase and outage records have their own sections; the paper's tables are the total's
        self.all_records = records
        records = _default_rows(records)
        records = records.assign(
            model=records["model"].astype(str),
            method=records["method"].astype(str),
            well=records["well"].astype(str),
            mape=[_to_float(v) for v in records["mape"]],
        )
        self.records = records
        summary = pd.DataFrame(list(result.summary or []))
        if summary.empty:
            summary = pd.DataFrame(columns=["model", "method", "mean_mape", "median_mape", "wells"])
        summary = _default_rows(summary)
        summary = summary.assign(
            model=summary["model"].astype(str),
            method=summary["method"].astype(str),
            mean_mape=[_to_float(v) for v in summary["mean_mape"]],
        )
        self.summary = summary

        def ordered(column: str) -> list[str]:
            seen: dict[str, None] = {}
            for frame in (summary, records, preds):
                for value in frame[column].dropna().astype(str):
                    seen.setdefault(value, None)
            return list(seen)

        self.methods = ordered("method")
        all_models = ordered("model")
        self.models = [m for m in all_models if m != BENCHMARK]
        self.has_benchmark = BENCHMARK in all_models
        self.all_models = self.models + ([BENCHMARK] if self.has_benchmark else [])
        wells = set(records["well"].dropna().astype(str)) | set(preds["well"].dropna().astype(str))
        wells |= {str(w) for w in (result.well_tests or {})}
        self.wells = sorted(wells, key=_natural_key)
        self.colours = {
            m: _METHOD_COLOURS[i % len(_METHOD_COLOURS)] for i, m in enumerate(self.methods)
        }

        # Mean MAPE across wells: model x method. From the summary when given, else from the
        # records (same definition as evaluate.summarise).
        if not summary.empty:
            mean = summary.pivot_table(
                index="method", columns="model", values="mean_mape", aggfunc="first", dropna=False
            )
        else:
            mean = records.groupby(["method", "model"])["mape"].mean().unstack("model")
        self.mean = mean.reindex(index=self.methods, columns=self.all_models).astype(float)
        self.all_column = self.mean[self.models].mean(axis=1, skipna=True) if self.models else None
        # NaN mean of an all-NaN row must stay NaN, not 0.
        if self.all_column is not None:
            has_any = self.mean[self.models].notna().any(axis=1)
            self.all_column = self.all_column.where(has_any)

    def per_well(self, model: str, method: str, well: str) -> float:
        r = self.records
        hit = r[(r["model"] == model) & (r["method"] == method) & (r["well"] == well)]["mape"]
        return float(hit.iloc[0]) if len(hit) else math.nan

    def best_model(self) -> str | None:
        """The non-benchmark model with the lowest mean MAPE (averaged over the methods)."""
        if not self.models:
            return None
        avg = self.mean[self.models].mean(axis=0, skipna=True)
        avg = avg[self.mean[self.models].notna().any(axis=0)]
        if avg.empty:
            return self.models[0]
        return str(avg.idxmin())

    def scored(self) -> pd.DataFrame:
        """Scored predictions with their absolute percentage error ``ape`` (%)."""
        p = self.preds
        pred = pd.to_numeric(p["predicted"], errors="coerce").to_numpy(dtype=float)
        meas = pd.to_numeric(p["measured"], errors="coerce").to_numpy(dtype=float)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ape = np.abs(pred - meas) / np.abs(meas) * 100.0
        ok = np.isfinite(ape)
        out = p.loc[ok, ["time", "well", "model", "method"]].copy()
        out["ape"] = ape[ok]
        out["time"] = pd.to_datetime(out["time"], utc=True)
        out["well"] = out["well"].astype(str)
        return out


# --------------------------------------------------------------------------- text sections
# Each returns the numbers and plain-text pieces one part of the template shows.


def _header(study: _Study) -> dict[str, Any]:
    r = study.result
    p = study.preds
    finite = np.isfinite(pd.to_numeric(p["predicted"], errors="coerce").to_numpy(dtype=float))
    per_combo = p.groupby(["model", "method"]).size() if len(p) else pd.Series(dtype=int)
    first = p.groupby(["model", "method"]).ngroup() == 0 if len(p) else pd.Series(dtype=bool)
    by_source = p.loc[first.to_numpy(dtype=bool), "source"].astype(str).value_counts()
    runtime = float(r.runtime_s or 0.0)
    runtime_text = f"{runtime:,.1f} s" + (f" ({runtime / 60:.1f} min)" if runtime >= 120 else "")
    targets = str(r.targets)
    return {
        "data_path": str(r.data_path or "(not recorded)"),
        "targets": targets,
        "target_text": _TARGET_NAMES.get(targets, targets),
        "split_text": pd.Timestamp(r.split).strftime("%Y-%m-%d %H:%M UTC"),
        "runtime_text": runtime_text,
        "wells": study.wells,
        "n_scored_wells": len({str(w) for w in p.loc[finite, "well"]}),
        "n_test": int(per_combo.max()) if len(per_combo) else 0,
        "sources": [(str(k), int(v)) for k, v in by_source.items()],
        "n_scored": int(finite.sum()),
        "n_runs": len(per_combo),
        "models": [(m, _model_label(m)) for m in study.all_models],
        "methods": [(m, study.colours[m], _method_label(m)) for m in study.methods],
    }


def _summary(study: _Study) -> dict[str, Any]:
    """The facts behind the plain-language findings; the template words them.

    Every key is present; a finding that does not apply is ``None`` or empty.
    """
    facts: dict[str, Any] = {
        "empty": True,
        "n_models": len(study.models),
        "models": study.models,
        "methods_ranked": [],
        "median_best": None,
        "best_method_per_model": [],
        "best_combination": None,
        "best_model": None,
        "many_methods": len(study.methods) > 1,
        "benchmark": None,
        "diverged": [],
        "n_diverged_more": 0,
        "missing_wells": [],
    }
    mean = study.mean
    if mean.empty or not np.isfinite(mean.to_numpy(dtype=float)).any():
        return facts
    facts["empty"] = False
    if study.all_column is not None and study.all_column.notna().any():
        facts.update(_method_findings(study, study.all_column))
    models_block = mean[study.models] if study.models else pd.DataFrame()
    if not models_block.empty and np.isfinite(models_block.to_numpy(dtype=float)).any():
        stacked = models_block.stack().dropna()
        (meth, model) = stacked.idxmin()
        if len(stacked) > 1:
            facts["best_combination"] = (str(model), str(meth), float(stacked.min()))
        best_model = study.best_model()
        if best_model is not None and len(study.models) > 1:
            facts["best_model"] = (best_model, _model_label(best_model))
    if study.has_benchmark:
        facts["benchmark"] = _benchmark_finding(mean[BENCHMARK].dropna(), models_block)

    # The mean hides how the wells differ: name divergent wells and the spread.
    rec = study.records
    extreme = rec[rec["mape"] > 100.0].sort_values("mape", ascending=False)
    facts["diverged"] = [
        (str(r.well), str(r.model), str(r.method), float(r.mape))
        for r in extreme.head(6).itertuples()
    ]
    facts["n_diverged_more"] = max(len(extreme) - 6, 0)
    facts["missing_wells"] = sorted(
        {str(w) for w in study.wells} - {str(w) for w in rec.loc[rec["mape"].notna(), "well"]},
        key=_natural_key,
    )
    return facts


def _method_findings(study: _Study, all_column: pd.Series) -> dict[str, Any]:
    """The methods ranked by their mean MAPE over all models; the method best by the
    median when it is another; which method is best for which model."""
    facts: dict[str, Any] = {}
    col = all_column.dropna().sort_values()
    facts["methods_ranked"] = [(str(m), float(v)) for m, v in col.items()]
    best_m = str(col.index[0])
    if len(col) < 2:
        return facts
    # The mean across wells is at the mercy of a single diverged well; the median is not.
    rec = study.records[study.records["model"].isin(study.models)]
    med = rec.groupby(["model", "method"])["mape"].median().groupby("method").mean()
    med = med.reindex(study.methods).dropna().sort_values()
    if len(med) > 1 and str(med.index[0]) != best_m:
        facts["median_best"] = (
            str(med.index[0]),
            float(med.iloc[0]),
            float(med.get(best_m, math.nan)),
            best_m,
        )
    per_model = (
        study.mean[study.models].idxmin(axis=0, skipna=True).dropna()
        if study.mean[study.models].notna().any().any()
        else pd.Series(dtype=str)
    )
    per_model = per_model[study.mean[study.models].notna().any(axis=0)]
    if len(per_model) > 1:
        groups: dict[str, list[str]] = {}
        for model, meth in per_model.items():
            groups.setdefault(str(meth), []).append(str(model))
        facts["best_method_per_model"] = list(groups.items())
    return facts


def _benchmark_finding(bench: pd.Series, models_block: pd.DataFrame) -> dict[str, Any] | None:
    """The benchmark's best mean MAPE (``bench``: per method, NaN dropped) and how many of
    the models' model-method means beat it; None without a benchmark score."""
    if bench.empty:
        return None
    b_val = float(bench.min())
    beaten: tuple[int, int] | None = None
    if not models_block.empty:
        vals = models_block.to_numpy(dtype=float).ravel()
        vals = vals[np.isfinite(vals)]
        if vals.size:
            beaten = (int((vals < b_val).sum()), int(vals.size))
    return {"name": BENCHMARK, "method": str(bench.idxmin()), "mape": b_val, "beaten": beaten}


def _mean_table(study: _Study) -> dict[str, Any] | None:
    """Mean MAPE across wells: one row per method, one cell per model column."""
    mean = study.mean
    if mean.empty:
        return None
    columns: list[tuple[str, pd.Series, bool]] = [(m, mean[m], False) for m in study.models]
    if study.all_column is not None:
        columns.append(("All", study.all_column, True))
    if study.has_benchmark:
        columns.append((f"{BENCHMARK} (benchmark)", mean[BENCHMARK], True))
    rows = []
    for meth in study.methods:
        cells = []
        for _, series, sep in columns:
            value = float(series.get(meth, math.nan))
            finite = series.dropna()
            # A column where every method ties has no best cell to point at.
            best = bool(finite.nunique() > 1 and np.isfinite(value) and value == finite.min())
            classes = " ".join(c for c in ("best" if best else "", "sep" if sep else "") if c)
            cells.append((value, classes))
        rows.append({"method": meth, "colour": study.colours[meth], "cells": cells})
    return {"columns": [(name, sep) for name, _, sep in columns], "rows": rows}


def _well_table(study: _Study) -> dict[str, Any] | None:
    """MAPE per well: one cell per model listing every method's value, the lowest marked."""
    if study.records.empty:
        return None
    names = {m: m if m != BENCHMARK else f"{m} (benchmark)" for m in study.all_models}
    rows = []
    for well in study.wells:
        cells = []
        for model in study.all_models:
            values = [study.per_well(model, meth, well) for meth in study.methods]
            finite = [v for v in values if np.isfinite(v)]
            low = min(finite) if len(finite) > 1 else None
            parts = [(v, low is not None and v == low) for v in values]
            cells.append((parts, model == BENCHMARK))
        rows.append({"well": well, "cells": cells})
    return {
        "methods": study.methods,
        "columns": [(names[m], m == BENCHMARK) for m in study.all_models],
        "rows": rows,
    }


# --------------------------------------------------------------------------- figures


def _method_legend(study: _Study, extra: Sequence[Any] = ()) -> list[Any]:
    handles: list[Any] = [
        Patch(facecolor=study.colours[m], edgecolor="black", label=m) for m in study.methods
    ]
    return handles + list(extra)


def _box_plot(study: _Study) -> dict[str, Any] | None:
    """Box plot of the per-well MAPE and the wells it leaves off its scale."""
    rec = study.records.dropna(subset=["mape"])
    if rec.empty:
        return None
    groups = study.models + ([BENCHMARK] if study.has_benchmark else [])
    width = 0.8 / max(len(study.methods), 1)
    boxes = _boxes(study, rec, groups, width)
    stats, positions, colours = boxes.stats, boxes.positions, boxes.colours
    top = _axis_top(np.concatenate(boxes.values), [s["med"] for s in stats])
    fig = Figure(figsize=(max(7.0, 1.5 * len(groups) + 3), 4.8))
    ax = fig.subplots()
    parts = ax.bxp(
        stats,
        positions=positions,
        widths=width * 0.85,
        patch_artist=True,
        showfliers=True,
        flierprops={
            "marker": "o",
            "markersize": 3.5,
            "markerfacecolor": "none",
            "markeredgecolor": "#444",
        },
        medianprops={"color": "black", "linewidth": 1.5},
    )
    for patch, colour in zip(parts["boxes"], colours, strict=True):
        patch.set_facecolor(colour)
        patch.set_alpha(0.75)
    off_scale: list[tuple[str, str, float]] = []
    if top is not None:
        ax.set_ylim(0, top)
        off_scale = _mark_off_scale(ax, top, boxes)
    if study.has_benchmark and study.models:
        ax.axvline(len(study.models) - 0.5, color="#888", linestyle=":", linewidth=1)
    ax.set_xticks(range(len(groups)))
    ax.set_xticklabels([g if g != BENCHMARK else f"{g}\n(benchmark)" for g in groups])
    ax.set_xlim(-0.6, len(groups) - 0.4)
    ax.set_xlabel("model")
    ax.set_ylabel("MAPE per well (%)")
    ax.set_title(f"Per-well MAPE by model and learning method ({rec['well'].nunique()} wells)")
    ax.grid(axis="y", alpha=0.3)
    extra = [
        Line2D([], [], color="black", linewidth=1.5, label="median"),
        Line2D(
            [],
            [],
            marker="o",
            linestyle="none",
            markerfacecolor="none",
            markeredgecolor="#444",
            markersize=4,
            label="well outside P10-P90",
        ),
    ]
    ax.legend(
        handles=_method_legend(study, extra),
        title="learning method",
        fontsize=8,
        title_fontsize=8,
        loc="upper left",
        bbox_to_anchor=(1.0, 1.0),
    )
    return {
        "png": page.png(fig),
        "top": top,
        "off_scale": off_scale[:_MAX_OFF_SCALE_NAMED],
        "n_off_scale_more": max(len(off_scale) - _MAX_OFF_SCALE_NAMED, 0),
    }


@dataclass
class _Boxes:
    """The boxes of :func:`_box_plot`, one entry per model and method with scores: the
    matplotlib box statistics (P10-P90 whiskers), the x position and colour, and the
    per-well MAPE (%) with the wells' names and the box's label."""

    stats: list[dict[str, Any]] = field(default_factory=list)
    positions: list[float] = field(default_factory=list)
    colours: list[str] = field(default_factory=list)
    values: list[np.ndarray] = field(default_factory=list)
    wells: list[np.ndarray] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)


def _boxes(study: _Study, rec: pd.DataFrame, groups: list[str], width: float) -> _Boxes:
    """One box per model (a group on the x axis) and method (side by side, ``width`` apart)."""
    n_meth = max(len(study.methods), 1)
    out = _Boxes()
    for gi, model in enumerate(groups):
        for mi, meth in enumerate(study.methods):
            sel = rec[(rec["model"] == model) & (rec["method"] == meth)]
            values = sel["mape"].to_numpy(dtype=float)
            if values.size == 0:
                continue
            p10, p25, p50, p75, p90 = np.percentile(values, [10, 25, 50, 75, 90])
            out.stats.append(
                {
                    "med": p50,
                    "q1": p25,
                    "q3": p75,
                    "whislo": p10,
                    "whishi": p90,
                    "fliers": values[(values < p10) | (values > p90)],
                    "label": "",
                }
            )
            out.positions.append(gi + (mi - (n_meth - 1) / 2) * width)
            out.colours.append(study.colours[meth])
            out.values.append(values)
            out.wells.append(sel["well"].astype(str).to_numpy())
            out.labels.append(f"{model}, {meth}")
    return out


def _mark_off_scale(ax: Any, top: float, boxes: _Boxes) -> list[tuple[str, str, float]]:
    """Mark above each box how many of its wells lie above ``top`` (%); those wells, named."""
    off_scale: list[tuple[str, str, float]] = []
    for pos, values, wells, label in zip(
        boxes.positions, boxes.values, boxes.wells, boxes.labels, strict=True
    ):
        above = values > top
        if above.any():
            off_scale += [
                (str(w), label, float(v)) for w, v in zip(wells[above], values[above], strict=True)
            ]
            ax.annotate(
                f"{int(above.sum())} off scale ↑",
                xy=(pos, top),
                xytext=(0, -4),
                textcoords="offset points",
                ha="center",
                va="top",
                rotation=90,
                fontsize=7,
                color="#b00",
            )
    return off_scale


def _rolling_frames(study: _Study, scored: pd.DataFrame) -> dict[tuple[str, str], pd.DataFrame]:
    """Per model and method: daily median, P25 and P75 across wells of the 14-day rolling APE."""
    out: dict[tuple[str, str], pd.DataFrame] = {}
    if scored.empty:
        return out
    start = scored["time"].min().floor("D")
    end = scored["time"].max().floor("D")
    days = pd.date_range(start, end, freq="D")
    for (model, meth), g in scored.groupby(["model", "method"], sort=False):
        daily = (
            g.assign(day=g["time"].dt.floor("D"))
            .groupby(["day", "well"])["ape"]
            .mean()
            .unstack("well")
            .reindex(days)
        )
        rolling = daily.rolling(14, min_periods=1).mean()
        out[(str(model), str(meth))] = pd.DataFrame(
            {
                "median": rolling.median(axis=1, skipna=True),
                "p25": rolling.quantile(0.25, axis=1),
                "p75": rolling.quantile(0.75, axis=1),
            },
            index=days,
        )
    return out


def _rolling_plot(study: _Study, scored: pd.DataFrame) -> dict[str, Any] | None:
    """The 14-day rolling error across wells per model, and where its shared axis stops."""
    frames = _rolling_frames(study, scored)
    if not frames:
        return None
    panels = [m for m in study.all_models if any((m, meth) in frames for meth in study.methods)]
    ncols = 1 if len(panels) == 1 else 2
    nrows = math.ceil(len(panels) / ncols)
    fig = Figure(figsize=(7.2 * ncols, 2.9 * nrows + 0.6))
    axes = fig.subplots(nrows, ncols, sharex=True, sharey=True, squeeze=False)
    top = _axis_top(
        np.concatenate([f["p75"].to_numpy(dtype=float) for f in frames.values()]),
        [float(f["median"].median()) for f in frames.values() if f["median"].notna().any()],
    )
    updates = (
        {m: list(study.result.updates.get(m, []) or []) for m in study.methods}
        if study.result.updates
        else {}
    )
    for ax, model in zip(axes.flat, panels, strict=False):
        off: list[str] = []
        for meth in study.methods:
            frame = frames.get((model, meth))
            if frame is None:
                continue
            x = _naive_utc(frame.index)
            colour = study.colours[meth]
            ax.fill_between(
                x,
                frame["p25"].to_numpy(dtype=float),
                frame["p75"].to_numpy(dtype=float),
                color=colour,
                alpha=0.15,
                linewidth=0,
            )
            ax.plot(x, frame["median"].to_numpy(dtype=float), color=colour, linewidth=1.3)
            if top is not None and (frame["p75"] > top).any():
                what = "median" if (frame["median"] > top).any() else "P75"
                off.append(f"{meth}: {what} partly above {top:.0f} %")
        for meth, times in updates.items():
            if not times:
                continue
            alpha = 0.6 if len(times) <= 12 else 0.18
            for t in _naive_utc(times):
                ax.axvline(t, color=study.colours.get(meth, "#888"), linewidth=0.7, alpha=alpha)
        name = model if model != BENCHMARK else f"{model} (benchmark)"
        ax.set_title(name, fontsize=10)
        if off:
            ax.text(
                0.01,
                0.97,
                "off scale: " + "; ".join(off),
                transform=ax.transAxes,
                ha="left",
                va="top",
                fontsize=7,
                color="#b00",
                bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 1},
            )
        ax.grid(alpha=0.3)
        ax.set_ylabel("14-day rolling APE (%)")
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    if top is not None:
        axes.flat[0].set_ylim(0, top)
    _date_axes_below(axes, len(panels))
    extra: list[Any] = [Patch(facecolor="#888", alpha=0.3, label="P25-P75 across wells")]
    if any(updates.values()):
        extra.append(
            Line2D([], [], color="#555", linewidth=0.7, label="PBL retrain (method colour)")
        )
    handles = [
        Line2D([], [], color=study.colours[m], linewidth=2, label=f"{m}: median across wells")
        for m in study.methods
    ] + extra
    fig.suptitle("14-day rolling absolute percentage error across wells, by model", fontsize=12)
    page.bottom_legend(fig, handles)
    return {"png": page.png(fig), "top": top}


def _gap_counts(well_tests: dict[str, list[Any]]) -> pd.DataFrame:
    """Number of gaps between chronological well tests per well (rows) and bin (columns)."""
    rows = {}
    for well, times in well_tests.items():
        if times is None or len(times) < 2:
            continue
        t = pd.DatetimeIndex(pd.to_datetime(list(times), utc=True)).sort_values().unique()
        if len(t) < 2:
            continue
        # pandas may hold any resolution (s, us, ns): convert explicitly, never via asi8.
        gaps = (
            np.diff(t.tz_localize(None).to_numpy()).astype("timedelta64[s]").astype(float) / 86400.0
        )
        binned = pd.cut(gaps, bins=list(_GAP_EDGES_DAYS), labels=list(_GAP_LABELS), right=False)
        rows[str(well)] = pd.Series(binned).value_counts().reindex(list(_GAP_LABELS), fill_value=0)
    if not rows:
        return pd.DataFrame(columns=list(_GAP_LABELS))
    frame = pd.DataFrame(rows).T
    return frame.reindex(sorted(frame.index, key=_natural_key)).astype(int)


def _well_test_section(study: _Study) -> dict[str, Any] | None:
    """Histogram and table of the days between chronological well tests per well."""
    counts = _gap_counts(study.result.well_tests or {})
    if counts.empty:
        return None
    cmap = matplotlib.colormaps["tab20b" if len(counts) > 10 else "tab10"]
    fig = Figure(figsize=(9, 4.6))
    ax = fig.subplots()
    bottom = np.zeros(len(_GAP_LABELS))
    x = np.arange(len(_GAP_LABELS))
    for i, (well, row) in enumerate(counts.iterrows()):
        values = row.to_numpy(dtype=float)
        ax.bar(
            x,
            values,
            bottom=bottom,
            color=cmap(i % cmap.N),
            edgecolor="white",
            linewidth=0.5,
            label=str(well),
        )
        bottom += values
    ax.set_xticks(x)
    ax.set_xticklabels(_GAP_LABELS)
    ax.set_xlabel("time between two chronological well tests (w = week, m = month, y = year)")
    ax.set_ylabel("number of intervals (-)")
    ax.set_title("Time between well tests, stacked by well")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(
        title="well",
        fontsize=8,
        title_fontsize=8,
        ncol=1 if len(counts) <= 12 else 2,
        loc="upper left",
        bbox_to_anchor=(1.0, 1.0),
    )
    pct = counts.div(counts.sum(axis=1), axis=0) * 100.0
    rows = [
        {
            "well": str(well),
            "tests": int(counts.loc[well].sum()) + 1,
            "shares": [float(v) for v in row.to_numpy(dtype=float)],
        }
        for well, row in pct.iterrows()
    ]
    return {
        "png": page.png(fig),
        "edges": [int(e) for e in _GAP_EDGES_DAYS[1:-1]],
        "bins": _GAP_LABELS,
        "rows": rows,
    }


def _rate_limits(measured: np.ndarray, predicted: pd.Series) -> tuple[float, float]:
    """y limits (Sm3/h) for one well: the measured range widened to take in most predictions.

    Predictions may widen the range by at most twice the measured span on either side, so a
    model whose prediction ran away does not squash the measurements into a flat line.
    """
    if measured.size == 0:
        return math.nan, math.nan
    lo, hi = float(measured.min()), float(measured.max())
    span = max(hi - lo, 0.1 * max(abs(hi), 1.0))
    q = pd.to_numeric(predicted, errors="coerce").to_numpy(dtype=float)
    q = q[np.isfinite(q)]
    if q.size:
        q_lo, q_hi = np.percentile(q, [1, 99])
        lo = max(min(lo, float(q_lo)), lo - 2 * span)
        hi = min(max(hi, float(q_hi)), hi + 2 * span)
    pad = 0.05 * (hi - lo)
    return max(0.0, lo - pad), hi + pad


def _rates_grid(study: _Study, model: str, why: str) -> dict[str, Any] | None:
    """Predicted against measured rates per well for one model; ``why`` it is shown
    (``"best"``: the most accurate model, ``"mechanistic"``: mm, whose parameters mean
    something)."""
    p = study.preds
    sub = p[p["model"] == model]
    if sub.empty:
        return None
    sub = sub.assign(time=pd.to_datetime(sub["time"], utc=True), well=sub["well"].astype(str))
    measured = sub.drop_duplicates(["time", "well", "source"]).sort_values("time")
    wells = [w for w in study.wells if (sub["well"] == w).any()]
    if not wells:
        return None
    ncols = 1 if len(wells) == 1 else 2
    nrows = math.ceil(len(wells) / ncols)
    fig = Figure(figsize=(7.2 * ncols, 2.7 * nrows + 0.6))
    axes = fig.subplots(nrows, ncols, sharex=True, squeeze=False)
    n_series = len(study.methods) + 1
    per_series = max(200, _MAX_POINTS_PER_PANEL // n_series)
    any_clipped = False
    banded = False
    for ax, well in zip(axes.flat, wells, strict=False):
        finite_meas = _plot_measured(ax, measured[measured["well"] == well], per_series)
        drawn = False
        clipped = False
        y_lo, y_hi = _rate_limits(finite_meas, sub.loc[sub["well"] == well, "predicted"])
        for meth in study.methods:
            g = sub[(sub["well"] == well) & (sub["method"] == meth)].sort_values("time")
            line = _plot_predicted(ax, g, study.colours[meth], per_series)
            if line is None:
                continue
            q, with_band = line
            banded = banded or with_band
            drawn = True
            if np.isfinite(y_hi) and ((q > y_hi) | (q < y_lo)).any():
                clipped = True
        if np.isfinite(y_lo) and np.isfinite(y_hi) and y_hi > y_lo:
            ax.set_ylim(y_lo, y_hi)
        title = well
        if not drawn:
            title += "  (no scored predictions)"
        if clipped:
            title += "  (some predictions off scale)"
            any_clipped = True
        ax.set_title(title, fontsize=10)
        ax.set_ylabel("total rate (Sm3/h)")
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(wells) :]:
        ax.set_visible(False)
    _date_axes_below(axes, len(wells))
    fig.suptitle(f"Predicted and measured total rate per well, model {model}", fontsize=12)
    page.bottom_legend(fig, _rates_legend(study, banded))
    return {
        "model": model,
        "label": _model_label(model),
        "why": why,
        "png": page.png(fig),
        "per_series": per_series,
        "clipped": any_clipped,
        "banded": banded,
    }


def _plot_measured(ax: Any, meas: pd.DataFrame, per_series: int) -> np.ndarray:
    """One well's measured rates on ``ax`` (MPFM grey dots thinned to ``per_series``, well
    tests black diamonds); the finite measured rates, Sm3/h."""
    meas_q = pd.to_numeric(meas["measured"], errors="coerce").to_numpy(dtype=float)
    is_test = (meas["source"].astype(str) == "well_test").to_numpy()
    mpfm = meas[~is_test]
    idx = _thin_index(len(mpfm), per_series)
    ax.plot(
        _naive_utc(mpfm["time"].iloc[idx]),
        mpfm["measured"].iloc[idx],
        linestyle="none",
        marker=".",
        markersize=2.5,
        color="#9a9a9a",
        zorder=1,
    )
    tests = meas[is_test]
    ax.plot(
        _naive_utc(tests["time"]),
        tests["measured"],
        linestyle="none",
        marker="D",
        markersize=3.5,
        color="black",
        zorder=4,
    )
    return meas_q[np.isfinite(meas_q)]


def _plot_predicted(
    ax: Any, g: pd.DataFrame, colour: str, per_series: int
) -> tuple[np.ndarray, bool] | None:
    """One method's predictions for one well on ``ax`` (``g`` sorted by time): a line thinned
    to ``per_series`` points and broken at gaps, under it the 90 % interval where the method
    gives one. The finite predicted rates (Sm3/h) and whether a band was drawn; None when
    no prediction is finite."""
    q = pd.to_numeric(g["predicted"], errors="coerce").to_numpy(dtype=float)
    ok = np.isfinite(q)
    if not ok.any():
        return None
    times = _naive_utc(g["time"]).to_numpy()[ok]
    q = q[ok]
    idx = _thin_index(len(q), per_series)
    banded = False
    if {"predicted_p05", "predicted_p95"} <= set(g.columns):
        lo = pd.to_numeric(g["predicted_p05"], errors="coerce").to_numpy(dtype=float)[ok]
        hi = pd.to_numeric(g["predicted_p95"], errors="coerce").to_numpy(dtype=float)[ok]
        if np.isfinite(lo).any() and np.isfinite(hi).any():
            band_t, band_lo = _break_gaps(times[idx], lo[idx])
            _, band_hi = _break_gaps(times[idx], hi[idx])
            ax.fill_between(
                band_t, band_lo, band_hi, color=colour, alpha=0.18, linewidth=0, zorder=2
            )
            banded = True
    line_t, line_q = _break_gaps(times[idx], q[idx])
    ax.plot(line_t, line_q, color=colour, linewidth=0.9, alpha=0.85, zorder=3)
    return q, banded


def _rates_legend(study: _Study, banded: bool) -> list[Artist]:
    """The legend of the rates grid: the two kinds of measurement, one line per method,
    and the interval's band when one was drawn."""
    handles: list[Artist] = [
        Line2D(
            [],
            [],
            linestyle="none",
            marker=".",
            markersize=6,
            color="#9a9a9a",
            label="measured (MPFM)",
        ),
        Line2D(
            [],
            [],
            linestyle="none",
            marker="D",
            markersize=5,
            color="black",
            label="measured (well test)",
        ),
        *(
            Line2D([], [], color=study.colours[m], linewidth=2, label=f"predicted, {m}")
            for m in study.methods
        ),
    ]
    if banded:
        handles.append(Patch(facecolor="#888", alpha=0.3, label="90 % predictive interval"))
    return handles


def _rates_section(study: _Study) -> list[dict[str, Any]]:
    """The rates of the best model and, when it is not the best, of the mechanistic model."""
    best = study.best_model()
    if best is None:
        return []
    grids = [_rates_grid(study, best, "best")]
    if "mm" in study.models and best != "mm":
        grids.append(_rates_grid(study, "mm", "mechanistic"))
    return [g for g in grids if g is not None]


def _parameter_section(study: _Study) -> Png | None:
    """The discharge coefficient of mm over time per well, when it was tracked."""
    params = study.result.parameters
    if params is None or not isinstance(params, pd.DataFrame) or params.empty:
        return None
    needed = {"time", "well", "model", "method", "name", "value"}
    if not needed.issubset(params.columns):
        return None
    cd = params[(params["model"].astype(str) == "mm") & (params["name"].astype(str) == "c_d")]
    cd = cd.assign(value=pd.to_numeric(cd["value"], errors="coerce")).dropna(subset=["value"])
    if cd.empty:
        return None
    cd = cd.assign(time=pd.to_datetime(cd["time"], utc=True), well=cd["well"].astype(str))
    wells = sorted(cd["well"].unique(), key=_natural_key)
    methods = [m for m in study.methods if (cd["method"] == m).any()]
    methods += [m for m in dict.fromkeys(cd["method"].astype(str)) if m not in methods]
    colours = {m: study.colours.get(m, "#555") for m in methods}
    ncols = 1 if len(wells) == 1 else 2
    nrows = math.ceil(len(wells) / ncols)
    fig = Figure(figsize=(7.2 * ncols, 2.5 * nrows + 0.6))
    axes = fig.subplots(nrows, ncols, sharex=True, squeeze=False)
    end = pd.to_datetime(study.preds["time"], utc=True).max() if len(study.preds) else None
    for ax, well in zip(axes.flat, wells, strict=False):
        for meth in methods:
            g = cd[(cd["well"] == well) & (cd["method"] == meth)].sort_values("time")
            if g.empty:
                continue
            times = g["time"]
            values = g["value"].to_numpy(dtype=float)
            # Hold the last value to the end of the test period, as the model does.
            if end is not None and pd.notna(end) and times.iloc[-1] < end:
                times = pd.concat([times, pd.Series([end])], ignore_index=True)
                values = np.append(values, values[-1])
            idx = _thin_index(len(values), 1000)
            ax.plot(
                _naive_utc(times.iloc[idx]),
                values[idx],
                drawstyle="steps-post",
                color=colours[meth],
                linewidth=1.1,
            )
        ax.set_title(well, fontsize=10)
        ax.set_ylabel("discharge coefficient C_D (-)")
        ax.yaxis.set_major_formatter("{x:.3f}")
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(wells) :]:
        ax.set_visible(False)
    _date_axes_below(axes, len(wells))
    handles = [Line2D([], [], color=colours[m], linewidth=2, label=m) for m in methods]
    fig.suptitle(
        "Discharge coefficient C_D of the mechanistic model mm after each update", fontsize=12
    )
    page.bottom_legend(fig, handles, title="learning method", title_fontsize=8)
    return page.png(fig)


# --------------------------------------------------------------------------- phases, outages, intervals


def _protocol_table(study: _Study) -> dict[str, Any] | None:
    """Mean MAPE across wells per protocol (ordinary, each outage length) and target (total
    and phases): one cell per model at its best method, the benchmark last. ``None`` when
    the study has neither phases nor outages."""
    summary = pd.DataFrame(list(study.result.summary or []))
    if summary.empty or not any(k in summary.columns for k in _SCORE_KEYS):
        return None
    df = _protocol_frame(summary)
    df = df.assign(mean_mape=[_to_float(v) for v in df["mean_mape"]])
    df = df[np.isfinite(df["mean_mape"].to_numpy(dtype=float))]
    if df.empty:
        return None
    protocols = list(dict.fromkeys(["ordinary", *df["protocol"]]))
    targets = [t for t in _TARGET_LABELS if (df["target"] == t).any()]
    models = [m for m in study.all_models if (df["model"] == m).any()]
    rows = []
    for protocol in protocols:
        for target in targets:
            sel = df[(df["protocol"] == protocol) & (df["target"] == target)]
            if sel.empty:
                continue
            best = sel.loc[sel.groupby("model")["mean_mape"].idxmin()].set_index("model")
            contenders = [m for m in models if m != BENCHMARK and m in best.index]
            low = min((float(best.loc[m, "mean_mape"]) for m in contenders), default=math.nan)
            bench = float(best.loc[BENCHMARK, "mean_mape"]) if BENCHMARK in best.index else math.nan
            cells = []
            for m in models:
                if m not in best.index:
                    cells.append((math.nan, "", ""))
                    continue
                value = float(best.loc[m, "mean_mape"])
                classes = []
                if m != BENCHMARK and value == low:
                    classes.append("best")
                if m == BENCHMARK:
                    classes.append("sep")
                cells.append((value, str(best.loc[m, "method"]), " ".join(classes)))
            rows.append(
                {
                    "protocol": protocol,
                    "target": _TARGET_LABELS.get(target, target),
                    "cells": cells,
                    "beats": bool(np.isfinite(bench) and np.isfinite(low) and low < bench),
                }
            )
    columns = [(m if m != BENCHMARK else f"{m} (benchmark)", m == BENCHMARK) for m in models]
    return {"columns": columns, "rows": rows, "has_benchmark": BENCHMARK in models}


#: Edges (days since the last measurement) of the outage figure's bins.
_SINCE_EDGES: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0, 7.0, 14.0, 30.0, 60.0, 90.0, 180.0, 365.0)


def _outage_section(study: _Study) -> dict[str, Any] | None:
    """Error against days since the last measurement, inside the outage windows, per model
    (panels) and method (lines), with the benchmark's curve on every panel."""
    preds = study.result.outage_predictions
    if preds is None or not isinstance(preds, pd.DataFrame) or preds.empty:
        return None
    if not {"days_since", "predicted", "measured", "model", "method"} <= set(preds.columns):
        return None
    binned = _outage_curves(preds)
    if binned is None:
        return None
    curves, edges, mids = binned
    panels = [mdl for mdl in study.models if (curves["model"] == mdl).any()]
    bench = curves[curves["model"] == BENCHMARK]
    if bench.empty and not panels:
        return None
    if not panels:
        panels = [BENCHMARK]
    ncols = 1 if len(panels) == 1 else 2
    nrows = math.ceil(len(panels) / ncols)
    fig = Figure(figsize=(7.2 * ncols, 2.9 * nrows + 0.7))
    axes = fig.subplots(nrows, ncols, sharex=True, sharey=True, squeeze=False)
    top = _axis_top(curves["mean"], curves.groupby("model")["mean"].median())
    for ax, model in zip(axes.flat, panels, strict=False):
        _outage_panel(ax, study, curves, mids, model, bench)
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    for ax in axes[-1, :]:
        ax.set_xlabel("days since the last measurement learned from")
    if top is not None:
        axes.flat[0].set_ylim(0, top)
    handles = [
        Line2D([], [], color=study.colours[m], marker="o", markersize=3, label=m)
        for m in study.methods
    ]
    if not bench.empty and panels != [BENCHMARK]:
        handles.append(
            Line2D([], [], color="black", linestyle="--", label=f"{BENCHMARK} (benchmark)")
        )
    fig.suptitle("Error inside the outage windows against the time without a measurement")
    page.bottom_legend(fig, handles)
    windows = study.result.outage_windows
    counts: list[tuple[str, int, int, int]] = []
    if isinstance(windows, pd.DataFrame) and not windows.empty:
        for label, g in windows.groupby("outage", sort=False):
            counts.append((str(label), len(g), int(g["well"].nunique()), int(g["rows"].sum())))
    return {
        "png": page.png(fig),
        "windows": counts,
        "fractions": str(study.result.outage_fractions),
        "edges": [int(e) if float(e).is_integer() else e for e in edges[1:-1]],
    }


def _outage_curves(preds: pd.DataFrame) -> tuple[pd.DataFrame, list[float], np.ndarray] | None:
    """The mean APE (%) per model, method and bin of days since the last measurement, over
    the bins with at least 5 points; the bin edges and mid-points (days). None when no row
    has a finite error."""
    q = pd.to_numeric(preds["predicted"], errors="coerce").to_numpy(dtype=float)
    m = pd.to_numeric(preds["measured"], errors="coerce").to_numpy(dtype=float)
    since = pd.to_numeric(preds["days_since"], errors="coerce").to_numpy(dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        ape = np.abs(q - m) / np.abs(m) * 100.0
    ok = np.isfinite(ape) & np.isfinite(since)
    if not ok.any():
        return None
    data = pd.DataFrame(
        {
            "model": preds["model"].astype(str).to_numpy()[ok],
            "method": preds["method"].astype(str).to_numpy()[ok],
            "since": since[ok],
            "ape": ape[ok],
        }
    )
    top_days = float(data["since"].max())
    edges = [e for e in _SINCE_EDGES if e < top_days] + [top_days + 1e-9]
    data["bin"] = pd.cut(data["since"], bins=edges, right=False, labels=False)
    mids = np.array([(a + b) / 2 for a, b in zip(edges[:-1], edges[1:], strict=True)])
    curves = data.groupby(["model", "method", "bin"])["ape"].agg(["mean", "size"]).reset_index()
    curves = curves[curves["size"] >= 5]  # a bin of a handful of points says little
    return curves, edges, mids


def _outage_panel(
    ax: Any,
    study: _Study,
    curves: pd.DataFrame,
    mids: np.ndarray,
    model: str,
    bench: pd.DataFrame,
) -> None:
    """One model's panel: a line per method, and the benchmark's best curve dashed."""
    for meth in study.methods:
        g = curves[(curves["model"] == model) & (curves["method"] == meth)]
        if g.empty:
            continue
        ax.plot(
            mids[g["bin"].to_numpy(dtype=int)],
            g["mean"],
            color=study.colours.get(meth, "#555"),
            marker="o",
            markersize=3,
            linewidth=1.3,
        )
    if model != BENCHMARK and not bench.empty:
        b = bench.groupby("bin")["mean"].min()
        ax.plot(
            mids[b.index.to_numpy(dtype=int)],
            b.to_numpy(dtype=float),
            color="black",
            linestyle="--",
            linewidth=1.2,
        )
    ax.set_title(model if model != BENCHMARK else f"{model} (benchmark)", fontsize=10)
    ax.set_xscale("symlog", linthresh=1.0)
    ax.grid(alpha=0.3)
    ax.set_ylabel("MAPE in the bin (%)")


def _phase_grid(study: _Study) -> dict[str, Any] | None:
    """Predicted against measured phase rates per well (rows) and phase (columns), for the
    best model at its best method."""
    p = study.preds
    phases = [ph for ph in ("q_gas", "q_oil", "q_water") if f"predicted_{ph}" in p.columns]
    phases = [ph for ph in phases if f"measured_{ph}" in p.columns]
    model = study.best_model()
    if not phases or model is None:
        return None
    col = study.mean[model].dropna() if model in study.mean.columns else pd.Series(dtype=float)
    if col.empty:
        return None
    method = str(col.idxmin())
    sub = p[(p["model"] == model) & (p["method"] == method)]
    sub = sub.assign(time=pd.to_datetime(sub["time"], utc=True), well=sub["well"].astype(str))
    wells = [w for w in study.wells if (sub["well"] == w).any()]
    if not wells:
        return None
    fig = Figure(figsize=(4.6 * len(phases), 2.1 * len(wells) + 0.8))
    axes = fig.subplots(len(wells), len(phases), sharex=True, squeeze=False)
    for i, well in enumerate(wells):
        g = sub[sub["well"] == well].sort_values("time")
        times = _naive_utc(g["time"]).to_numpy()
        idx = _thin_index(len(g), 600)
        for k, phase in enumerate(phases):
            ax = axes[i, k]
            meas = pd.to_numeric(g[f"measured_{phase}"], errors="coerce").to_numpy(dtype=float)
            pred = pd.to_numeric(g[f"predicted_{phase}"], errors="coerce").to_numpy(dtype=float)
            ax.plot(
                times[idx], meas[idx], linestyle="none", marker=".", markersize=2.5, color="#9a9a9a"
            )
            line_t, line_q = _break_gaps(times[idx], pred[idx])
            ax.plot(line_t, line_q, color=study.colours.get(method, "#1f77b4"), linewidth=0.9)
            finite = meas[np.isfinite(meas)]
            y_lo, y_hi = _rate_limits(finite, pd.Series(pred))
            if np.isfinite(y_lo) and np.isfinite(y_hi) and y_hi > y_lo:
                ax.set_ylim(y_lo, y_hi)
            ax.grid(alpha=0.3)
            if i == 0:
                ax.set_title(f"{_TARGET_LABELS[phase]} (Sm3/h)", fontsize=10)
            if k == 0:
                ax.set_ylabel(well, fontsize=9)
    for ax in axes[-1, :]:
        ax.set_xlabel("time (UTC)")
        page.date_axis(ax)
    handles = [
        Line2D(
            [], [], linestyle="none", marker=".", markersize=6, color="#9a9a9a", label="measured"
        ),
        Line2D([], [], color=study.colours.get(method, "#1f77b4"), label=f"predicted, {method}"),
    ]
    fig.suptitle(f"Phase rates per well, model {model} with {method}", fontsize=12)
    fig.legend(
        handles=handles,
        loc="lower center",
        ncol=2,
        fontsize=8,
        bbox_to_anchor=(0.5, -0.005),
        frameon=False,
    )
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    return {"png": page.png(fig), "model": model, "method": method}


#: Nominal levels of the calibration plot's central intervals.
_LEVELS: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)


def calibration_curve(
    predicted: np.ndarray, measured: np.ndarray, p95: np.ndarray, levels: Sequence[float] = _LEVELS
) -> np.ndarray:
    """Observed coverage of central intervals at each nominal level, for a log-normal
    predictive distribution with median ``predicted`` whose 95 % quantile is ``p95``
    (sd in log space ``log(p95 / predicted) / 1.6449``). NaN where nothing is scored."""
    from statistics import NormalDist

    q = np.asarray(predicted, dtype=float)
    m = np.asarray(measured, dtype=float)
    hi = np.asarray(p95, dtype=float)
    ok = np.isfinite(q) & np.isfinite(m) & np.isfinite(hi) & (q > 0) & (m > 0) & (hi > q)
    if not ok.any():
        return np.full(len(levels), np.nan)
    sd = np.log(hi[ok] / q[ok]) / NormalDist().inv_cdf(0.95)
    z = np.abs(np.log(m[ok] / q[ok])) / sd
    return np.array([float(np.mean(z <= NormalDist().inv_cdf(0.5 + lv / 2))) for lv in levels])


def _calibration_section(study: _Study) -> dict[str, Any] | None:
    """Observed against nominal coverage of the predictive intervals, per model and method
    (ordinary protocol solid, outage protocol dashed)."""
    frames = [("ordinary", study.preds)]
    outage = study.result.outage_predictions
    if isinstance(outage, pd.DataFrame) and not outage.empty:
        frames.append(("outage", outage))
    curves = []
    for protocol, frame in frames:
        if not {"predicted_p95", "predicted"} <= set(frame.columns):
            continue
        for (model, meth), g in frame.groupby(["model", "method"], sort=False):
            cov = calibration_curve(
                g["predicted"].to_numpy(dtype=float),
                g["measured"].to_numpy(dtype=float),
                g["predicted_p95"].to_numpy(dtype=float),
            )
            if np.isfinite(cov).any():
                crps = float("nan")
                if "predicted_p05" in g.columns:
                    _, crps = probabilistic_scores(
                        g["measured"], g["predicted_p05"], g["predicted_p95"]
                    )
                curves.append((protocol, str(model), str(meth), cov, crps))
    if not curves:
        return None
    fig = Figure(figsize=(6.4, 5.4))
    ax = fig.subplots()
    levels = np.array(_LEVELS) * 100
    ax.plot([0, 100], [0, 100], color="#888", linewidth=1, linestyle=":")
    markers = "osD^v<>ph*"
    pairs = list(dict.fromkeys((mdl, meth) for _, mdl, meth, _, _ in curves))
    rows = []
    for protocol, model, meth, cov, crps in curves:
        k = pairs.index((model, meth))
        ax.plot(
            levels,
            cov * 100,
            color=study.colours.get(meth, "#555"),
            marker=markers[k % len(markers)],
            markersize=4,
            linestyle="-" if protocol == "ordinary" else "--",
            label=f"{model}, {meth}" + ("" if protocol == "ordinary" else " (outages)"),
        )
        rows.append((model, meth, protocol, float(cov[_LEVELS.index(0.9)]) * 100, crps))
    ax.set_xlim(0, 100)
    ax.set_ylim(0, 100)
    ax.set_xlabel("nominal coverage of the central interval (%)")
    ax.set_ylabel("observed coverage (%)")
    ax.set_title("Calibration of the predictive intervals")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    return {"png": page.png(fig), "rows": rows}


def _separator_section(separators: Sequence[Any]) -> dict[str, Any] | None:
    """The separators' totals (``vfm evaluate`` on data with separator readings): each run's
    well-test MAPE with and without learning from the readings, per well, and a figure of
    the reconciliation residual over time (the total minus the sum of the wells'
    predictions, %, a rolling mean over 15 readings), learned from (solid) and not (dashed)."""
    if not separators:
        return None
    runs, wells = [], []
    for sep in separators:
        m = sep.metrics()
        runs.append(m)
        for well, r in m["wells"].items():
            wells.append(
                (
                    m["model"],
                    m["method"],
                    well,
                    r["n"],
                    r["mape_without_percent"],
                    r["mape_percent"],
                )
            )
    names = sorted({str(n) for sep in separators for n in sep.run.allocation.get("separator", [])})
    png = None
    if names:
        fig = Figure(figsize=(8.0, 2.4 + 1.6 * len(names)))
        axes = fig.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
        colours = matplotlib.colormaps["tab10"]
        for k, sep in enumerate(separators):
            for run, style, what in (
                (sep.run, "-", "learned from"),
                (sep.without, "--", "not learned from"),
            ):
                if run.allocation.empty:
                    continue
                res = run.reading_residuals()
                for ax, name in zip(axes, names, strict=True):
                    g = res[res["separator"] == name]
                    if g.empty:
                        continue
                    smooth = g["percent"].rolling(15, min_periods=1).mean().to_numpy()
                    stamps = pd.DatetimeIndex(pd.to_datetime(g["time"], utc=True))
                    times = stamps.tz_convert(None).to_numpy()  # UTC, as datetime64
                    # no line across a week without readings (a shut-in, a historian gap)
                    gap = np.flatnonzero(np.diff(times) > np.timedelta64(7, "D")) + 1
                    smooth = np.insert(smooth, gap, np.nan)
                    times = np.insert(times, gap, times[gap - 1] + np.timedelta64(1, "D"))
                    ax.plot(
                        times,
                        smooth,
                        linestyle=style,
                        color=colours(k % 10),
                        linewidth=1.2,
                        label=f"{sep.model}, {sep.method}: readings {what}",
                    )
        for ax, name in zip(axes, names, strict=True):
            ax.axhline(0.0, color="#888", linewidth=0.8)
            ax.set_ylabel(f"{name}: total - sum (%)")
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8, loc="best")
        axes[0].set_title("Separator totals against the sum of the wells' predictions")
        fig.tight_layout()
        png = page.png(fig)
    return {"png": png, "runs": runs, "wells": wells}


# --------------------------------------------------------------------------- entry point


def build_report(result: StudyResult, path: Path, *, separators: Sequence[Any] = ()) -> Path:
    """Write the study as one self-contained HTML file at ``path`` and return the path.

    Figures are PNG embedded as base64; nothing is loaded from outside the file. Text taken
    from the data (well, model and method names, the data path) is escaped by the template
    engine. The file is written atomically.
    """
    study = _Study(result)
    scored = study.scored()
    # Names from the data go into figure text too: never read them as mathtext ($...$).
    with matplotlib.rc_context({"text.parse_math": False}):
        context = {
            "title_targets": str(result.targets),
            "title_split": str(pd.Timestamp(result.split).date()),
            "header": _header(study),
            "summary": _summary(study),
            "mean_table": _mean_table(study),
            "well_table": _well_table(study),
            "box": _box_plot(study),
            "rolling": _rolling_plot(study, scored),
            "well_tests": _well_test_section(study),
            "rates": _rates_section(study),
            "c_d": _parameter_section(study),
            "protocols": _protocol_table(study),
            "outages": _outage_section(study),
            "phases": _phase_grid(study),
            "calibration": _calibration_section(study),
            "separators": _separator_section(separators),
        }
    return page.write_page(path, page.render("study.html.j2", **context))
