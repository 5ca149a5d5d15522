"""``vfm drift DATA --out DIR``: Algorithm A.1 per well, and the T^2 statistic over time.

For each well, the reference window is the first part of its data before the split
(``--reference``, a fraction); every later observation is tested against it with the
single-observation Hotelling test. The first confirmed shift in the training data gives
the estimated retraining period (paper appendix A); the statistic over the whole history
is plotted with detections coloured, as in the paper's Hotelling T^2 figures.
Outputs: ``DIR/drift.json`` (periods per well) and ``DIR/report.html``.
"""

from __future__ import annotations

import argparse
import base64
import html
import io
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from vfm_core.data import target_mask
from vfm_core.drift import estimate_update_period
from vfm_core.schema import INPUT_COLUMNS, TIME, WELL
from vfm_core.jobs.study import resolve_split

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


def _figure(result: dict[str, Any]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    wells = [(w, e) for w, e in result["wells"].items() if e.get("t2")]
    if not wells:
        return ""
    cols = 2
    rows = (len(wells) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(12, 2.6 * rows), squeeze=False, sharey=False)
    split = (
        pd.Timestamp(result["split"]).tz_localize(None)
        if pd.Timestamp(result["split"]).tzinfo
        else pd.Timestamp(result["split"])
    )
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
                pd.Timestamp(e["first_shift"]),
                color="#ff7f0e",
                lw=1.2,
                label="first confirmed shift",
            )
        ax.set_yscale("log")
        ax.set_title(f"{well}: Hotelling T² vs reference window", fontsize=9)
        ax.set_ylabel("T² (-)")
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(wells) :]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7, loc="upper left", markerscale=3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def write_drift(result: dict[str, Any], out: Path, data_path: str) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    tmp_json = out / ".drift.json.tmp"
    tmp_json.write_text(json.dumps(result, indent=1))
    rows = []
    for well, e in result["wells"].items():
        period = "-" if e.get("period_days") is None else f"{e['period_days']:.0f}"
        share = (
            "-"
            if e.get("share_detected_after_split") is None
            else f"{100 * e['share_detected_after_split']:.0f} %"
        )
        rows.append(
            f"<tr><td>{html.escape(well)}</td><td>{e.get('n_train', 0)}</td><td>{period}</td>"
            f"<td>{html.escape(str(e.get('first_shift') or e.get('error') or 'none'))}</td><td>{share}</td></tr>"
        )
    img = _figure(result)
    med = result["median_period_days"]
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>VFM drift report</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:auto}}td,th{{padding:2px 8px;border-bottom:1px solid #ddd}}</style></head><body>
<h1>Input drift: Hotelling T² (paper appendix A)</h1>
<p>Data: {html.escape(data_path)}; targets {html.escape(result["targets"])}; split {html.escape(result["split"][:10])};
alpha {result["alpha"]}; a shift is confirmed after {result["confirm"]} consecutive detections; reference window:
the first {100 * result["reference_fraction"]:.0f} % of each well's observations before the split.</p>
<p>Median estimated retraining period across wells: <b>{"-" if med is None else f"{med:.0f} days"}</b>.
A short period means the inputs left the region the model was trained on quickly; retrain such wells often
(or use <code>pbl:auto</code>).</p>
<table><tr><th>well</th><th>observations before split</th><th>estimated period (days)</th><th>first confirmed shift</th>
<th>share of observations after the split flagged</th></tr>{"".join(rows)}</table>
{f'<img alt="T2 over time per well" src="data:image/png;base64,{img}" style="max-width:100%">' if img else ""}
</body></html>"""
    tmp_html = out / ".report.html.tmp"
    tmp_html.write_text(page)
    os.replace(tmp_json, out / "drift.json")
    os.replace(tmp_html, out / "report.html")
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
