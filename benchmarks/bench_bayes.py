"""The Bayesian learning method against online and periodic learning, on simulated fields
with each hidden effect, in both of the paper's cases: MAPE (mean over wells), coverage of
the 90 % intervals, their median width, the noise floor, and the run time of each run.

The noise floor is the MAPE of the noise-free truth (``field.truth.parquet``'s ``q_true``)
read against the same measurements: no model can beat it on average.

    python benchmarks/bench_bayes.py [--hidden none,erosion,...] [--models mm,ham]
        [--methods ol,pbl:14d,bayes] [--cases well_test,all] [--wells 10 --years 5 --seed 0]
        [--physics sachdeva|bernoulli|gilbert] [--json out.json]

The floor is taken on the rows each run scored (the study's own split), so it holds for
fields of any length (before session 48 it used the split of a 5-year field, and shorter
fields printed nan).

On two shared cores the full default (7 fields x 2 cases x 2 models x 3 methods) takes
about an hour; ``pbl:14d`` with ``ham`` in case 1 is the slowest run.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pandas as pd

from vfm_core.errors import ConfigError
from vfm_core.jobs.study import run_prequential
from vfm_core.runtime import configure
from vfm_core.simulate import simulate_field

EFFECTS = ("none", "erosion", "valve", "real_gas", "slip", "mpfm_bias", "critical_ratio")


def _well_mean(values: pd.Series, wells: pd.Series) -> float:
    return float(values.groupby(wells.to_numpy()).mean().mean() * 100.0)


def _floor(pr: pd.DataFrame, q_true: pd.Series) -> float:
    """The noise floor (%) of a run's scored rows: the truth's MAPE against the measured
    rates, mean over wells."""
    key = pd.MultiIndex.from_arrays([pr["time"], pr["well"]])
    measured = pr["measured"].to_numpy(dtype=float)
    ape = np.abs(q_true.reindex(key).to_numpy(dtype=float) - measured) / measured
    return _well_mean(pd.Series(ape), pr["well"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hidden", default=",".join(EFFECTS))
    parser.add_argument("--models", default="mm,ham")
    parser.add_argument("--methods", default="ol,pbl:14d,bayes")
    parser.add_argument("--cases", default="well_test,all")
    parser.add_argument("--wells", type=int, default=10)
    parser.add_argument("--years", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--physics", default="sachdeva", help="the truth (vfm simulate --physics)")
    parser.add_argument("--json", default=None, help="also write the rows to this file")
    args = parser.parse_args()
    configure(1)  # torch's threads, glibc's malloc: as the vfm command (vfm_core.runtime)
    rows = []
    print(
        f"{'hidden':<15} {'case':<9} {'floor %':>7} {'model':<5} {'method':<10} {'MAPE %':>7} "
        f"{'cov90 %':>7} {'width90 %':>9} {'time s':>7}"
    )
    for hidden in args.hidden.split(","):
        try:
            field = simulate_field(
                wells=args.wells,
                years=args.years,
                seed=args.seed,
                hidden=[hidden],
                physics=args.physics,
            )
        except ConfigError as exc:  # an effect that the chosen truth has of its own
            print(f"{hidden:<15} skipped: {exc}", flush=True)
            continue
        obs, truth = field.observations, field.truth_samples
        q_true = truth.set_index(["time", "well"])["q_true"]
        for case in args.cases.split(","):
            for model in args.models.split(","):
                for method in args.methods.split(","):
                    started = time.perf_counter()
                    pr = run_prequential(obs, model, method, targets=case).predictions
                    seconds = time.perf_counter() - started
                    floor = _floor(pr, q_true)
                    ape = (pr["predicted"] - pr["measured"]).abs() / pr["measured"]
                    row = {
                        "hidden": hidden,
                        "case": case,
                        "floor": floor,
                        "model": model,
                        "method": method,
                        "mape": _well_mean(ape, pr["well"]),
                        "coverage90": None,
                        "width90": None,
                        "seconds": seconds,
                    }
                    if "predicted_p05" in pr:
                        ok = pr["predicted_p05"].notna()
                        inside = (pr["measured"] >= pr["predicted_p05"]) & (
                            pr["measured"] <= pr["predicted_p95"]
                        )
                        width = (pr["predicted_p95"] - pr["predicted_p05"]) / pr["predicted"]
                        row["coverage90"] = float(inside[ok].mean() * 100.0)
                        row["width90"] = float(width[ok].median() * 100.0)
                    rows.append(row)
                    cov = "" if row["coverage90"] is None else f"{row['coverage90']:7.1f}"
                    wid = "" if row["width90"] is None else f"{row['width90']:9.2f}"
                    print(
                        f"{hidden:<15} {case:<9} {floor:7.2f} {model:<5} {method:<10} "
                        f"{row['mape']:7.2f} {cov:>7} {wid:>9} {seconds:7.0f}",
                        flush=True,
                    )
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
