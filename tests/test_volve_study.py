"""A small slice of the study on real data (Volve), end to end. Skipped where the licensed file is absent."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vfm_core.cli import main

VOLVE = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "volve" / "volve_daily_production.csv"
)


@pytest.mark.skipif(
    not VOLVE.exists(),
    reason=f"Volve data not found at {VOLVE}: it is licensed and lives beside the repo in ../shared/data/volve/",
)
def test_volve_slice_end_to_end(tmp_path: Path) -> None:
    data = tmp_path / "volve.parquet"
    assert main(["import-volve", str(VOLVE), "--out", str(data)]) == 0
    import pandas as pd

    frame = pd.read_parquet(data)
    # two long-lived wells, 2013-2015: fit on 2013-2014, score 2015
    part = frame[
        frame["well"].isin(["15/9-F-12", "15/9-F-14"])
        & (frame["time"] >= "2013-01-01")
        & (frame["time"] < "2016-01-01")
    ]
    slice_path = tmp_path / "slice.parquet"
    part.to_parquet(slice_path, index=False)
    out = tmp_path / "study"
    assert (
        main(
            [
                "evaluate",
                str(slice_path),
                "--out",
                str(out),
                "--models",
                "last,mm",
                "--methods",
                "ol,pbl:182d",
                "--split",
                "2015-01-01",
                "--quiet",
                "--no-report",
            ]
        )
        == 0
    )
    metrics = json.loads((out / "metrics.json").read_text())
    by = {(r["model"], r["method"], r["well"]): r for r in metrics["records"]}
    assert len(by) == 8
    for (model, method, well), r in by.items():
        assert r["n"] > 300, (model, method, well)
        # real data: the numbers are what they are, but they must be finite and sane
        assert 0 < r["mape"] < 100, (model, method, well, r["mape"])
