"""What a study produces, in memory: :class:`StudyResult`.

Its own module, below both the job that makes it (:mod:`vfm_core.jobs.evaluate`) and the
report that draws it (:mod:`vfm_core.reporting.study`), so neither imports the other for
its type. It needs pandas only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pandas as pd

__all__ = ["StudyResult"]


@dataclass
class StudyResult:
    """Everything one study produced; :func:`vfm_core.jobs.evaluate.write_study` turns it into files."""

    split: pd.Timestamp
    targets: str
    records: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    predictions: pd.DataFrame
    #: times of periodic retrains per method (the same for every model)
    updates: dict[str, list[pd.Timestamp]]
    #: well-test times per well, from the data (for the days-between-tests view)
    well_tests: dict[str, list[pd.Timestamp]]
    runtime_s: float
    #: physical parameter traces (time, well, model, method, name, value), may be empty
    parameters: pd.DataFrame = field(default_factory=pd.DataFrame)
    data_path: str = ""
    #: the outage protocol's scored rows (inside the windows), with ``outage`` and
    #: ``days_since``; empty without outages
    outage_predictions: pd.DataFrame = field(default_factory=pd.DataFrame)
    #: every outage window (outage, well, start, end, rows); empty without outages
    outage_windows: pd.DataFrame = field(default_factory=pd.DataFrame)
    #: the outage lengths as asked (``["7d", "30d"]``) and how the fractions were taken
    outages: list[str] = field(default_factory=list)
    outage_fractions: str = "held"
    #: the phase rates scored beside the total (empty when the data have none)
    phases: list[str] = field(default_factory=list)
    #: per run: model, method, (outage,) runtime_s, retrains
    runs: list[dict[str, Any]] = field(default_factory=list)

    def metrics(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "data": self.data_path,
            "split": self.split.isoformat(),
            "targets": self.targets,
            "records": self.records,
            "summary": self.summary,
            "runtime_s": round(self.runtime_s, 3),
            "runs": [{**r, "runtime_s": round(float(r["runtime_s"]), 3)} for r in self.runs],
        }
        if self.phases:
            out["phases"] = list(self.phases)
        if self.outages:
            out["outages"] = list(self.outages)
            out["outage_fractions"] = self.outage_fractions
            windows = self.outage_windows
            out["outage_windows"] = [
                {
                    "outage": str(r.outage),
                    "well": str(r.well),
                    "start": pd.Timestamp(r.start).isoformat(),
                    "end": pd.Timestamp(r.end).isoformat(),
                    "rows": int(r.rows),
                }
                for r in windows.itertuples()
            ]
        return out
