"""What ``vfm diagnose`` writes: ``diagnosis.json`` (and ``report.html``, drawn by
:mod:`vfm_core.reporting.diagnosis`), each atomically, and the summary it prints.

Exported from :mod:`vfm_core.jobs.diagnose` as before; no dependency on it.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from vfm_core.jobs.diagnose_results import Diagnosis

__all__ = ["json_safe", "write_diagnosis", "format_summary"]


def json_safe(obj: Any) -> Any:
    """``obj`` as plain JSON values: keys as text, numpy numbers as Python ones, a float
    that is not finite as None (``diagnosis.json`` has no NaN)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def write_diagnosis(
    diag: Diagnosis, out_dir: str | os.PathLike[str], *, report: bool = True
) -> list[Path]:
    """Write ``diagnosis.json`` (and ``report.html``) into ``out_dir``, each atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    staging = out / f".diagnose-staging-{os.getpid()}"
    staging.mkdir(exist_ok=True)
    written: list[Path] = []
    try:
        (staging / "diagnosis.json").write_text(
            json.dumps(json_safe(diag.to_json()), indent=2, allow_nan=False) + "\n",
            encoding="utf-8",
        )
        names = ["diagnosis.json"]
        if report:
            # Imported here: matplotlib and the templates are only needed for the report.
            from vfm_core.reporting.diagnosis import build_report

            build_report(diag, staging / "report.html")
            names.append("report.html")
        for name in names:
            os.replace(staging / name, out / name)
            written.append(out / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return written


def format_summary(diag: Diagnosis) -> str:
    """The diagnosis in a few lines for the terminal: the verdict, the headline, the live
    protocol, the drivers and the candidates."""
    h = diag.headline
    lines = [f"Verdict ({diag.verdict_kind}): {diag.verdict}"]
    with_text = f"; with {h['with']}: {h['with_mape']:.2f} %" if h["with_mape"] is not None else ""
    floor = f"; noise floor {h['floor_mape']:.2f} %" if h["floor_mape"] is not None else ""
    lines.append(
        f"Headline ({diag.candidate_method}): baseline {diag.model_label} MAPE "
        f"{diag.candidate_baseline_mape:.2f} %{with_text}{floor}."
    )
    lines.append(
        f"Online ({diag.method}, {diag.targets}): MAPE {diag.baseline_mape:.2f} % on "
        f"{len(diag.residuals):,} observations (where it fails in operation)."
    )
    if diag.live:
        lines += _live_lines(diag)
    lines.append(
        "Drivers beyond per-well trends (out-of-sample R^2, p): "
        + ", ".join(
            f"{d['name']} {d['score']:.3f}"
            + (f" (p {d['p_value']:.3f})" if d["p_value"] is not None else "")
            for d in diag.drivers[:5]
        )
    )
    lines.append(
        f"Candidates (dBIC on the {diag.bic_on}; dBIC all on every measurement; * material):"
    )
    for c in diag.candidates:
        flag = " *" if c.material else ""
        lines.append(
            f"  {c.effect:<24} MAPE {c.mape:6.2f} %  dMAPE {c.delta_mape:+6.2f}  dBIC {c.delta_bic:+9.1f}"
            f"  dBIC all {c.delta_bic_all:+9.1f}{flag}"
        )
    for skip in diag.skipped:
        lines.append(f"  {skip['effect']:<24} skipped: {skip['reason']}")
    if diag.suggestion is not None:
        sug = diag.suggestion
        lines.append(
            f"Suggested correction: {sug.text}; MAPE {sug.mape:.2f} % "
            f"(dBIC {sug.result.delta_bic:+.1f}); --effects {sug.spec}"
        )
    if diag.extended is not None:
        e = diag.extended
        lines.append(
            f"With --effects {e.effect}: MAPE {e.mape:.2f} % (dMAPE {e.delta_mape:+.2f}, dBIC {e.delta_bic:+.1f})."
        )
    lines += diag.notes
    return "\n".join(lines)


def _live_lines(diag: Diagnosis) -> list[str]:
    """The summary's lines of the replay: the live and outage baselines, the replayed
    candidates' changes, and each well's verdict."""
    lines: list[str] = []
    out = (
        f"; in {diag.outage['label']} outages {diag.outage['mape']:.2f} % on "
        f"{diag.outage['n']:,} measurements"
        if diag.outage
        else ""
    )
    service = (
        f"; the service recorded {diag.live['service_mape']:.2f} %"
        if diag.live.get("service_mape") is not None
        else ""
    )
    lines.append(f"Live ({diag.method} replayed): MAPE {diag.live['mape']:.2f} %{service}{out}.")
    lines.append(f"False discoveries: {diag.fdr['procedure']}.")
    lines.append("Replayed candidates (change of the error, points, 95 % interval, q):")
    focus = diag.pool.get("focus")
    shown = [c for c in diag.candidates if c.replayed]
    if diag.suggestion is not None and diag.suggestion.result.replayed:
        shown.append(diag.suggestion.result)
    for c in shown:
        parts = []
        for proto in ("live", "outage"):
            t = c.test(proto, focus if proto == "live" else None)
            if t and t.get("change") is not None:
                parts.append(
                    f"{proto} {t['change']:+.2f} [{t['low']:+.2f}, {t['high']:+.2f}] "
                    f"q {t.get('q_value', float('nan')):.3g}"
                )
        t = c.test("trial", focus)
        if t and t.get("change") is not None:
            interval = f" [{t['low']:+.2f}, {t['high']:+.2f}]" if t.get("low") is not None else ""
            parts.append(f"trial forecast {t['change']:+.2f}{interval}")
        flag = "offered" if c.offer else ("raises the error" if c.raises_error else "not offered")
        lines.append(f"  {(c.spec or c.effect):<24} " + "; ".join(parts) + f"  ({flag})")
    if len(diag.pool.get("wells") or []) > 1:
        lines.append(
            "Each well's verdict: "
            + ", ".join(
                f"{w} {v['kind']}"
                + (f" {v['effect'] or v['driver']}" if v["effect"] or v["driver"] else "")
                for w, v in diag.well_verdicts.items()
            )
        )
    return lines
