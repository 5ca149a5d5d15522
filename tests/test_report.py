"""Tests of the HTML report on a made-up study whose MAPEs are known by hand (no training)."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vfm_core.jobs.evaluate import StudyResult, summarise
from vfm_core.jobs.study import metrics_records
from vfm_core.reporting.study import build_report, calibration_curve

SPLIT = pd.Timestamp("2019-01-01", tz="UTC")
WELLS = ("<b>W1</b>", "W2", "W3")
#: Absolute percentage error of every prediction per (model, method), one value per well.
#: Signs alternate between observations, so each well's MAPE is exactly this value.
ERRORS: dict[tuple[str, str], tuple[float, float, float]] = {
    ("lr", "ol"): (1.0, 2.0, 3.0),  # mean 2.0
    ("lr", "pbl:14d"): (2.0, 4.0, 6.0),  # mean 4.0
    ("mm", "ol"): (3.0, 6.0, 9.0),  # mean 6.0
    ("mm", "pbl:14d"): (5.0, 10.0, 15.0),  # mean 10.0
    ("last", "ol"): (40.0, 50.0, 60.0),  # mean 50.0, the benchmark: not in "All"
    ("last", "pbl:14d"): (40.0, 50.0, 60.0),
}
#: The hand-computed table: "All" averages lr and mm only, (2 + 6) / 2 and (4 + 10) / 2.
EXPECTED_MEAN = {
    "ol": {"lr": "2.0", "mm": "6.0", "All": "4.0", "last (benchmark)": "50.0"},
    "pbl:14d": {"lr": "4.0", "mm": "10.0", "All": "7.0", "last (benchmark)": "50.0"},
}


def make_predictions(
    errors: dict[tuple[str, str], tuple[float, ...]], days: int = 60
) -> pd.DataFrame:
    """Four observations a day per well; every 10th one a well test, the rest MPFM."""
    times = pd.date_range(SPLIT, periods=days * 4, freq="6h")
    frames = []
    for (model, method), per_well in errors.items():
        for w, (well, err) in enumerate(zip(WELLS, per_well, strict=True)):
            measured = 1000.0 * (w + 1) + 50.0 * np.sin(np.arange(len(times)) / 9.0)
            sign = np.where(np.arange(len(times)) % 2 == 0, 1.0, -1.0)
            frames.append(
                pd.DataFrame(
                    {
                        "time": times,
                        "well": well,
                        "model": model,
                        "method": method,
                        "source": np.where(np.arange(len(times)) % 10 == 0, "well_test", "mpfm"),
                        "predicted": measured * (1.0 + sign * err / 100.0),
                        "measured": measured,
                    }
                )
            )
    return pd.concat(frames, ignore_index=True)


def make_parameters() -> pd.DataFrame:
    rows = []
    for method in ("ol", "pbl:14d"):
        for well in WELLS:
            for k, t in enumerate(pd.date_range(SPLIT, periods=5, freq="14D")):
                rows.append(
                    {
                        "time": t,
                        "well": well,
                        "model": "mm",
                        "method": method,
                        "name": "c_d",
                        "value": 0.85 - 0.01 * k,
                    }
                )
                rows.append(
                    {
                        "time": t,
                        "well": well,
                        "model": "mm",
                        "method": method,
                        "name": "kappa",
                        "value": 1.3,
                    }
                )
    return pd.DataFrame(rows)


def make_result(predictions: pd.DataFrame, **overrides: object) -> StudyResult:
    records = metrics_records(predictions) if len(predictions) else []
    fields: dict[str, object] = {
        "split": SPLIT,
        "targets": "all",
        "records": records,
        "summary": summarise(records),
        "predictions": predictions,
        "updates": {"ol": [], "pbl:14d": list(pd.date_range(SPLIT, periods=4, freq="14D"))},
        "well_tests": {
            well: list(pd.date_range("2018-01-01", periods=8, freq=f"{5 + 20 * i}D", tz="UTC"))
            for i, well in enumerate(WELLS)
        },
        "runtime_s": 12.5,
        "parameters": make_parameters(),
        "data_path": "/data/field <test>.parquet",
    }
    fields.update(overrides)
    return StudyResult(**fields)  # type: ignore[arg-type]


class _Tables(HTMLParser):
    """Every table of a page as a list of rows of cell texts."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: list[list[list[str]]] = []
        self._cell: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append("".join(self._cell).strip())
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)


def tables_of(page: str) -> list[list[list[str]]]:
    parser = _Tables()
    parser.feed(page)
    return parser.tables


def table_after(page: str, heading: str) -> list[list[str]]:
    """The first table after the ``<h2>`` with this text."""
    start = page.index(f"<h2>{heading}</h2>")
    return tables_of(page[start:])[0]


def image_count(page: str) -> int:
    return page.count('src="data:image/png;base64,')


@pytest.fixture
def page(tmp_path: Path) -> str:
    out = build_report(make_result(make_predictions(ERRORS)), tmp_path / "sub" / "report.html")
    assert out == tmp_path / "sub" / "report.html"
    assert out.is_file()
    return out.read_text(encoding="utf-8")


def test_report_is_self_contained(page: str) -> None:
    assert page.startswith("<!DOCTYPE html>")
    assert 'src="http' not in page
    assert "<link" not in page
    assert "<script" not in page
    assert "url(" not in page
    # box plot, rolling error, well-test gaps, rates of the best model (lr), rates of mm, C_D
    assert image_count(page) == 6


def test_mean_table_holds_hand_computed_mape(page: str) -> None:
    table = table_after(page, "Mean MAPE across wells")
    header = table[0]
    assert header == ["Learning method", "lr", "mm", "All", "last (benchmark)"]
    body = {row[0]: dict(zip(header[1:], row[1:], strict=True)) for row in table[1:]}
    assert body == EXPECTED_MEAN
    # the lowest cell per column is highlighted: ol everywhere; the benchmark ties, so none
    best_cells = re.findall(r'<td class="best[^"]*">([^<]*)</td>', page)
    assert best_cells == ["2.0", "6.0", "4.0"]


def test_per_well_table_lists_methods_in_order(page: str) -> None:
    table = table_after(page, "MAPE per well")
    assert table[0] == ["Well", "lr", "mm", "last (benchmark)"]
    rows = {row[0]: row[1:] for row in table[1:]}
    assert rows["W2"] == ["2.0, 4.0", "6.0, 10.0", "50.0, 50.0"]
    assert rows["<b>W1</b>"] == ["1.0, 2.0", "3.0, 5.0", "40.0, 40.0"]  # parser unescapes
    assert "order <b>ol, pbl:14d</b>" in page


def test_summary_is_computed_from_the_numbers(page: str) -> None:
    summary = page[page.index("<h2>What this shows</h2>") : page.index("<h2>Mean MAPE")]
    assert "<b>ol</b> gives the lowest mean MAPE (4.0&nbsp;%; then pbl:14d 7.0&nbsp;%)" in summary
    assert "<b>lr</b> with <b>ol</b> (2.0&nbsp;%" in summary
    assert "4 of 4 model-method combinations beat it" in summary
    assert "Model <b>lr</b>" in page  # the representative model of the rates grid


def test_text_from_data_is_escaped(page: str) -> None:
    assert "<b>W1</b>" not in page
    assert "&lt;b&gt;W1&lt;/b&gt;" in page
    assert "/data/field &lt;test&gt;.parquet" in page


def test_well_test_gap_table(page: str) -> None:
    table = table_after(page, "Days between well tests")
    assert table[0][:3] == ["Well", "tests", "< 2w"]
    rows = {row[0]: row[1:] for row in table[1:]}
    # W1: gaps of 5 d, all in "< 2w"; W2: 25 d, all in "2w-1m"; 8 tests each
    assert rows["<b>W1</b>"][:3] == ["8", "100.0\xa0%", "0.0\xa0%"]
    assert rows["W2"][:3] == ["8", "0.0\xa0%", "100.0\xa0%"]


def test_single_model_single_method_no_well_tests_no_updates(tmp_path: Path) -> None:
    preds = make_predictions({("mm", "ol"): (3.0, 6.0, 9.0)})
    result = make_result(preds, well_tests={}, updates={}, parameters=pd.DataFrame(), data_path="")
    page = build_report(result, tmp_path / "r.html").read_text(encoding="utf-8")
    table = table_after(page, "Mean MAPE across wells")
    assert table[0] == ["Learning method", "mm", "All"]
    assert table[1] == ["ol", "6.0", "6.0"]
    assert "no gaps to show" in page
    # box plot, rolling error, rates of mm; no gap histogram, no C_D
    assert image_count(page) == 3


def test_nan_mape_and_a_well_without_predictions(tmp_path: Path) -> None:
    preds = make_predictions(ERRORS)
    unscored = preds["well"] == "W3"
    preds.loc[unscored & (preds["model"] == "mm"), "predicted"] = np.nan
    result = make_result(preds)
    # records as they come from JSON: NaN written as None
    result.records = [
        {**r, "mape": None if r["mape"] != r["mape"] else r["mape"]} for r in result.records
    ]
    page = build_report(result, tmp_path / "r.html").read_text(encoding="utf-8")
    rows = {row[0]: row[1:] for row in table_after(page, "MAPE per well")[1:]}
    assert rows["W3"][1] == "–, –"
    # mm's mean skips the unscored well: (3 + 6) / 2 and (5 + 10) / 2
    mean = {row[0]: row[1:] for row in table_after(page, "Mean MAPE across wells")[1:]}
    assert mean["ol"][1] == "4.5"
    assert mean["pbl:14d"][1] == "7.5"
    assert image_count(page) == 6


def test_diverged_model_and_missing_well_do_not_break_the_page(tmp_path: Path) -> None:
    errors = dict(ERRORS)
    errors[("lr", "pbl:14d")] = (2.0, 4.0, 1e90)  # one well's predictions ran away
    preds = make_predictions(errors)
    preds = preds[~((preds["well"] == "W2") & (preds["model"] == "mm"))]
    page = build_report(make_result(preds), tmp_path / "r.html").read_text(encoding="utf-8")
    assert "Warning:" in page
    rows = {row[0]: row[1:] for row in table_after(page, "MAPE per well")[1:]}
    assert rows["W3"][0] == "3.0, 1.0e+90"  # huge MAPE in scientific notation, not 91 digits
    assert rows["W2"][1] == "–, –"  # no mm predictions for W2
    # the box plot's axis stops below the diverged well and the caption names it
    assert re.search(r"y axis stops at \d+&nbsp;%.*W3 \(lr, pbl:14d\): 1\.0e\+90", page)
    # lr's mean is now huge, so mm is the representative model: no second rates grid
    assert "Model <b>mm</b>" in page
    assert image_count(page) == 5


def test_empty_study(tmp_path: Path) -> None:
    empty = pd.DataFrame(
        columns=["time", "well", "model", "method", "source", "predicted", "measured"]
    )
    result = make_result(empty, well_tests={}, updates={}, parameters=pd.DataFrame())
    page = build_report(result, tmp_path / "r.html").read_text(encoding="utf-8")
    assert "nothing to compare" in page
    assert image_count(page) == 0


def test_file_stays_small_for_a_long_study(tmp_path: Path) -> None:
    preds = make_predictions(ERRORS, days=2000)  # 8,000 observations per well and run
    page = build_report(make_result(preds), tmp_path / "r.html")
    assert page.stat().st_size < 2_000_000
    assert re.search(r"at most \d+ points per series", page.read_text(encoding="utf-8"))


# --------------------------------------------------------------------------- phases, outages, intervals


def with_oil(preds: pd.DataFrame, factor: float = 2.0) -> pd.DataFrame:
    """Oil at 1 % of the total, its error ``factor`` times the total's (same sign)."""
    rel = (preds["predicted"] - preds["measured"]) / preds["measured"]
    return preds.assign(
        measured_q_oil=preds["measured"] * 0.01,
        predicted_q_oil=preds["measured"] * 0.01 * (1.0 + factor * rel),
    )


def make_outage_predictions() -> pd.DataFrame:
    """Inside 30-day windows: every error three times the ordinary one; 0-29 days since."""
    errors = {k: tuple(3.0 * e for e in v) for k, v in ERRORS.items()}
    preds = make_predictions(errors, days=30)
    since = np.tile(np.arange(120) / 4.0, len(preds) // 120)
    return preds.assign(outage="30d", days_since=since)


@pytest.fixture
def protocol_page(tmp_path: Path) -> str:
    preds = with_oil(make_predictions(ERRORS))
    outage = make_outage_predictions()
    records = metrics_records(preds) + metrics_records(outage)
    windows = pd.DataFrame(
        {
            "outage": "30d",
            "well": list(WELLS) * 2,
            "start": SPLIT,
            "end": SPLIT + pd.Timedelta(days=30),
            "rows": 60,
        }
    )
    result = make_result(
        preds,
        records=records,
        summary=summarise(records),
        outage_predictions=outage,
        outage_windows=windows,
        outages=["30d"],
        phases=["q_oil"],
    )
    return build_report(result, tmp_path / "r.html").read_text(encoding="utf-8")


def test_protocol_table_holds_hand_computed_scores(protocol_page: str) -> None:
    table = table_after(protocol_page, "Total and phases, ordinary and outage protocol")
    assert table[0] == ["Protocol", "Target", "lr", "mm", "last (benchmark)", "beats benchmark"]
    rows = {(r[0], r[1]): r[2:] for r in table[1:]}
    # each model at its best method (ol); oil errors twice the total's, outages three times
    assert rows["ordinary", "total"] == ["2.0ol", "6.0ol", "50.0ol", "✓"]
    assert rows["ordinary", "oil"] == ["4.0ol", "12.0ol", "100.0ol", "✓"]
    assert rows["30d", "total"] == ["6.0ol", "18.0ol", "150.0ol", "✓"]
    assert len(rows) == 3
    # the paper's tables stay those of the total under the ordinary protocol
    mean = table_after(protocol_page, "Mean MAPE across wells")
    assert {r[0]: r[1:] for r in mean[1:]}["ol"] == ["2.0", "6.0", "4.0", "50.0"]


def test_outage_figure_and_its_windows(protocol_page: str) -> None:
    section = protocol_page[protocol_page.index("Standing in for a failed meter") :]
    assert "30d: 6 windows in 3 wells, 360 hidden measurements" in section
    assert "held at the last measurement before it" in section
    # the seven of the default page, plus the outage figure and the phase grid
    assert image_count(protocol_page) == 8
    assert "<h2>Phase rates: lr (ol)</h2>" in protocol_page


def test_calibration_curve_by_hand() -> None:
    # sd 0.1 in log space (p95 = q e^(1.6449 * 0.1)); measurements at z = 0, 0.5, 1, 2 sd
    predicted = np.full(4, 100.0)
    p95 = predicted * np.exp(1.6448536269514722 * 0.1)
    measured = predicted * np.exp(0.1 * np.array([0.0, -0.5, 1.0, 2.0]))
    cov = calibration_curve(predicted, measured, p95, levels=(0.1, 0.5, 0.8, 0.95, 0.99))
    # central-interval half widths in sd: 0.126, 0.674, 1.282, 1.960, 2.576
    np.testing.assert_allclose(cov, [0.25, 0.5, 0.75, 0.75, 1.0])
    assert np.isnan(calibration_curve(predicted, measured, np.full(4, np.nan))).all()
