"""The study's replay of ``bayes:cal_pool=on`` (a method that couples the wells): in time
order around the well tests (the rounds it uses) against one round per distinct time (the
rounds before session 56), beside ``bayes`` without the pool, side by side in one run.

Only the well tests' forecast errors enter the other wells' priors, so the forecasts of the
two replays are the same to the digit (``tests/test_bayes_pooled.py``); this prints what the
fewer rounds save. For each model: ``run_prequential`` of a simulated field in case 1 (MPFM
readings and well tests: the case the time order slowed most), the three replays in turn,
``--repeats`` times (the first a warm-up: compiled kernels, caches), the median wall time of
the rest, the ratios to the unpooled replay, and the number of rounds of each order.

    python benchmarks/bench_pool_replay.py [--models mm,ham] [--wells 6] [--years 3]
        [--repeats 3] [--seed 11]

One torch thread (as the ``vfm`` command runs).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pandas as pd

from vfm_core.data import make_batch, target_mask
from vfm_core.jobs import study
from vfm_core.jobs.study import run_prequential
from vfm_core.learning.bayes import BayesianFilter
from vfm_core.observations import validate_frame
from vfm_core.runtime import configure
from vfm_core.simulate import simulate_field

REPLAYS = ("unpooled", "pooled, around the well tests", "pooled, one round per time")


@contextmanager
def _one_round_per_time(on: bool) -> Iterator[None]:
    """While ``on``: the pooled filter names no coupling samples, so the study replays it in
    one round per distinct time (its order before session 56)."""
    saved = BayesianFilter.coupling_samples
    if on:
        BayesianFilter.coupling_samples = lambda self, batch: None  # type: ignore[method-assign]
    try:
        yield
    finally:
        BayesianFilter.coupling_samples = saved  # type: ignore[method-assign]


def _rounds(frame: pd.DataFrame) -> tuple[int, int, int]:
    """The rounds of the study's test span in case 1 (from the default split): each well's
    k-th sample, around the well tests, and one per distinct time."""
    wells = study.wells_of(frame)
    split = study.resolve_split("all", None, frame)
    keep = target_mask(frame, "all") & (frame["time"] >= split).to_numpy()
    test = make_batch(frame, wells, np.flatnonzero(keep))
    around = study._coupled_rounds(test, test.well_test & test.mask)
    return test.x.shape[1], len(around), len(study._day_rounds(test, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", default="mm,ham")
    parser.add_argument("--wells", type=int, default=6)
    parser.add_argument("--years", type=float, default=3.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=11)
    args = parser.parse_args()
    configure()
    frame = validate_frame(
        simulate_field(wells=args.wells, years=args.years, seed=args.seed).observations
    ).frame
    per_well, around, by_time = _rounds(frame)
    print(
        f"simulate_field(wells={args.wells}, years={args.years}, seed={args.seed}), case 1: "
        f"rounds {per_well} (each well's k-th sample), {around} (around the well tests), "
        f"{by_time} (one per distinct time)"
    )
    for model in args.models.split(","):
        times: dict[str, list[float]] = {r: [] for r in REPLAYS}
        for _ in range(args.repeats):
            for replay in REPLAYS:
                method = "bayes" if replay == "unpooled" else "bayes:cal_pool=on"
                with _one_round_per_time(replay.endswith("per time")):
                    t0 = time.perf_counter()
                    run_prequential(frame, model, method, targets="all", seed=args.seed)
                    times[replay].append(time.perf_counter() - t0)
        med = {r: statistics.median(v[1:] or v) for r, v in times.items()}
        base = med["unpooled"]
        cells = ", ".join(f"{r} {med[r]:.1f} s ({med[r] / base:.2f}x)" for r in REPLAYS)
        print(f"{model}: {cells}", flush=True)


if __name__ == "__main__":
    main()
