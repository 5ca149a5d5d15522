"""Diagnosis on fields with a known hidden effect of the library: the right verdict, and
the effects that leave no trace not claimed (see ``tests/test_diagnose.py``'s docstring for
the protocol and the noise floor). Apart from ``test_diagnose.py`` so that the two files'
whole-field diagnoses run in the suite's two processes at once."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from diagnose_support import PROGRESS
from diagnose_support import diagnose as _diagnose
from diagnose_support import field as _field
from diagnose_support import floor as _floor

from vfm_core.jobs.diagnose import format_summary, write_diagnosis

# --- hidden effects ------------------------------------------------------------------------------
LIBRARY_CASES = [
    # (hidden, seed, wells, the effect's family): rate 0.1 (default 0.04): the default wear is
    # within the MPFM noise on 3 wells x 2 years
    ("erosion:rate=0.1", 1, 3, "erosion"),
    ("erosion:rate=0.2", 3, 4, "erosion"),
    # the learned valve curve, then the named families: the hidden family should win
    ("valve", 1, 3, "valve"),
    ("valve:family=quick_opening", 1, 3, "valve"),
    ("valve:family=convex", 2, 3, "valve"),
    ("mpfm_bias", 1, 3, "mpfm_bias"),
    ("slip", 1, 3, "slip"),
]


@pytest.mark.parametrize(("hidden", "seed", "wells", "family"), LIBRARY_CASES)
def test_hidden_library_effect_is_the_verdict_and_halves_the_error(
    hidden: str, seed: int, wells: int, family: str
) -> None:
    diag = _diagnose(hidden, seed, wells)
    floor = _floor(_field(hidden, seed, wells))
    summary = format_summary(diag) + f"\ntruth floor {floor:.2f}"
    print(summary)
    assert diag.verdict_kind == "effect", summary
    assert diag.verdict_effect is not None and diag.verdict_effect.startswith(family), summary
    best = diag.with_effect
    assert best is not None and best.effect == diag.verdict_effect
    base = diag.candidate_baseline_mape
    assert best.mape - floor <= 0.5 * (base - floor), summary
    if hidden.startswith("valve:family=") or hidden == "valve":
        want = hidden.partition("=")[2] or "equal_percentage"
        assert diag.verdict_effect == f"valve_{want}", summary


@pytest.mark.parametrize("effect", ["real_gas", "critical_ratio"])
def test_effects_that_leave_no_trace_are_not_claimed(effect: str) -> None:
    """A limit, stated plainly and checked: on this field, once mm refits C_D, A_max and its
    constant p_cr, the hidden real-gas Z and Sachdeva's critical ratio leave almost nothing
    behind (the baseline is within half a point of the noise floor; a constant p_cr
    reproduces Sachdeva's ratio to about 0.02 % RMS), far below the MPFM's 2-5 % noise. No
    diagnosis can rank what it cannot see; what it must not do is claim something else."""
    diag = _diagnose(effect)
    floor = _floor(_field(effect))
    assert diag.candidate_baseline_mape - floor < 0.5, format_summary(diag)
    assert not any(c.material for c in diag.candidates), format_summary(diag)
    assert diag.verdict_kind == "noise", format_summary(diag)
    # the candidate itself stays physical: Papay's Z (strength 1) and Sachdeva's ratio (weight 1)
    mine = next(c for c in diag.candidates if c.effect == effect)
    value = next(iter(mine.parameters.values()))["value"]
    assert 0.3 < value < 1.5, format_summary(diag)


# --- the erosion 0.1 case's diagnosis (cached above) read as a user reads it -------------------
def test_progress_is_reported_as_a_fraction_with_a_text() -> None:
    _diagnose("erosion:rate=0.1", 1, 3)
    events = PROGRESS[("erosion:rate=0.1", 1, 3)]
    fractions = [f for f, _ in events]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] == 1.0
    assert all(text for _, text in events) and len(events) >= 8
    assert events[-1][1] == "verdict: effect"


def test_outputs_follow_the_contract(tmp_path: Path) -> None:
    diag = _diagnose("erosion:rate=0.1")
    written = write_diagnosis(diag, tmp_path / "out")
    assert sorted(p.name for p in written) == ["diagnosis.json", "report.html"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["diagnosis.json", "report.html"]
    data = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    assert data["model"] == "mm" and data["baseline"]["mape"] == pytest.approx(diag.baseline_mape)
    scores = [d["score"] for d in data["drivers"]]
    assert scores == sorted(scores, reverse=True)
    bics = [c["delta_bic"] for c in data["candidates"]]
    assert bics == sorted(bics)
    for c in data["candidates"]:
        assert {"effect", "mape", "delta_mape", "delta_bic", "parameters", "warnings"} <= set(c)
        assert {"explained_by", "rivals", "shape"} <= set(c)
        if c["material"]:  # its own shape beyond the trend, alone
            assert {"beta", "se", "spread", "decisive", "rejected", "confirmed"} <= set(c["shape"])
    rate = data["candidates"][0]["parameters"]["erosion.rate"]
    assert rate["sd"] > 0 and set(rate["per_well_sd"]) == set(rate["per_well"])
    v = data["verdict"]
    assert v["kind"] == "effect" and v["effect"] == "erosion" and v["driver"] is None
    assert v["text"] == diag.verdict
    # the rivals of other physics: erosion is the only thing missing, so none is at work
    # beside it (``then``) and none is explained by anything
    assert {"explains", "then", "alternatives"} <= set(v) and v["then"] == []
    assert all(c["explained_by"] in (None, "erosion") for c in data["candidates"])
    h = data["headline"]  # under the live protocol (the method replayed); fit-once beside it
    assert h["baseline_mape"] == pytest.approx(diag.live["mape"])
    assert h["fit_once_baseline_mape"] == pytest.approx(diag.candidate_baseline_mape)
    assert h["with"] == "erosion" and h["with_mape"] < h["baseline_mape"]
    assert h["live_change"]["change"] < 0 and h["live_change"]["high"] is not None
    assert data["floor"]["mape"] > 0 and "consecutive readings" in data["floor"]["method"]
    assert data["noise_test"]["shifts"] > 0 and data["suggestion"] is None
    html = (tmp_path / "out" / "report.html").read_text()
    assert "data:image/png;base64," in html and 'src="http' not in html
    assert "Verdict" in html and "Top candidate: the residual without and with erosion" in html
    assert "noise floor" in html and "Fitted parameters" in html
