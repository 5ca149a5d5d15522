"""The diagnosis report: one self-contained HTML page of what ``vfm diagnose`` found.

Owns how a :class:`vfm_core.jobs.diagnose.Diagnosis` is shown: the verdict, where the model
fails, the candidate effects and the drivers of the residual as tables, the model with
``--effects`` before and after, and figures of the residual against each variable, over
time per well and by region. The numbers come from the diagnosis; this module only draws
the figures and hands everything to ``templates/diagnosis.html.j2`` on the shared layout
of :mod:`vfm_core.reporting.page`, which escapes every text taken from the data (well,
model and effect names, the fitted meaning).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from vfm_core.jobs.study import mape
from vfm_core.reporting import page
from vfm_core.reporting.page import Png

if TYPE_CHECKING:
    from vfm_core.jobs.diagnose import Diagnosis

__all__ = ["build_report"]

#: Most residuals drawn as dots per panel (the binned lines use all of them).
_MAX_POINTS = 4000
#: Relative residuals are drawn clipped to +-100 %, as the diagnosis clips them for its
#: scores: one diverged prediction must not set the scale.
_CLIP = 1.0
_BASE_COLOUR = "#1f77b4"
_EXTENDED_COLOUR = "#d62728"


def _decimal_years(times: pd.Series) -> np.ndarray:
    """UTC times as calendar years with a fraction (2019.5 is early July 2019)."""
    t = pd.to_datetime(times, utc=True)
    epoch = pd.Timestamp("1970-01-01", tz="UTC")
    return 1970.0 + ((t - epoch) / pd.Timedelta(days=365.25)).to_numpy(dtype=float)


def _numeric_drivers(res: pd.DataFrame, variables: tuple[str, ...]) -> list[str]:
    """The driver variables with an axis: time and every numeric column (not well, source,
    flow regime)."""
    return [
        v
        for v in variables
        if v == "time" or (v in res.columns and pd.api.types.is_numeric_dtype(res[v]))
    ]


def _trend(x: np.ndarray, r: np.ndarray, bins: int = 14) -> tuple[np.ndarray, ...]:
    """Binned median and P25-P75 of r against x on quantile bins."""
    ok = np.isfinite(x) & np.isfinite(r)
    x, r = x[ok], r[ok]
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1))) if len(x) else np.array([])
    centres, med, lo, hi = [], [], [], []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        sel = (x >= a) & ((x < b) | (b == edges[-1]))
        if sel.sum() < 5:
            continue
        centres.append(float(np.median(x[sel])))
        q25, q50, q75 = np.percentile(r[sel], [25, 50, 75])
        med.append(q50)
        lo.append(q25)
        hi.append(q75)
    return np.array(centres), np.array(med), np.array(lo), np.array(hi)


def _residual_grid(
    res: pd.DataFrame,
    drivers: list[dict[str, Any]],
    variables: tuple[str, ...],
    extended: pd.DataFrame | None = None,
) -> Png:
    """The residual against each numeric driver variable, base (and extended) model."""
    score = {d["name"]: d["score"] for d in drivers}
    units = {d["name"]: d.get("unit", "-") for d in drivers}
    names = _numeric_drivers(res, variables)
    cols = 4
    rows = math.ceil(len(names) / cols)
    fig = Figure(figsize=(4.0 * cols, 2.8 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    rng = np.random.default_rng(0)
    thin = rng.permutation(len(res))[:_MAX_POINTS]
    r = 100 * np.clip(res["r"].to_numpy(dtype=float), -_CLIP, _CLIP)
    for ax, name in zip(axes.flat, names, strict=False):
        x = _decimal_years(res["time"]) if name == "time" else res[name].to_numpy(dtype=float)
        ax.scatter(x[thin], r[thin], s=2, alpha=0.25, color="#888")
        c, m, lo, hi = _trend(x, r)
        ax.fill_between(c, lo, hi, color=_BASE_COLOUR, alpha=0.25, label="base P25-P75")
        ax.plot(c, m, color=_BASE_COLOUR, lw=2, label="base median")
        if extended is not None:
            re_ = 100 * np.clip(extended["r"].to_numpy(dtype=float), -_CLIP, _CLIP)
            c2, m2, lo2, hi2 = _trend(x, re_)
            ax.fill_between(c2, lo2, hi2, color=_EXTENDED_COLOUR, alpha=0.15)
            ax.plot(c2, m2, color=_EXTENDED_COLOUR, lw=2, label="extended median")
        ax.axhline(0, color="k", lw=0.6)
        lim = np.nanpercentile(np.abs(r), 98) if len(r) else 10
        ax.set_ylim(-1.2 * lim, 1.2 * lim)
        label = "time (calendar year)" if name == "time" else f"{name} [{units.get(name, '-')}]"
        ax.set_xlabel(label, fontsize=8)
        ax.set_ylabel("residual %", fontsize=8)
        ax.set_title(f"{name}: R2 out of sample {score.get(name, float('nan')):.2f}", fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    return page.png(fig)


def _time_grid(res: pd.DataFrame, extended: pd.DataFrame | None = None) -> Png:
    """The residual over time per well: 14-day median and P25-P75."""
    wells = sorted(res["well"].unique())
    cols = min(3, len(wells))
    rows = math.ceil(len(wells) / cols)
    fig = Figure(figsize=(5.0 * cols, 2.4 * rows))
    axes = fig.subplots(rows, cols, squeeze=False, sharey=True)
    for ax, well in zip(axes.flat, wells, strict=False):
        for frame_, colour, label in (
            (res, _BASE_COLOUR, "base"),
            (extended, _EXTENDED_COLOUR, "extended"),
        ):
            if frame_ is None:
                continue
            g = frame_[frame_["well"] == well].set_index("time")["r"].clip(-_CLIP, _CLIP) * 100
            if g.empty:
                continue
            g.index = g.index.tz_convert(None)
            fortnight = g.resample("14D")
            median = fortnight.median()
            ax.plot(median.index, median.to_numpy(), color=colour, lw=1.5, label=label)
            ax.fill_between(
                median.index,
                fortnight.quantile(0.25).to_numpy(),
                fortnight.quantile(0.75).to_numpy(),
                color=colour,
                alpha=0.2,
            )
        ax.axhline(0, color="k", lw=0.6)
        ax.set_title(well, fontsize=9)
        ax.tick_params(labelsize=7)
        page.date_axis(ax)
    for ax in list(axes.flat)[len(wells) :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    axes.flat[0].set_ylabel("residual %", fontsize=8)
    fig.tight_layout()
    return page.png(fig)


def _rolling_plot(base: pd.DataFrame, ext: pd.DataFrame, name: str) -> Png:
    """The 14-day rolling MAPE over all wells, base model against extended model."""
    fig = Figure(figsize=(10, 3))
    ax = fig.subplots()
    for frame_, colour, label in ((base, _BASE_COLOUR, "base"), (ext, _EXTENDED_COLOUR, name)):
        err = (100 * (frame_["r"].abs().clip(upper=_CLIP))).to_numpy()
        s = pd.Series(err, index=pd.DatetimeIndex(frame_["time"]).tz_convert(None)).sort_index()
        ax.plot(s.rolling("14D").mean(), color=colour, label=label, lw=1.2)
    ax.set_ylabel("14-day rolling MAPE %")
    page.date_axis(ax)
    ax.legend()
    fig.tight_layout()
    return page.png(fig)


def _extended(diag: Diagnosis) -> tuple[dict[str, Any] | None, pd.DataFrame | None]:
    """The before-and-after section of ``--effects`` and the extended model's residuals."""
    e = diag.extended
    if e is None or e.run is None:
        return None, None
    res = diag.residuals
    ext_res = diag.residuals_of(e.run)
    per_well = []
    for well, g in res.groupby("well"):
        h = ext_res[ext_res["well"] == well]
        per_well.append(
            {
                "well": well,
                "before": mape(g["predicted"], g["measured"]),
                "after": mape(h["predicted"], h["measured"]),
            }
        )
    section = {
        "effect": e.effect,
        "mape": e.mape,
        "delta_mape": e.delta_mape,
        "delta_bic": e.delta_bic,
        "meaning": e.meaning,
        "per_well": per_well,
        "rolling": _rolling_plot(res, ext_res, e.effect),
    }
    return section, ext_res


def build_report(diag: Diagnosis, path: Path) -> Path:
    """Write the diagnosis as one self-contained HTML page at ``path`` (PNG figures inline,
    written atomically) and return the path."""
    res = diag.residuals
    # Names from the data go into figure text too: never read them as mathtext ($...$).
    with matplotlib.rc_context({"text.parse_math": False}):
        extended, ext_res = _extended(diag)
        context = {
            "diag": diag,
            "n_scored": len(res),
            "material": {
                "mape_abs": diag.material_rule["mape_abs"],
                "mape_rel_pct": 100 * diag.material_rule["mape_rel"],
                "bic": diag.material_rule["bic"],
            },
            "candidates": [c.to_json() for c in diag.candidates],
            "extended": extended,
            "residual_grid": _residual_grid(res, diag.drivers, diag.driver_variables, ext_res),
            "time_grid": _time_grid(res, ext_res),
        }
    return page.write_page(path, page.render("diagnosis.html.j2", **context))
