"""``vfm demo --effects``: the service's model extended with a physical effect, end to end.

The demo's field hides choke erosion; ``--model mm --effects erosion`` runs the service with
``mm+erosion`` (its settings name the effect), replays the field through it over Zenoh, and
runs the offline study with the same extended model beside the plain one. The service's
error must be the offline prequential run's for the same model and method. Bad settings
fail before anything runs, with a sentence.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(300)


def _demo(*args: str, timeout: float = 280) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "vfm_core.cli", "demo", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def test_demo_with_an_effect_agrees_with_the_offline_run(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    done = _demo(
        "--out", str(out), "--wells", "2", "--years", "1.5", "--model", "mm",
        "--effects", "erosion", "--quiet",
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    text = done.stdout
    settings = (out / "service.toml").read_text()
    assert 'name = "mm"' in settings and 'effects = ["erosion"]' in settings
    assert "mm+erosion+ol (service)" in text
    # the offline study ran the extended model beside the plain one
    offline = dict(re.findall(r"([\w+:.]+) (\d+\.\d+)", text.split("Offline (vfm evaluate")[1]))
    assert {"mm+ol", "mm+erosion+ol", "mm+erosion+pbl:182d"} <= set(offline)
    found = re.search(
        r"gave (\d+\.\d+) for mm\+erosion\+ol; the offline prequential run (\d+\.\d+)", text
    )
    assert found is not None, text
    served, reference = float(found.group(1)), float(found.group(2))
    assert served == pytest.approx(reference, abs=0.011)  # printed to two decimals
    assert "rejected 0, dropped 0" in text
    # each well's `last` figure is its total's record in the study's metrics.json (the phase
    # records that follow it there are not the total's)
    metrics = json.loads((out / "study" / "metrics.json").read_text())
    last = {
        r["well"]: r["mape"]
        for r in metrics["records"]
        if r["model"] == "last" and r["method"] == "ol" and "target" not in r and "outage" not in r
    }
    assert any("target" in r for r in metrics["records"])  # the field has phases to mix up
    rows = re.findall(r"^  (W\d+)\s+(\d+\.\d+)\s+(\d+\.\d+)\s+[\d,]+$", text, re.MULTILINE)
    assert sorted(w for w, _, _ in rows) == sorted(last)
    for well, _, printed in rows:
        assert float(printed) == pytest.approx(last[well], abs=0.006), well


@pytest.mark.parametrize(
    ("args", "sentence"),
    [
        (("--model", "last", "--effects", "erosion"), "extend the physics models mm, hem and ham"),
        (("--model", "mm", "--effects", "no_such_effect"), "Unknown effect 'no_such_effect'"),
    ],
)
def test_demo_refuses_bad_effects_before_it_starts(
    tmp_path: Path, args: tuple[str, ...], sentence: str
) -> None:
    out = tmp_path / "demo"
    done = _demo("--out", str(out), "--quiet", *args, timeout=120)
    assert done.returncode == 2
    assert sentence in done.stderr
    assert not out.exists()  # nothing simulated, no service started


@pytest.mark.parametrize(
    ("model", "method", "models", "methods"),
    [("mm", "pbl:182d", "last,mm", "pbl:182d"), ("ham", "bayes", "last,mm,ham", "bayes,pbl:182d")],
)
def test_demo_without_report_names_each_model_and_method_once(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    model: str,
    method: str,
    models: str,
    methods: str,
) -> None:
    """With ``--no-report`` the demo prints the command that writes the report: the study
    of step 4, each model and method once (``--model mm`` listed ``last,mm,mm`` before)."""
    import argparse

    from replay.demo import _print_files

    args = argparse.Namespace(model=model, method=method)
    _print_files(args, tmp_path, tmp_path / "service.toml", None, "2017-01-01", [])
    line = next(x for x in capsys.readouterr().out.splitlines() if "vfm evaluate" in x)
    assert f" --models {models} " in line and f" --methods {methods} " in line
