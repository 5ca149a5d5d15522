"""Tests of the shared page module and of the diagnosis and drift pages, on made-up
results (no training): escaping of text from the data, self-contained pages, formats."""

from __future__ import annotations

import re
import stat
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from markupsafe import Markup
from matplotlib.figure import Figure

import vfm_core
from vfm_core.jobs.diagnose import DRIVER_VARIABLES, CandidateResult, Diagnosis
from vfm_core.reporting import diagnosis, drift_report, page

NASTY_WELL = "<b>W1</b>"
NASTY_EFFECT = "<script>alert(1)</script>"
NASTY_PATH = "/data/field <test> & co.parquet"


def image_count(html: str) -> int:
    return html.count('src="data:image/png;base64,')


def assert_self_contained(html: str) -> None:
    assert html.startswith("<!DOCTYPE html>")
    assert 'src="http' not in html and "href=" not in html
    assert "<link" not in html and "<script" not in html and "url(" not in html


# --------------------------------------------------------------------------- page


def test_templates_autoescape_and_markup_passes_through() -> None:
    template = page.ENV.from_string("{{ text }}|{{ safe }}")
    out = template.render(text="<b>&'\"", safe=Markup("<i>ok</i>"))
    assert out == "&lt;b&gt;&amp;&#39;&#34;|<i>ok</i>"


def test_figure_embeds_a_png_and_escapes_a_plain_caption() -> None:
    fig = Figure(figsize=(2, 1))
    fig.subplots().plot([0, 1], [0, 1])
    html = page.figure(fig, "a < b", alt='x "quoted"')
    assert isinstance(html, Markup)
    assert image_count(html) == 1
    assert "<figcaption>a &lt; b</figcaption>" in html
    assert 'alt="x &#34;quoted&#34;"' in html
    # an encoded figure is reused as is; a Markup caption is kept
    png = page.png(fig)
    again = page.figure(png, Markup("<b>bold</b>"))
    assert png.data in again and "<figcaption><b>bold</b></figcaption>" in again


def test_table_helper_formats_and_escapes_cells() -> None:
    html = page.table(
        [{"name": NASTY_WELL, "x": 1.23456, "n": 3, "ok": True, "bad": float("nan")}],
        [("name", "well"), ("x", "x"), ("n", "n"), ("ok", "ok"), ("bad", "bad"), ("gone", "gone")],
        caption="c & d",
    )
    cells = re.findall(r"<td[^>]*>([^<]*)</td>", html)
    assert cells == ["&lt;b&gt;W1&lt;/b&gt;", "1.23", "3", "True", "-", ""]
    assert "<caption>c &amp; d</caption>" in html
    assert '<div class="table-scroll">' in html


@pytest.mark.parametrize(
    ("value", "pct", "fixed", "signed", "thousands"),
    [
        (12.345, "12.3", "12.35", "+12.35", "12"),
        (-0.5, "-0.5", "-0.50", "-0.50", "0"),
        (12345.0, "1.2e+04", "12345.00", "+12345.00", "12,345"),
        (None, "–", "–", "–", "–"),
        (float("nan"), "–", "–", "–", "–"),
        (float("inf"), "–", "–", "–", "–"),
    ],
)
def test_number_filters_by_hand(value, pct, fixed, signed, thousands) -> None:
    assert page.fmt_pct(value) == pct
    assert page.fmt_fixed(value) == fixed
    assert page.fmt_signed(value) == signed
    assert page.fmt_thousands(value) == thousands


def test_write_page_is_atomic_and_readable(tmp_path: Path) -> None:
    out = page.write_page(tmp_path / "sub" / "p.html", "<p>hi</p>\n")
    assert out.read_text(encoding="utf-8") == "<p>hi</p>\n"
    assert [p.name for p in out.parent.iterdir()] == ["p.html"]  # no temporary left behind
    assert out.stat().st_mode & stat.S_IRGRP  # not the private mode of a temporary file


def test_templates_ship_in_the_package() -> None:
    folder = Path(page.__file__).parent / "templates"
    names = set(page.ENV.list_templates())
    for name in ("base.html.j2", "page.css", "study.html.j2", "diagnosis.html.j2"):
        assert name in names and (folder / name).is_file()
    pyproject = Path(vfm_core.__file__).parent.parent / "pyproject.toml"
    if pyproject.is_file():  # a source checkout: the wheel must carry the templates
        assert '"vfm_core.reporting" = ["templates/*"]' in pyproject.read_text()


def test_no_html_is_built_in_python() -> None:
    """HTML lives in templates, where the engine escapes data; none is assembled in .py."""
    root = Path(vfm_core.__file__).parent
    offenders = [
        f"{path.relative_to(root)}: {tag}"
        for path in sorted(root.rglob("*.py"))
        for tag in ("<div", "<table", "<tr", "<td", "<p>", "<p ", "<h1", "<h2", "<img", "<figure")
        if tag in path.read_text(encoding="utf-8")
    ]
    assert offenders == []


# --------------------------------------------------------------------------- diagnosis


def _residuals(wells: tuple[str, ...] = (NASTY_WELL, "W2"), n: int = 120) -> pd.DataFrame:
    rng = np.random.default_rng(1)
    frames = []
    for w, well in enumerate(wells):
        time = pd.date_range("2019-01-01", periods=n, freq="3D", tz="UTC")
        measured = 100.0 + 10 * w + rng.normal(0, 1, n)
        predicted = measured * (1 + rng.normal(0, 0.03, n))
        frame = pd.DataFrame(
            {
                "time": time,
                "well": well,
                "source": np.where(np.arange(n) % 10 == 0, "well_test", "mpfm"),
                "choke": rng.uniform(0.2, 0.9, n),
                "p_up": rng.uniform(60, 90, n),
                "p_down": rng.uniform(20, 40, n),
                "t_up": rng.uniform(50, 70, n),
                "eta_gas": rng.uniform(0.1, 0.2, n),
                "eta_oil": rng.uniform(0.5, 0.7, n),
                "water_cut": rng.uniform(0, 0.3, n),
                "throughput_years": np.linspace(0, 1, n),
                "predicted": predicted,
                "measured": measured,
            }
        )
        frame["p_ratio"] = frame["p_down"] / frame["p_up"]
        frame["flow_regime"] = "subcritical"
        frame["r"] = (frame["measured"] - frame["predicted"]) / frame["measured"]
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def _candidate(effect: str, meaning: str, run: object = None) -> CandidateResult:
    return CandidateResult(
        effect=effect,
        mape=2.5,
        delta_mape=-0.5,
        bic=-100.0,
        delta_bic=-20.0,
        n_parameters=2,
        parameters={},
        meaning=meaning,
        material=True,
        run=run,  # type: ignore[arg-type]
        delta_bic_all=-15.0,
    )


def _diagnosis() -> Diagnosis:
    res = _residuals()
    extended_run = SimpleNamespace(predictions=res.assign(predicted=res["measured"] * 1.01))
    regions = {
        "well": [
            {"region": NASTY_WELL, "n": 120, "mape": 3.1, "median_residual": 0.01},
            {"region": "W2", "n": 120, "mape": 2.9, "median_residual": -0.002},
        ]
    }
    return Diagnosis(
        model="mm",
        method="ol",
        targets="all",
        split=pd.Timestamp("2019-01-01", tz="UTC"),
        baseline=None,  # type: ignore[arg-type]
        baseline_mape=3.0,
        baseline_bic=-50.0,
        residuals=res,
        drivers=[{"name": v, "score": 0.1, "unit": "-"} for v in DRIVER_VARIABLES],
        regions=regions,
        candidates=[_candidate(NASTY_EFFECT, f"The {NASTY_WELL} rate & more.")],
        findings=[f"By well: the largest error is in {NASTY_WELL}."],
        verdict=f"The missing effect is most likely {NASTY_EFFECT}.",
        extended=_candidate(NASTY_EFFECT, "fitted <i>meaning</i>", extended_run),
        runtime_s=12.0,
        candidate_method="pbl:36500d",
        candidate_baseline_mape=3.2,
        bic_on="well tests",
    )


@pytest.fixture(scope="module")
def diagnosis_page(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("diag") / "report.html"
    assert diagnosis.build_report(_diagnosis(), path) == path
    return path.read_text(encoding="utf-8")


def test_diagnosis_page_escapes_text_from_data(diagnosis_page: str) -> None:
    assert NASTY_WELL not in diagnosis_page and NASTY_EFFECT not in diagnosis_page
    assert "<i>meaning</i>" not in diagnosis_page
    assert "&lt;b&gt;W1&lt;/b&gt;" in diagnosis_page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in diagnosis_page
    assert "The &lt;b&gt;W1&lt;/b&gt; rate &amp; more." in diagnosis_page


def test_diagnosis_page_keeps_its_sections(diagnosis_page: str) -> None:
    assert_self_contained(diagnosis_page)
    for heading in (
        "Where the model fails",
        "Candidate effects",
        "Drivers of the residual",
        "Before and after: mm vs mm+&lt;script&gt;alert(1)&lt;/script&gt;",
        "Residual against each variable",
        "Residual over time per well",
        "Errors by region",
    ):
        assert f"<h2>{heading}</h2>" in diagnosis_page
    text = " ".join(diagnosis_page.split())  # line breaks in HTML are plain spaces
    assert "<b>Verdict.</b>" in text
    assert "baseline MAPE 3.00 %" in text
    assert "(change -0.50 points, BIC -20)" in text
    assert "max(0.25 points, 10 % of the baseline) and the BIC by more than 10," in text
    # rolling error before/after, residual against the variables, residual over time
    assert image_count(diagnosis_page) == 3


# --------------------------------------------------------------------------- drift


def _drift_result() -> dict[str, object]:
    times = [str(t) for t in pd.date_range("2018-06-01", periods=50, freq="7D")]
    return {
        "targets": "all",
        "split": "2019-01-01T00:00:00+00:00",
        "alpha": 0.05,
        "confirm": 3,
        "reference_fraction": 0.5,
        "median_period_days": 37.4,
        "wells": {
            NASTY_WELL: {
                "n_train": 40,
                "reference": 20,
                "first_shift": "2018-09-01 00:00:00",
                "period_days": 37.4,
                "share_detected_after_split": 0.25,
                "times": times,
                "t2": list(np.linspace(1, 50, 50)),
                "detected": [i > 30 for i in range(50)],
                "t2_critical": 20.0,
            },
            "W2": {"n_train": 5, "reference": 2, "error": "too few <observations>"},
        },
    }


def test_drift_page_escapes_text_and_keeps_its_table(tmp_path: Path) -> None:
    path = drift_report.build_report(_drift_result(), tmp_path / "report.html", NASTY_PATH)
    html = path.read_text(encoding="utf-8")
    assert_self_contained(html)
    assert NASTY_WELL not in html and "<observations>" not in html
    assert "&lt;b&gt;W1&lt;/b&gt;" in html and "too few &lt;observations&gt;" in html
    assert "/data/field &lt;test&gt; &amp; co.parquet" in html
    assert "Hotelling" in html and "<b>37 days</b>" in html
    rows = re.findall(r"<tr><td[^>]*>(.*?)</tr>", html)
    assert len(rows) == 2
    cells = [re.findall(r"<td[^>]*>([^<]*)</td>", "<td>" + r) for r in rows]
    assert cells[0][1:] == ["40", "37", "2018-09-01 00:00:00", "25 %"]
    assert cells[1][1:] == ["5", "–", "too few &lt;observations&gt;", "–"]
    assert image_count(html) == 1
