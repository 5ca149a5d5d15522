"""Wear or a drifting operating point? The operating-point rival of erosion, measured.

On a truth whose physics differs from the diagnosed model's (``vfm simulate --physics
bernoulli`` under ``mm``), the model's misfit changes as the field depletes, and a C_D that
grows with throughput (``erosion``) takes it up in the fit-once evidence. The rival that
would tell them apart is a correction in an input that drifts with depletion (the state):
wear should add beyond it, a misfit of the state should not. This script measures both
halves on one field:

1. **The truth's misfit** (the simulator's noise-free rates): a once-fitted model's
   log(q_true / q_predicted) per well, its trend in time after the split, and its slope in
   log p_up before and after the split (the same slope on both sides is a misfit of the
   operating point, which a p_up correction could carry forward) with the spread of
   log p_up the fit sees before the split.
2. **The rival as the diagnosis would fit it**: for each state driver, the generic
   ``suggest`` correction (per well, linear; ``--forms linear,log``) fitted once before the
   split alone and together with erosion, and whether each adds beyond the other
   (:func:`vfm_core.jobs.diagnose_rivals.adds_beyond`: material and a paired block test),
   with both shapes beyond the trend (:func:`vfm_core.jobs.diagnose_rivals.shape_beyond_trend`).

Run (about 2 minutes per field on one core):

    python benchmarks/bench_state_rival.py --case none --physics bernoulli --seed 75 \\
        --wells 5 [--drivers p_up,p_ratio,eta_gas,water_cut] [--forms linear]

Prints one line per well and per driver. Nothing here is used by the diagnosis: it is the
measurement behind ``docs/benchmarks/verdicts.md``'s section on the operating-point rival.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
import pandas as pd
import torch

from vfm_core.data import make_batch
from vfm_core.effects import resolve_effect
from vfm_core.jobs import diagnose as dg
from vfm_core.jobs import diagnose_rivals as rivals
from vfm_core.jobs.study import run_prequential
from vfm_core.simulate import simulate_field


def _truth_misfit(field: Any, split: pd.Timestamp) -> None:
    """Part 1: the truth's misfit of a once-fitted mm, per well."""
    obs = field.observations.reset_index(drop=True)
    run = run_prequential(obs, "mm", dg.CANDIDATE_METHOD, split=split, targets="all", seed=0)
    model = run.final_model
    assert model is not None
    batch = make_batch(obs, model.wells, rows=np.arange(len(obs)), extra_columns=())
    with torch.no_grad():
        q = model.predict_batch(batch).numpy()
    q_true = field.truth_samples.reset_index(drop=True)["q_true"].to_numpy()
    log_p = np.log(obs["p_up"].to_numpy(dtype=float))
    before = (pd.to_datetime(obs["time"], utc=True) < split).to_numpy()
    years = (pd.to_datetime(obs["time"], utc=True) - split).dt.days.to_numpy() / 365.25
    print("truth's misfit log(q_true / q_mm) of mm fitted once before the split:")
    for i, well in enumerate(model.wells):
        mask = batch.mask[i].numpy()
        rows = batch.row[i].numpy()[mask]
        lr = np.log(q_true[rows] / q[i][mask])
        ok = np.isfinite(lr)
        parts = []
        for name, sel in (("before", before[rows] & ok), ("after", ~before[rows] & ok)):
            slope = np.polyfit(log_p[rows][sel], lr[sel], 1)[0]
            parts.append(
                f"{name}: slope in log p_up {slope:+.3f} (sd log p_up {log_p[rows][sel].std():.3f})"
            )
        after = ~before[rows] & ok
        trend = 100.0 * np.polyfit(years[rows][after], lr[after], 1)[0]
        corr = np.corrcoef(log_p[rows][after], lr[after])[0, 1]
        print(
            f"  {well}: {' | '.join(parts)}; after: {trend:+.2f} %/yr, corr with log p_up {corr:+.2f}"
        )


def _shape(s: dict[str, Any]) -> str:
    if s["beta"] is None:
        return "untestable"
    verdict = "rejected" if s["rejected"] else ("confirmed" if s["confirmed"] else "undecided")
    return f"{s['beta']:+.2f} +/- {s['se']:.2f} ({verdict})"


def _rivals(
    obs: pd.DataFrame, split: str, drivers: list[str], forms: list[str]
) -> list[dict[str, str]]:
    """Part 2: each state correction against erosion, as the diagnosis fits and weighs; one
    row per correction for the table."""
    box: dict[str, Any] = {}
    weigh = dg._DiagnosisRun.weigh_rivals

    def capture(job: Any) -> None:
        box["job"] = job
        weigh(job)

    dg._DiagnosisRun.weigh_rivals = capture  # type: ignore[method-assign]
    try:
        d = dg.run_diagnosis(obs, "mm", method="ol", replay_top=0, split=split)
    finally:
        dg._DiagnosisRun.weigh_rivals = weigh  # type: ignore[method-assign]
    job = box["job"]
    print(f"fit-once verdict: {d.verdict_kind} {d.verdict_effect or ''}")
    wear = next(c for c in job.results if c.effect == "erosion")
    print(f"  erosion alone: {wear.delta_mape:+.2f} points, dBIC {wear.delta_bic:+.0f}")
    train = dg._derived(job.frame.iloc[job.train_rows])
    rows: list[dict[str, str]] = []
    for driver in drivers:
        x = np.asarray(dg.stats.driver_values(train, driver), dtype=float)
        for form, head in dg._correction_heads(driver, x).items():
            if form not in forms:
                continue
            cls = resolve_effect(head)
            run_s = job.run(f"state {driver}", [cls], job.cand_method, job.cand_train)
            state = dg._score(driver, run_s, [cls], job.comp_mape, job.comp, None)
            classes = [*job.classes_of["erosion"], cls]
            run_p = job.run(f"erosion+{driver}", classes, job.cand_method, job.cand_train)
            pair = dg._score("pair", run_p, classes, job.comp_mape, job.comp, None)
            wear_beyond = rivals.adds_beyond(pair, state, 0)
            state_beyond = rivals.adds_beyond(pair, wear, 0)
            shapes = rivals.shape_beyond_trend(
                job.comp.predictions, wear.run.predictions, state.run.predictions
            )
            print(
                f"  {driver} ({form}): alone {state.delta_mape:+.2f} points; pair "
                f"{pair.delta_mape:+.2f}; erosion beyond it {wear_beyond['delta_mape']:+.2f} "
                f"(p {wear_beyond['p_value']:.2g}, adds {wear_beyond['adds']}); it beyond "
                f"erosion {state_beyond['delta_mape']:+.2f} (p {state_beyond['p_value']:.2g}, "
                f"adds {state_beyond['adds']}); shapes beyond the trend: erosion "
                f"{_shape(shapes[0])}, it {_shape(shapes[1])}"
            )
            rows.append(
                {
                    "correction": f"{driver} ({form})",
                    "alone": f"{state.delta_mape:+.2f}",
                    "erosion alone": f"{wear.delta_mape:+.2f}",
                    "pair": f"{pair.delta_mape:+.2f}",
                    "erosion beyond it": _beyond(wear_beyond),
                    "it beyond erosion": _beyond(state_beyond),
                    "its shape beyond the trend": _shape(shapes[1]),
                }
            )
    return rows


def _beyond(t: dict[str, Any]) -> str:
    return f"{t['delta_mape']:+.2f} (p {t['p_value']:.2g}){' adds' if t['adds'] else ''}"


def _markdown(path: str, command: str, rows: list[dict[str, str]]) -> None:
    """The table of part 2 (fit-once points of MAPE against the comparison baseline)."""
    head = list(rows[0]) if rows else ["correction"]
    lines = [
        f"Written by `{command}` (do not edit by hand). Fit-once MAPE changes in points "
        "against the baseline; 'beyond': the pair against the other alone, with the paired "
        "block test's p ('adds': material and p < 0.05).",
        "",
        "| " + " | ".join(head) + " |",
        "| " + " | ".join("---" for _ in head) + " |",
        *("| " + " | ".join(r[h] for h in head) + " |" for r in rows),
    ]
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="none", help="hidden effect, or none")
    parser.add_argument("--physics", default="bernoulli")
    parser.add_argument("--seed", type=int, default=75)
    parser.add_argument("--wells", type=int, default=5)
    parser.add_argument("--years", type=float, default=3.0)
    parser.add_argument("--split", default="2017-07-01")
    parser.add_argument("--drivers", default="p_up,p_ratio,eta_gas,water_cut")
    parser.add_argument("--forms", default="linear")
    parser.add_argument("--markdown", help="write part 2's table here")
    args = parser.parse_args()
    started = time.perf_counter()
    hidden = [] if args.case == "none" else [args.case]
    field = simulate_field(
        wells=args.wells, years=args.years, seed=args.seed, hidden=hidden, physics=args.physics
    )
    print(f"{args.physics} truth, seed {args.seed}, {args.wells} wells, hidden: {args.case}")
    split = pd.Timestamp(args.split, tz="UTC")
    _truth_misfit(field, split)
    rows = _rivals(field.observations, args.split, args.drivers.split(","), args.forms.split(","))
    if args.markdown:
        command = (
            f"python benchmarks/bench_state_rival.py --case {args.case} --physics {args.physics} "
            f"--seed {args.seed} --wells {args.wells} --drivers {args.drivers} --forms {args.forms}"
        )
        _markdown(args.markdown, command, rows)
    print(f"{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
