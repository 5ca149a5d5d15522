"""The commands as a user runs them: simulate, evaluate, tune (resumable), drift, and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vfm_core.cli import main
from vfm_core.jobs.tune import load_params, run_tuning, settings_for, trial_grid
from vfm_core.simulate import simulate_field


@pytest.fixture(scope="module")
def small_field(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("field") / "field.parquet"
    assert (
        main(
            [
                "simulate",
                "--out",
                str(out),
                "--wells",
                "2",
                "--years",
                "1.5",
                "--start",
                "2017-09-01",
                "--seed",
                "4",
                "--quiet",
            ]
        )
        == 0
    )
    return out


def test_simulate_then_evaluate_writes_the_contract(
    small_field: Path, tmp_path: Path, capsys
) -> None:
    out = tmp_path / "eval"
    rc = main(
        [
            "evaluate",
            str(small_field),
            "--out",
            str(out),
            "--models",
            "last,mm",
            "--methods",
            "ol,pbl:30d",
            "--quiet",
            "--no-report",
        ]
    )
    assert rc == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert {(s["model"], s["method"]) for s in metrics["summary"]} == {
        ("last", "ol"),
        ("last", "pbl:30d"),
        ("mm", "ol"),
        ("mm", "pbl:30d"),
    }
    assert "Mean MAPE across wells" in capsys.readouterr().out


def test_bad_input_gives_one_sentence_and_status_2(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("time,well,choke\n2019-01-01,W1,0.5\n")
    assert main(["evaluate", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "missing" in err.lower()
    assert main(["evaluate", str(bad), "--out", str(tmp_path / "o"), "--methods", "pbl:soon"]) == 2
    assert main(["simulate", "--out", str(tmp_path / "x.parquet"), "--hidden", "gremlins"]) == 2
    assert "erosion" in capsys.readouterr().err


def test_tune_is_resumable_and_chooses_from_the_grid(small_field: Path, tmp_path: Path) -> None:
    out = tmp_path / "tune"
    kw = dict(
        models=["mm"],
        methods=["pbl:60d"],
        targets="all",
        split="2019-01-01",
        grid="small",
        workers=1,
        progress=False,
    )
    params = run_tuning(small_field, out, **kw)
    trials = (out / "trials.jsonl").read_text().splitlines()
    assert len(trials) == len(trial_grid(["mm"], ["pbl:60d"], "small")) == 3
    chosen = params["models"]["mm"]["pbl:60d"]
    scores = {json.loads(t)["train"]["lr"]: json.loads(t)["mean_mape"] for t in trials}
    assert chosen["train"]["lr"] == min(
        scores, key=lambda k: scores[k] if scores[k] is not None else 1e9
    )
    # the inner validation period lies strictly before the split: no peeking
    assert pd.Timestamp(params["inner_split"]) < pd.Timestamp(params["split"])
    # a second run finds every trial done and only rewrites params.json
    before = (out / "trials.jsonl").read_text()
    again = run_tuning(small_field, out, **kw)
    assert (out / "trials.jsonl").read_text() == before and again["models"] == params["models"]
    loaded = load_params(out / "params.json")
    assert settings_for(loaded, "mm", "pbl:60d")["train"].lr == chosen["train"]["lr"]


def test_drift_command_reports_periods(small_field: Path, tmp_path: Path) -> None:
    out = tmp_path / "drift"
    assert main(["drift", str(small_field), "--out", str(out)]) == 0
    result = json.loads((out / "drift.json").read_text())
    assert set(result["wells"]) == {"W01", "W02"}
    html = (out / "report.html").read_text()
    assert "data:image/png;base64" in html and "Hotelling" in html


def test_evaluate_with_an_effect_shows_the_error_fall(tmp_path: Path) -> None:
    data = tmp_path / "eroding.parquet"
    assert (
        main(
            [
                "simulate",
                "--out",
                str(data),
                "--wells",
                "2",
                "--years",
                "2.5",
                "--start",
                "2017-01-01",
                "--hidden",
                "erosion:rate=0.1",
                "--quiet",
            ]
        )
        == 0
    )
    out = tmp_path / "eval"
    assert (
        main(
            [
                "evaluate",
                str(data),
                "--out",
                str(out),
                "--models",
                "mm",
                "--methods",
                "pbl:182d",
                "--effects",
                "erosion",
                "--quiet",
                "--no-report",
            ]
        )
        == 0
    )
    summary = {
        s["model"]: s["mean_mape"]
        for s in json.loads((out / "metrics.json").read_text())["summary"]
        if "target" not in s  # the total rate (phases have rows of their own)
    }
    assert set(summary) == {"mm", "mm+erosion"}
    assert summary["mm+erosion"] < 0.6 * summary["mm"], summary


def test_every_method_has_something_to_tune_and_bayes_its_drift() -> None:
    from vfm_core.jobs.tune import method_for
    from vfm_core.learning import METHODS, parse_method

    for cls in METHODS.values():
        trials = trial_grid(["mm"], [cls.example], "small")
        assert trials, cls.key
        for t in trials:  # every setting is one the method and the settings accept
            parse_method(t.get("text", t["method"]))
            settings_for({"models": {"mm": {t["method"]: t}}}, "mm", t["method"])
    bayes = trial_grid(["mm", "last"], ["bayes"], "small")
    assert {t["text"] for t in bayes} == {f"bayes:drift={d:g}" for d in (0.25, 0.5, 1, 2, 4)}
    params = {"models": {"mm": {"bayes": {"text": "bayes:drift=2"}}}}
    assert method_for(params, "mm", "bayes") == "bayes:drift=2"
    assert method_for(params, "ham", "bayes") == "bayes"


def test_evaluate_runs_the_method_options_a_params_file_chose() -> None:
    """params.json's ``text`` (e.g. ``bayes:drift=4``) is the method the study runs for
    that model; the records keep the method's name, so a table reads the same."""
    from vfm_core.jobs.evaluate import run_study

    frame = simulate_field(wells=2, years=1.2, seed=5, start="2018-06-01").observations
    runs = {}
    for text in ("bayes", "bayes:drift=4"):
        params = {"models": {"mm": {"bayes": {"text": text}}}}
        result = run_study(frame, models=["mm"], methods=["bayes"], progress=False, params=params)
        assert set(result.predictions["method"]) == {"bayes"}
        runs[text] = result.predictions["predicted"].to_numpy()
    # four times the drift lets the filter move further: the predictions differ
    assert not np.allclose(runs["bayes"], runs["bayes:drift=4"])
