"""One self-contained HTML page with the paper's tables and figures for a finished study.

:func:`build_report` renders a :class:`vfm_core.jobs.evaluate.StudyResult` for a production
engineer: a computed summary in plain words, the mean MAPE table (the paper's Tables 2/3),
the per-well MAPE table (Table C1/C2), per-well MAPE box plots, the 14-day rolling error
against time, the days between well tests (Figure and Table C3), predicted against measured
rates per well and, when tracked, the discharge coefficient over time.

The page has no external resources: figures are PNG (matplotlib, Agg backend) embedded as
base64, styles are inline. Tables use every scored observation; only the figures thin
their points to keep the file small. Rates are in Sm3/h, errors in percent.
"""

from __future__ import annotations

import base64
import html
import io
import math
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.dates as mdates  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from PIL import Image  # noqa: E402

if TYPE_CHECKING:
    from vfm_core.jobs.evaluate import StudyResult

__all__ = ["build_report", "BENCHMARK"]

#: The benchmark model: it repeats the most recent measured rate (the paper's Benchmark).
BENCHMARK = "last"

_DPI = 100
_SEP = ' class="sep"'
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

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, Helvetica, Arial, sans-serif;
       max-width: 1180px; margin: 1.5em auto; padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { font-size: 1.25em; margin-top: 2em; border-bottom: 1px solid #ccc; padding-bottom: 0.2em; }
table { border-collapse: collapse; margin: 0.6em 0 1.2em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; white-space: nowrap; }
th { background: #f2f2f2; }
td.label, th.label { text-align: left; }
td.best { background: #d9f2d9; font-weight: bold; }
td.sep, th.sep { border-left: 3px double #999; }
table.meta td, table.meta th { text-align: left; border: none; padding: 0.1em 1em 0.1em 0; }
table.meta th { background: none; font-weight: 600; }
caption { caption-side: top; text-align: left; font-size: 0.92em; color: #444;
          padding-bottom: 0.3em; }
figure { margin: 1em 0 2em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: 0.92em; color: #444; margin-top: 0.3em; }
p.summary { background: #f7f9fc; border-left: 4px solid #1f77b4; padding: 0.6em 1em; }
p.note { color: #555; font-size: 0.92em; }
span.swatch { display: inline-block; width: 0.9em; height: 0.9em; vertical-align: middle;
              margin-right: 0.3em; border-radius: 2px; }
"""


# --------------------------------------------------------------------------- small helpers


def _esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _natural_key(text: str) -> list[Any]:
    """Sort key so that W2 comes before W10."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", text)]


def _fmt_pct(value: float | None, digits: int = 1) -> str:
    """A percentage for a table cell; huge values (diverged models) in scientific notation."""
    if value is None or not np.isfinite(value):
        return "–"
    if abs(value) >= 1e4:
        return f"{value:.1e}"
    return f"{value:.{digits}f}"


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


def _figure_html(fig: Figure, caption: str, alt: str) -> str:
    """Encode a figure as an embedded PNG and close it."""
    try:
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=_DPI, bbox_inches="tight")
    finally:
        plt.close(fig)
    # A 256-colour palette looks the same for line plots and makes the PNG about 3x smaller.
    buf.seek(0)
    with Image.open(buf) as image:
        small = io.BytesIO()
        image.convert("RGB").quantize(colors=256).save(small, format="PNG", optimize=True)
    data = base64.b64encode(small.getvalue()).decode("ascii")
    return (
        f'<figure><img src="data:image/png;base64,{data}" alt="{_esc(alt)}">'
        f"<figcaption>{caption}</figcaption></figure>\n"
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


# --------------------------------------------------------------------------- data shaping


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


def _header(study: _Study) -> str:
    r = study.result
    p = study.preds
    finite = np.isfinite(pd.to_numeric(p["predicted"], errors="coerce").to_numpy(dtype=float))
    n_scored = int(finite.sum())
    per_combo = p.groupby(["model", "method"]).size() if len(p) else pd.Series(dtype=int)
    n_test = int(per_combo.max()) if len(per_combo) else 0
    first = p.groupby(["model", "method"]).ngroup() == 0 if len(p) else pd.Series(dtype=bool)
    by_source = p.loc[first.to_numpy(dtype=bool), "source"].astype(str).value_counts()
    source_text = ", ".join(f"{_esc(k)} {int(v):,}" for k, v in by_source.items()) or "none"
    n_runs = len(per_combo)
    scored_wells = sorted({str(w) for w in p.loc[finite, "well"]}, key=_natural_key)
    runtime = float(r.runtime_s or 0.0)
    runtime_text = f"{runtime:,.1f} s" + (f" ({runtime / 60:.1f} min)" if runtime >= 120 else "")
    split = pd.Timestamp(r.split)
    target_text = _TARGET_NAMES.get(str(r.targets), str(r.targets))
    rows = [
        ("Data", _esc(r.data_path or "(not recorded)")),
        ("Target case", f"<code>{_esc(r.targets)}</code> = {_esc(target_text)}"),
        ("Split (start of the test period)", _esc(split.strftime("%Y-%m-%d %H:%M UTC"))),
        ("Runtime", _esc(runtime_text)),
        (
            "Wells",
            f"{len(study.wells)} ({len(scored_wells)} with scored predictions): "
            + _esc(", ".join(study.wells)),
        ),
        ("Test observations per model and method", f"{n_test:,} ({source_text})"),
        ("Scored predictions", f"{n_scored:,} over {n_runs} model-method runs"),
        (
            "Models",
            "<br>".join(
                f"<code>{_esc(m)}</code>: {_esc(_model_label(m))}" for m in study.all_models
            )
            or "none",
        ),
        (
            "Learning methods",
            "<br>".join(
                f'<span class="swatch" style="background:{study.colours[m]}"></span>'
                f"<code>{_esc(m)}</code>: {_esc(_method_label(m))}"
                for m in study.methods
            )
            or "none",
        ),
    ]
    body = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    return (
        "<h1>Virtual flow meter study: passive learning</h1>\n"
        f'<table class="meta">{body}</table>\n'
        '<p class="note">MAPE: mean absolute percentage error of the predicted total rate '
        "(Sm3/h) against the measured rate, per well over the whole test period, in percent. "
        "Every observation is predicted before the model learns from it.</p>\n"
    )


def _summary_text(study: _Study) -> str:
    """Plain-language findings computed from the numbers."""
    sentences: list[str] = []
    mean = study.mean
    if mean.empty or not np.isfinite(mean.to_numpy(dtype=float)).any():
        return (
            '<h2>What this shows</h2>\n<p class="summary">No model produced a scored '
            "prediction, so there is nothing to compare.</p>\n"
        )

    n_models = len(study.models)
    over = f"the {n_models} models" if n_models != 1 else f"model {_esc(study.models[0])}"
    if study.all_column is not None and study.all_column.notna().any():
        col = study.all_column.dropna().sort_values()
        best_m = str(col.index[0])
        if len(col) == 1:
            sentences.append(
                f"With the one learning method <b>{_esc(best_m)}</b>, the mean MAPE across wells "
                f"averaged over {over} is {_fmt_pct(col.iloc[0])}&nbsp;%."
            )
        else:
            ranking = ", ".join(f"{_esc(m)} {_fmt_pct(v)}&nbsp;%" for m, v in col.iloc[1:].items())
            sentences.append(
                f"Averaged over {over}, <b>{_esc(best_m)}</b> gives the lowest mean MAPE "
                f"({_fmt_pct(col.iloc[0])}&nbsp;%; then {ranking})."
            )
            # The mean across wells is at the mercy of a single diverged well; the median is not.
            rec = study.records[study.records["model"].isin(study.models)]
            med = rec.groupby(["model", "method"])["mape"].median().groupby("method").mean()
            med = med.reindex(study.methods).dropna().sort_values()
            if len(med) > 1 and str(med.index[0]) != best_m:
                sentences.append(
                    f"On the median across wells, which one bad well cannot dominate, "
                    f"<b>{_esc(med.index[0])}</b> is best instead ({_fmt_pct(med.iloc[0])}&nbsp;%"
                    f" against {_fmt_pct(med.get(best_m, math.nan))}&nbsp;% for {_esc(best_m)})."
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
                parts = [
                    f"{_esc(meth)} for {_esc(', '.join(models))}" for meth, models in groups.items()
                ]
                sentences.append("The best method per model is " + "; ".join(parts) + ".")

    models_block = mean[study.models] if study.models else pd.DataFrame()
    if not models_block.empty and np.isfinite(models_block.to_numpy(dtype=float)).any():
        stacked = models_block.stack().dropna()
        (meth, model) = stacked.idxmin()
        if len(stacked) > 1:
            sentences.append(
                f"The best single combination is <b>{_esc(model)}</b> with <b>{_esc(meth)}</b> "
                f"({_fmt_pct(stacked.min())}&nbsp;% mean MAPE across wells)."
            )
        best_model = study.best_model()
        if best_model is not None and len(study.models) > 1:
            over_methods = "Averaged over the methods, t" if len(study.methods) > 1 else "T"
            sentences.append(
                f"{over_methods}he most accurate model is <b>{_esc(best_model)}</b> "
                f"({_esc(_model_label(best_model))})."
            )

    if study.has_benchmark:
        bench = mean[BENCHMARK].dropna()
        if not bench.empty:
            b_meth = str(bench.idxmin())
            b_val = float(bench.min())
            text = (
                f"The benchmark <b>{BENCHMARK}</b> (repeat the most recent measured rate) "
                f"reaches {_fmt_pct(b_val)}&nbsp;% at best ({_esc(b_meth)})"
            )
            if not models_block.empty:
                vals = models_block.to_numpy(dtype=float).ravel()
                vals = vals[np.isfinite(vals)]
                if vals.size:
                    beaten = int((vals < b_val).sum())
                    text += f"; {beaten} of {vals.size} model-method combinations beat it"
            sentences.append(text + ".")

    # The mean hides how the wells differ: name divergent wells and the spread.
    rec = study.records
    extreme = rec[rec["mape"] > 100.0]
    if len(extreme):
        items = [
            f"{_esc(r.well)} with {_esc(r.model)}/{_esc(r.method)} ({_fmt_pct(r.mape)}&nbsp;%)"
            for r in extreme.sort_values("mape", ascending=False).head(6).itertuples()
        ]
        more = f" and {len(extreme) - 6} more" if len(extreme) > 6 else ""
        sentences.append(
            "<b>Warning:</b> some wells have a MAPE above 100&nbsp;%, i.e. the model's "
            f"predictions ran away: {', '.join(items)}{more}. A mean across wells that "
            "includes such a well says little; look at the medians in the box plot instead."
        )
    missing = sorted(
        {str(w) for w in study.wells} - {str(w) for w in rec.loc[rec["mape"].notna(), "well"]},
        key=_natural_key,
    )
    if missing:
        sentences.append(f"No scored predictions for: {_esc(', '.join(missing))}.")
    return '<h2>What this shows</h2>\n<p class="summary">' + " ".join(sentences) + "</p>\n"


def _mean_table(study: _Study) -> str:
    mean = study.mean
    if mean.empty:
        return "<h2>Mean MAPE across wells</h2><p>No results.</p>\n"
    columns: list[tuple[str, pd.Series, bool]] = [(m, mean[m], False) for m in study.models]
    if study.all_column is not None:
        columns.append(("All", study.all_column, True))
    if study.has_benchmark:
        columns.append((f"{BENCHMARK} (benchmark)", mean[BENCHMARK], True))
    head = '<th class="label">Learning method</th>' + "".join(
        f"<th{_SEP if sep else ''}>{_esc(name)}</th>" for name, _, sep in columns
    )
    body = []
    for meth in study.methods:
        cells = [
            f'<td class="label"><span class="swatch" style="background:{study.colours[meth]}">'
            f"</span>{_esc(meth)}</td>"
        ]
        for _, series, sep in columns:
            value = float(series.get(meth, math.nan))
            finite = series.dropna()
            # A column where every method ties has no best cell to point at.
            best = bool(finite.nunique() > 1 and np.isfinite(value) and value == finite.min())
            cls = " ".join(c for c in ("best" if best else "", "sep" if sep else "") if c)
            cells.append(
                f"<td{f' class={chr(34)}{cls}{chr(34)}' if cls else ''}>{_fmt_pct(value)}</td>"
            )
        body.append("<tr>" + "".join(cells) + "</tr>")
    caption = (
        "Mean MAPE across wells (%) per model (columns) and learning method (rows), as the paper's "
        "Tables 2 and 3. <i>All</i> averages the non-benchmark models. The lowest value in each "
        "column is highlighted."
    )
    return (
        "<h2>Mean MAPE across wells</h2>\n"
        f"<table><caption>{caption}</caption><thead><tr>{head}</tr></thead>"
        f"<tbody>{''.join(body)}</tbody></table>\n"
    )


def _well_table(study: _Study) -> str:
    if study.records.empty:
        return ""
    order = ", ".join(_esc(m) for m in study.methods)
    names = {m: m if m != BENCHMARK else f"{m} (benchmark)" for m in study.all_models}
    head = '<th class="label">Well</th>' + "".join(
        f"<th{_SEP if m == BENCHMARK else ''}>{_esc(names[m])}</th>" for m in study.all_models
    )
    body = []
    for well in study.wells:
        cells = [f'<td class="label">{_esc(well)}</td>']
        for model in study.all_models:
            values = [study.per_well(model, meth, well) for meth in study.methods]
            finite = [v for v in values if np.isfinite(v)]
            low = min(finite) if len(finite) > 1 else None
            parts = [
                f"<b>{_fmt_pct(v)}</b>" if low is not None and v == low else _fmt_pct(v)
                for v in values
            ]
            cells.append(f"<td{_SEP if model == BENCHMARK else ''}>{', '.join(parts)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    caption = (
        f"MAPE (%) per well, model and learning method, as the paper's Table C1. Each cell lists "
        f"the methods in the order <b>{order}</b>; the lowest of each cell is bold; – means no "
        "scored prediction."
    )
    return (
        "<h2>MAPE per well</h2>\n"
        f"<table><caption>{caption}</caption><thead><tr>{head}</tr></thead>"
        f"<tbody>{''.join(body)}</tbody></table>\n"
    )


# --------------------------------------------------------------------------- figures


def _method_legend(study: _Study, extra: Sequence[Any] = ()) -> list[Any]:
    handles: list[Any] = [
        Patch(facecolor=study.colours[m], edgecolor="black", label=m) for m in study.methods
    ]
    return handles + list(extra)


def _box_plot(study: _Study) -> str:
    rec = study.records.dropna(subset=["mape"])
    if rec.empty:
        return "<h2>Per-well MAPE</h2><p>No per-well MAPE to plot.</p>\n"
    groups = study.models + ([BENCHMARK] if study.has_benchmark else [])
    n_meth = max(len(study.methods), 1)
    width = 0.8 / n_meth
    stats, positions, colours, raw, raw_wells, labels = [], [], [], [], [], []
    for gi, model in enumerate(groups):
        for mi, meth in enumerate(study.methods):
            sel = rec[(rec["model"] == model) & (rec["method"] == meth)]
            values = sel["mape"].to_numpy(dtype=float)
            if values.size == 0:
                continue
            p10, p25, p50, p75, p90 = np.percentile(values, [10, 25, 50, 75, 90])
            stats.append(
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
            positions.append(gi + (mi - (n_meth - 1) / 2) * width)
            colours.append(study.colours[meth])
            raw.append(values)
            raw_wells.append(sel["well"].astype(str).to_numpy())
            labels.append(f"{model}, {meth}")
    top = _axis_top(np.concatenate(raw), [s["med"] for s in stats])
    fig, ax = plt.subplots(figsize=(max(7.0, 1.5 * len(groups) + 3), 4.8))
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
    off_scale: list[str] = []
    if top is not None:
        ax.set_ylim(0, top)
        for pos, values, wells, label in zip(positions, raw, raw_wells, labels, strict=True):
            above = values > top
            if above.any():
                off_scale += [
                    f"{_esc(w)} ({_esc(label)}): {_fmt_pct(v)}&nbsp;%"
                    for w, v in zip(wells[above], values[above], strict=True)
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
    caption = (
        "Distribution across wells of the MAPE, grouped by model, one box per learning method "
        "(as the paper's Figures 8/11). Boxes: P25 to P75, line: median, whiskers: P10 and P90, "
        "circles: single wells outside the whiskers. The benchmark is its own group on the right."
    )
    if off_scale:
        caption += (
            f" The y axis stops at {top:.0f}&nbsp;%; red labels count the wells above it "
            f"(diverged predictions): {'; '.join(off_scale[:12])}"
            + (f" and {len(off_scale) - 12} more." if len(off_scale) > 12 else ".")
        )
    return "<h2>Per-well MAPE</h2>\n" + _figure_html(fig, caption, "box plot of per-well MAPE")


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


def _rolling_plot(study: _Study, scored: pd.DataFrame) -> str:
    title = "<h2>Error over time</h2>\n"
    frames = _rolling_frames(study, scored)
    if not frames:
        return title + "<p>No scored predictions to plot.</p>\n"
    panels = [m for m in study.all_models if any((m, meth) in frames for meth in study.methods)]
    ncols = 1 if len(panels) == 1 else 2
    nrows = math.ceil(len(panels) / ncols)
    fig, axes = plt.subplots(
        nrows,
        ncols,
        figsize=(7.2 * ncols, 2.9 * nrows + 0.6),
        sharex=True,
        sharey=True,
        squeeze=False,
    )
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
    for ax in axes[-1, :]:
        ax.set_xlabel("time (UTC)")
        ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(ax.xaxis.get_major_locator()))
    # With an odd number of panels, the hidden last cell leaves the one above without dates.
    if len(panels) % ncols and nrows > 1:
        ax = axes[-2, -1]
        ax.xaxis.set_tick_params(labelbottom=True)
        ax.set_xlabel("time (UTC)")
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
    fig.legend(
        handles=handles,
        loc="lower center",
        ncol=min(len(handles), 5),
        fontsize=8,
        bbox_to_anchor=(0.5, -0.01),
        frameon=False,
    )
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    caption = (
        "As the paper's Figure 10: for every well, the absolute percentage error of each scored "
        "prediction is averaged per day and then over a rolling 14-day window; the line is the "
        "median across wells, the band P25 to P75 across wells. Thin vertical lines mark the "
        "periodic retrains of each PBL method in its colour (faint where there are many)."
    )
    if top is not None:
        caption += f" The y axis is shared and stops at {top:.0f}&nbsp;%."
    return title + _figure_html(fig, caption, "rolling error over time")


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


def _well_test_section(study: _Study) -> str:
    title = "<h2>Days between well tests</h2>\n"
    counts = _gap_counts(study.result.well_tests or {})
    if counts.empty:
        return title + "<p>No well has two or more well tests, so there are no gaps to show.</p>\n"
    cmap = plt.get_cmap("tab20b" if len(counts) > 10 else "tab10")
    fig, ax = plt.subplots(figsize=(9, 4.6))
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
    edges = ", ".join(f"{int(e)}" for e in _GAP_EDGES_DAYS[1:-1])
    caption = (
        "As the paper's Figure 12: how long the wells go between two tests over the whole data "
        f"set (training and test period). Bins have different widths; edges at {edges} days."
    )
    fig_html = _figure_html(fig, caption, "stacked histogram of days between well tests")
    pct = counts.div(counts.sum(axis=1), axis=0) * 100.0
    head = '<th class="label">Well</th><th>tests</th>' + "".join(
        f"<th>{_esc(b)}</th>" for b in _GAP_LABELS
    )
    body = []
    for well, row in pct.iterrows():
        n_tests = int(counts.loc[well].sum()) + 1
        cells = "".join(f"<td>{v:.1f}&nbsp;%</td>" for v in row.to_numpy(dtype=float))
        body.append(f'<tr><td class="label">{_esc(well)}</td><td>{n_tests}</td>{cells}</tr>')
    table = (
        "<table><caption>Share of the gaps between chronological well tests per well in each bin, "
        "as the paper's Table C3 (d = day, w = week, m = month, y = year).</caption>"
        f"<thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>\n"
    )
    return title + fig_html + table


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


def _rates_grid(study: _Study, model: str, heading: str, intro: str) -> str:
    p = study.preds
    sub = p[p["model"] == model]
    if sub.empty:
        return ""
    sub = sub.assign(time=pd.to_datetime(sub["time"], utc=True), well=sub["well"].astype(str))
    measured = sub.drop_duplicates(["time", "well", "source"]).sort_values("time")
    wells = [w for w in study.wells if (sub["well"] == w).any()]
    if not wells:
        return ""
    ncols = 1 if len(wells) == 1 else 2
    nrows = math.ceil(len(wells) / ncols)
    fig, axes = plt.subplots(
        nrows, ncols, figsize=(7.2 * ncols, 2.7 * nrows + 0.6), sharex=True, squeeze=False
    )
    n_series = len(study.methods) + 1
    per_series = max(200, _MAX_POINTS_PER_PANEL // n_series)
    any_clipped = False
    for ax, well in zip(axes.flat, wells, strict=False):
        meas = measured[measured["well"] == well]
        meas_q = pd.to_numeric(meas["measured"], errors="coerce").to_numpy(dtype=float)
        finite_meas = meas_q[np.isfinite(meas_q)]
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
        drawn = False
        clipped = False
        y_lo, y_hi = _rate_limits(finite_meas, sub.loc[sub["well"] == well, "predicted"])
        for meth in study.methods:
            g = sub[(sub["well"] == well) & (sub["method"] == meth)].sort_values("time")
            q = pd.to_numeric(g["predicted"], errors="coerce").to_numpy(dtype=float)
            ok = np.isfinite(q)
            if not ok.any():
                continue
            times = _naive_utc(g["time"]).to_numpy()[ok]
            q = q[ok]
            idx = _thin_index(len(q), per_series)
            line_t, line_q = _break_gaps(times[idx], q[idx])
            ax.plot(
                line_t,
                line_q,
                color=study.colours[meth],
                linewidth=0.9,
                alpha=0.85,
                zorder=3,
            )
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
    for ax in axes[-1, :]:
        ax.set_xlabel("time (UTC)")
        ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(ax.xaxis.get_major_locator()))
    if len(wells) % ncols and nrows > 1:
        axes[-2, -1].xaxis.set_tick_params(labelbottom=True)
        axes[-2, -1].set_xlabel("time (UTC)")
    handles = [
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
    ] + [
        Line2D([], [], color=study.colours[m], linewidth=2, label=f"predicted, {m}")
        for m in study.methods
    ]
    fig.suptitle(f"Predicted and measured total rate per well, model {model}", fontsize=12)
    fig.legend(
        handles=handles,
        loc="lower center",
        ncol=min(len(handles), 5),
        fontsize=8,
        bbox_to_anchor=(0.5, -0.01),
        frameon=False,
    )
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    caption = (
        f"{intro} Test period only. Long series are thinned evenly for drawing (at most "
        f"{per_series} points per series); every well test is shown."
    )
    if any_clipped:
        caption += (
            " The y axis follows the measured rates; predictions far outside them are cut off."
        )
    return f"<h2>{heading}</h2>\n" + _figure_html(
        fig, caption, f"predicted and measured rates, {model}"
    )


def _rates_section(study: _Study) -> str:
    best = study.best_model()
    if best is None:
        return ""
    intro = (
        f"Model <b>{_esc(best)}</b> ({_esc(_model_label(best))}) is shown because it has the "
        "lowest mean MAPE of the non-benchmark models, averaged over the learning methods."
    )
    out = _rates_grid(
        study, best, f"Predicted and measured rates: {_esc(best)} (best model)", intro
    )
    if "mm" in study.models and best != "mm":
        out += _rates_grid(
            study,
            "mm",
            "Predicted and measured rates: mm (mechanistic model)",
            "The mechanistic model <b>mm</b>, whose parameters have a physical meaning.",
        )
    return out


def _parameter_section(study: _Study) -> str:
    params = study.result.parameters
    if params is None or not isinstance(params, pd.DataFrame) or params.empty:
        return ""
    needed = {"time", "well", "model", "method", "name", "value"}
    if not needed.issubset(params.columns):
        return ""
    cd = params[(params["model"].astype(str) == "mm") & (params["name"].astype(str) == "c_d")]
    cd = cd.assign(value=pd.to_numeric(cd["value"], errors="coerce")).dropna(subset=["value"])
    if cd.empty:
        return ""
    cd = cd.assign(time=pd.to_datetime(cd["time"], utc=True), well=cd["well"].astype(str))
    wells = sorted(cd["well"].unique(), key=_natural_key)
    methods = [m for m in study.methods if (cd["method"] == m).any()]
    methods += [m for m in dict.fromkeys(cd["method"].astype(str)) if m not in methods]
    colours = {m: study.colours.get(m, "#555") for m in methods}
    ncols = 1 if len(wells) == 1 else 2
    nrows = math.ceil(len(wells) / ncols)
    fig, axes = plt.subplots(
        nrows, ncols, figsize=(7.2 * ncols, 2.5 * nrows + 0.6), sharex=True, squeeze=False
    )
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
    for ax in axes[-1, :]:
        ax.set_xlabel("time (UTC)")
        ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(ax.xaxis.get_major_locator()))
    if len(wells) % ncols and nrows > 1:
        axes[-2, -1].xaxis.set_tick_params(labelbottom=True)
        axes[-2, -1].set_xlabel("time (UTC)")
    handles = [Line2D([], [], color=colours[m], linewidth=2, label=m) for m in methods]
    fig.suptitle(
        "Discharge coefficient C_D of the mechanistic model mm after each update", fontsize=12
    )
    fig.legend(
        handles=handles,
        loc="lower center",
        ncol=min(len(handles), 5),
        fontsize=8,
        title="learning method",
        title_fontsize=8,
        bbox_to_anchor=(0.5, -0.01),
        frameon=False,
    )
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    caption = (
        "The estimated discharge coefficient per well over the test period, one line per learning "
        "method (held constant between updates). Online learning moves it with every measurement; "
        "periodic batch learning only at its retrains. A drifting C_D absorbs changes the model "
        "does not describe (e.g. erosion or a changed choke characteristic)."
    )
    return "<h2>Discharge coefficient over time (mm)</h2>\n" + _figure_html(
        fig, caption, "discharge coefficient over time"
    )


# --------------------------------------------------------------------------- entry point


def build_report(result: StudyResult, path: Path) -> Path:
    """Write the study as one self-contained HTML file at ``path`` and return the path.

    Figures are PNG embedded as base64; nothing is loaded from outside the file. Text taken
    from the data (well, model and method names, the data path) is HTML-escaped.
    """
    path = Path(path)
    study = _Study(result)
    scored = study.scored()
    # Names from the data go into figure text too: never read them as mathtext ($...$).
    with plt.rc_context({"text.parse_math": False}):
        sections = [
            _header(study),
            _summary_text(study),
            _mean_table(study),
            _well_table(study),
            _box_plot(study),
            _rolling_plot(study, scored),
            _well_test_section(study),
            _rates_section(study),
            _parameter_section(study),
        ]
    page = (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>VFM study report: {_esc(result.targets)}, "
        f"split {_esc(pd.Timestamp(result.split).date())}</title>\n"
        f"<style>{_CSS}</style>\n</head>\n<body>\n" + "".join(sections) + "</body>\n</html>\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(page, encoding="utf-8")
    return path
