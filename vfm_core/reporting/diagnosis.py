"""The diagnosis report: one self-contained HTML page of what ``vfm diagnose`` found.

Owns how a :class:`vfm_core.jobs.diagnose_results.Diagnosis` is shown: the verdict with one
baseline and one "with" figure under one protocol, the before/after panel of the top
candidate (its residual against the variable it acts through, without and with it), the
suggested correction with its code, the candidates and their fitted parameters (with
uncertainty and bound warnings), the drivers of the residual and their per-well panels,
where the model fails in operation, and the model with ``--effects`` before and after.
The numbers come from the diagnosis; this module only draws the figures and hands
everything to ``templates/diagnosis.html.j2`` on the shared layout of
:mod:`vfm_core.reporting.page`, which escapes every text taken from the data (well, model
and effect names, the fitted meaning).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from vfm_core.jobs.diagnose_rivals import trend_proxy_text, why_explained
from vfm_core.jobs.diagnose_stats import CLIP, UNITS, detrend, driver_values
from vfm_core.jobs.study import mape
from vfm_core.reporting import page
from vfm_core.reporting.page import Png

if TYPE_CHECKING:
    from vfm_core.jobs.diagnose_results import CandidateResult, Diagnosis

__all__ = ["build_report"]

#: Most residuals drawn as dots per panel (the binned lines use all of them).
_MAX_POINTS = 4000
#: Most wells drawn in the per-well panels (the ones with the most measurements).
_MAX_WELLS = 12
_BASE_COLOUR = "#1f77b4"
_EXTENDED_COLOUR = "#d62728"


def _numeric_drivers(res: pd.DataFrame, variables: tuple[str, ...]) -> list[str]:
    """The driver variables with an axis: time, the season and every numeric column (not
    well, source, flow regime)."""
    return [
        v
        for v in variables
        if v in ("time", "day_of_year")
        or (v in res.columns and pd.api.types.is_numeric_dtype(res[v]))
    ]


def _x(res: pd.DataFrame, name: str) -> np.ndarray:
    """A variable's values for an axis: naive UTC datetimes for time, else numbers."""
    if name == "time":
        return pd.DatetimeIndex(res["time"]).tz_convert(None).to_numpy()
    return np.asarray(driver_values(res, name), dtype=float)


def _trend(x: np.ndarray, r: np.ndarray, bins: int = 14) -> tuple[np.ndarray, ...]:
    """Binned median and P25-P75 of r against x on quantile bins (x numeric or datetime)."""
    is_time = np.issubdtype(x.dtype, np.datetime64)
    xf = x.astype("datetime64[ns]").astype("int64").astype(float) if is_time else x
    ok = np.isfinite(xf) & np.isfinite(r)
    xf, r = xf[ok], r[ok]
    edges = np.unique(np.quantile(xf, np.linspace(0, 1, bins + 1))) if len(xf) else np.array([])
    centres, med, lo, hi = [], [], [], []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        sel = (xf >= a) & ((xf < b) | (b == edges[-1]))
        if sel.sum() < 5:
            continue
        centres.append(float(np.median(xf[sel])))
        q25, q50, q75 = np.percentile(r[sel], [25, 50, 75])
        med.append(q50)
        lo.append(q25)
        hi.append(q75)
    c = np.array(centres)
    if is_time:
        c = c.astype("int64").astype("datetime64[ns]")
    return c, np.array(med), np.array(lo), np.array(hi)


def _label(ax: Axes, name: str, unit: str) -> None:
    if name == "time":
        page.date_axis(ax)
        ax.set_xlabel("time", fontsize=8)
    else:
        ax.set_xlabel(f"{name} [{unit}]", fontsize=8)
    ax.tick_params(labelsize=7)


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
    fig = Figure(figsize=(4.0 * cols, 2.9 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    rng = np.random.default_rng(0)
    thin = rng.permutation(len(res))[:_MAX_POINTS]
    r = 100 * np.clip(res["r"].to_numpy(dtype=float), -CLIP, CLIP)
    lim = float(np.nanpercentile(np.abs(r), 98)) if len(r) else 10.0
    for ax, name in zip(axes.flat, names, strict=False):
        x = _x(res, name)
        ax.scatter(x[thin], r[thin], s=2, alpha=0.25, color="#888")
        c, m, lo, hi = _trend(x, r)
        ax.fill_between(c, lo, hi, color=_BASE_COLOUR, alpha=0.25, label="base P25-P75")
        ax.plot(c, m, color=_BASE_COLOUR, lw=2, label="base median")
        if extended is not None:
            re_ = 100 * np.clip(extended["r"].to_numpy(dtype=float), -CLIP, CLIP)
            c2, m2, lo2, hi2 = _trend(x, re_)
            ax.fill_between(c2, lo2, hi2, color=_EXTENDED_COLOUR, alpha=0.15)
            ax.plot(c2, m2, color=_EXTENDED_COLOUR, lw=2, label="extended median")
        ax.axhline(0, color="k", lw=0.6)
        ax.set_ylim(-1.2 * lim, 1.2 * lim)
        _label(ax, name, units.get(name, UNITS.get(name, "-")))
        ax.set_ylabel("residual %", fontsize=8)
        ax.set_title(f"{name}: R2 beyond trends {score.get(name, float('nan')):.3f}", fontsize=9)
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
            g = frame_[frame_["well"] == well].set_index("time")["r"].clip(-CLIP, CLIP) * 100
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
        err = (100 * (frame_["r"].abs().clip(upper=CLIP))).to_numpy()
        s = pd.Series(err, index=pd.DatetimeIndex(frame_["time"]).tz_convert(None)).sort_index()
        ax.plot(s.rolling("14D").mean(), color=colour, label=label, lw=1.2)
    ax.set_ylabel("14-day rolling MAPE %")
    page.date_axis(ax)
    ax.legend()
    fig.tight_layout()
    return page.png(fig)


def _before_after(
    res: pd.DataFrame, with_res: pd.DataFrame, driver: str, name: str, floor: float | None
) -> Png:
    """The top candidate's panel: the residual against the variable it acts through and over
    time, without (blue) and with it (red); the noise floor as a band of +-floor."""
    fig = Figure(figsize=(11, 3.4))
    axes = fig.subplots(1, 2)
    panels = [(driver, UNITS.get(driver, "-"))]
    if driver != "time":
        panels.append(("time", "date"))
    r0 = 100 * np.clip(res["r"].to_numpy(dtype=float), -CLIP, CLIP)
    r1 = 100 * np.clip(with_res["r"].to_numpy(dtype=float), -CLIP, CLIP)
    lim = float(np.nanpercentile(np.abs(r0), 95)) if len(r0) else 10.0
    for ax, (var, unit) in zip(axes, panels, strict=False):
        x = _x(res, var)
        for r, colour, label in (
            (r0, _BASE_COLOUR, "without"),
            (r1, _EXTENDED_COLOUR, f"with {name}"),
        ):
            c, m, lo, hi = _trend(x, r, bins=16)
            ax.fill_between(c, lo, hi, color=colour, alpha=0.18)
            ax.plot(c, m, color=colour, lw=2, label=f"{label}: median, P25-P75")
        if floor is not None:
            ax.axhspan(-floor, floor, color="#bbb", alpha=0.25, lw=0, label="+- noise floor (MAPE)")
        ax.axhline(0, color="k", lw=0.6)
        ax.set_ylim(-1.3 * lim, 1.3 * lim)
        ax.set_ylabel("residual %", fontsize=8)
        _label(ax, var, unit)
    for ax in list(axes)[len(panels) :]:
        ax.axis("off")
    axes[0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return page.png(fig)


def _per_well_drivers(res: pd.DataFrame, names: list[str]) -> Png:
    """Per well (rows) the residual after its straight line in time against each top
    driver (columns): what the drivers' scores measure."""
    r_d = 100 * detrend(res)
    counts = res["well"].value_counts()
    wells = sorted(counts.index[:_MAX_WELLS])
    fig = Figure(figsize=(3.6 * len(names), 1.9 * len(wells) + 0.4))
    axes = fig.subplots(len(wells), len(names), squeeze=False, sharey=True)
    lim = float(np.nanpercentile(np.abs(r_d), 97)) if len(r_d) else 10.0
    for i, well in enumerate(wells):
        sel = (res["well"] == well).to_numpy()
        sub = res[sel]
        for j, name in enumerate(names):
            ax = axes[i, j]
            x = _x(sub, name)
            y = r_d[sel]
            ax.scatter(x, y, s=2, alpha=0.25, color="#888")
            c, m, _, _ = _trend(x, y, bins=8)
            ax.plot(c, m, color=_BASE_COLOUR, lw=1.8)
            ax.axhline(0, color="k", lw=0.5)
            ax.set_ylim(-1.2 * lim, 1.2 * lim)
            ax.tick_params(labelsize=7)
            if i == 0:
                ax.set_title(name, fontsize=9)
            if i == len(wells) - 1:
                _label(ax, name, UNITS.get(name, "-"))
            if j == 0:
                ax.set_ylabel(f"{well}\nresidual %", fontsize=8)
    fig.tight_layout()
    return page.png(fig)


def _comparison_residuals(diag: Diagnosis, cand: CandidateResult) -> pd.DataFrame | None:
    if cand.run is None or diag.comparison_residuals is None:
        return None
    return diag.residuals_of(cand.run, diag.comparison_residuals)


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


def _parameter_rows(diag: Diagnosis) -> list[dict[str, Any]]:
    """One row per fitted effect parameter of every candidate (and the suggestion)."""
    rows = []
    results = list(diag.candidates)
    if diag.suggestion is not None:
        results.append(diag.suggestion.result)
    for c in results:
        for key, p in c.parameters.items():
            per_well = p.get("per_well") or {}
            values = [v for v in per_well.values() if math.isfinite(v)]
            rows.append(
                {
                    "candidate": c.spec if c.effect.startswith("suggest") else c.effect,
                    "parameter": key.split(".", 1)[-1],
                    "value": p.get("value"),
                    "sd": p.get("sd"),
                    "unit": p.get("unit", ""),
                    "range": (
                        f"{min(values):.3g} .. {max(values):.3g}" if len(values) > 1 else "shared"
                    ),
                    "meaning": p.get("meaning", ""),
                }
            )
    return rows


def _replay_context(diag: Diagnosis) -> dict[str, Any]:
    """The live and outage tables: one row per replayed candidate (the field's tests, or the
    diagnosed well's with a pool), and the per-well panel."""
    if not getattr(diag, "live", None):
        return {"replay": [], "per_well": [], "replay_top": 0}
    focus = diag.pool.get("focus")
    rows = []
    cands = [c for c in diag.candidates if c.replayed]
    if diag.suggestion is not None and diag.suggestion.result.replayed:
        cands.append(diag.suggestion.result)
    empty = {"change": None, "low": None, "high": None, "p_value": None, "q_value": None}
    for c in cands:
        rows.append(
            {
                "effect": c.spec or c.effect,
                "live": {**empty, **(c.test("live", focus) or {})},
                "outage": {**empty, **(c.test("outage") or {})},
                "offer": "yes" if c.offer else ("no: raises the error" if c.raises_error else "no"),
                "candidate": c,
            }
        )
    per_well = []
    wells = diag.pool.get("wells") or []
    if len(wells) > 1:
        for w in wells:
            v = diag.well_verdicts.get(w, {})
            cells = [{**empty, **(c.test("live", w) or {})} for c in cands]
            per_well.append(
                {
                    "well": w + (" (diagnosed)" if w == focus else ""),
                    "mape": diag.live.get("per_well", {}).get(w, {}).get("mape"),
                    "cells": cells,
                    "verdict": " ".join(
                        x
                        for x in (
                            v.get("kind"),
                            v.get("effect")
                            or v.get("driver")
                            or (v.get("instrument") or {}).get("sensor"),
                        )
                        if x
                    ),
                }
            )
    return {"replay": rows, "per_well": per_well, "replay_top": len(cands)}


def build_report(diag: Diagnosis, path: Path) -> Path:
    """Write the diagnosis as one self-contained HTML page at ``path`` (PNG figures inline,
    written atomically) and return the path."""
    res = diag.residuals
    comp = diag.comparison_residuals
    floor = diag.floor.get("mape") if diag.floor else None
    # Names from the data go into figure text too: never read them as mathtext ($...$).
    with matplotlib.rc_context({"text.parse_math": False}):
        extended, ext_res = _extended(diag)
        top = diag.with_effect
        before_after = None
        if top is not None and comp is not None:
            with_res = _comparison_residuals(diag, top)
            driver = top.driver or next(
                (d["name"] for d in diag.drivers if d.get("role") == "driver"), "time"
            )
            if with_res is not None:
                before_after = {
                    "name": top.spec or top.effect,
                    "effect": top.effect,
                    "driver": driver,
                    "png": _before_after(comp, with_res, driver, top.effect, floor),
                }
        per_well_png = None
        top_drivers = [d["name"] for d in diag.drivers if d.get("role") == "driver"][:3]
        if comp is not None and top_drivers:
            per_well_png = _per_well_drivers(comp, top_drivers)
        grid_source = comp if comp is not None else res
        context = {
            "diag": diag,
            "headline": diag.headline,
            "n_scored": len(res),
            "material": {
                "mape_abs": diag.material_rule["mape_abs"],
                "mape_rel_pct": 100 * diag.material_rule["mape_rel"],
                "bic": diag.material_rule["bic"],
                "near_floor": diag.material_rule.get("near_floor", 0.1),
                "share_pct": 100 * diag.material_rule.get("share", 1 / 3),
            },
            "candidates": diag.candidates,
            "why_explained": why_explained,
            "trend_proxy_text": trend_proxy_text,
            "parameters": _parameter_rows(diag),
            "drivers": diag.drivers,
            "top_drivers": top_drivers,
            "suggestion": diag.suggestion,
            "before_after": before_after,
            "per_well_drivers": per_well_png,
            "extended": extended,
            "residual_grid": _residual_grid(
                grid_source, diag.drivers, diag.driver_variables, ext_res if comp is None else None
            ),
            "time_grid": _time_grid(res, ext_res),
            **_replay_context(diag),
        }
    return page.write_page(path, page.render("diagnosis.html.j2", **context))
