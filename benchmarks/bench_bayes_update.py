"""The cost of one ``bayes`` update with and without the well tests' variance factor, and
with the factor's prior pooled over the wells (``cal_pool=on``), side by side in one run
(issue 38: the factor must keep an update within 1.5 times its cost).

A well test's update also learns the factor from the standardised error of the forecast
the filter gave for it (``BayesianFilter._learn_calibration``); an MPFM reading's does not.
For each model and well count, six filters learn the same simulated stream, one
measurement per well per call, without the factor (``bayes:cal_prior=0``), with it and its
stated prior (``bayes:cal_pool=off``) and with its prior pooled over the filter's wells
(``bayes:cal_pool=on``), every measurement an MPFM reading or every one a well test; their
calls alternate (in a new random order every round), so a busy machine slows all six alike.
Prints the median cost per well-update (microseconds) and the ratios with/without,
pooled/without and pooled/with (``--methods`` names other ones). ``mm`` and ``ham`` update compiled (numba,
``vfm_core/learning/kernels.py``); ``lr`` and ``nn`` run the torch path.

    python benchmarks/bench_bayes_update.py [--models mm,ham,lr] [--wells 1,10]
        [--calls 300] [--warmup 20] [--seed 0]

One torch thread (as the ``vfm`` command and the service run).
"""

from __future__ import annotations

import argparse
import gc
import random
import statistics
import time
from dataclasses import replace

import numpy as np
import torch
from bench_speed import tile_wells  # benchmarks/ is on sys.path when a script runs

from vfm_core.data import Batch, make_batch, target_mask
from vfm_core.jobs.study import wells_of
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, LearningMethod, parse_method
from vfm_core.models import make_model
from vfm_core.observations import validate_frame
from vfm_core.runtime import configure
from vfm_core.simulate import simulate_field

#: measured rows per well the model is fitted on before the timed stream
HISTORY = 200
#: (label, method text): without the factor first, the ratios' denominator
METHODS = (
    ("without", "bayes:cal_prior=0"),
    ("with", "bayes:cal_pool=off"),
    ("pooled", "bayes:cal_pool=on"),
)


def _as_source(col: Batch, well_test: bool) -> Batch:
    """``col`` with every measurement flagged as a well test (or as an MPFM reading)."""
    assert col.well_test is not None
    flag = col.mask.clone() if well_test else torch.zeros_like(col.mask)
    return replace(col, well_test=flag)


def _stream(frame, n_wells: int, calls: int) -> tuple[Batch, list[Batch]]:
    """A history batch (``HISTORY`` rows per well) and ``calls`` one-row columns after it."""
    rows = np.flatnonzero(target_mask(frame, "all"))
    batch = tile_wells(make_batch(frame, wells_of(frame), rows), n_wells)
    rank = torch.cumsum(batch.mask.long(), 1)
    return batch.select(rank <= HISTORY), [
        batch.select(rank == HISTORY + 1 + k) for k in range(calls)
    ]


def _filter(model_name: str, text: str, history: Batch) -> LearningMethod:
    """``text`` bound to a fresh ``model_name``, fitted on ``history`` and started after it."""
    model = make_model(model_name, history.wells)
    method = parse_method(text)
    train = replace(DEFAULT_TRAIN[model_name], max_iter=100, early_stopping=False)
    method.bind(model, train=train, online=DEFAULT_ONLINE[model_name])
    method.fit(history)
    method.start(int(history.time_ns[history.mask].max()))
    return method


def update_costs(
    model_name: str,
    history: Batch,
    cols: list[Batch],
    warmup: int,
    methods: tuple[tuple[str, str], ...] = METHODS,
) -> dict[tuple[str, str], float]:
    """Median cost (us) of one call of each (method label, source), calls interleaved."""
    runs = {}
    for label, text in methods:
        for source in ("mpfm", "well_test"):
            stream = [_as_source(c, source == "well_test") for c in cols]
            runs[(label, source)] = (_filter(model_name, text, history), stream)
    keys = list(runs)
    times: dict[tuple[str, str], list[float]] = {key: [] for key in keys}
    order = random.Random(0)
    gc.disable()
    try:
        for k in range(len(cols)):
            # a new order every round: no run always first, or always after a heavier one
            for key in order.sample(keys, len(keys)):
                method, stream = runs[key]
                t0 = time.perf_counter()
                method.on_measurement(stream[k])
                dt = time.perf_counter() - t0
                if k >= warmup:
                    times[key].append(dt)
    finally:
        gc.enable()
    return {key: statistics.median(t) * 1e6 for key, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="mm,ham,lr")
    parser.add_argument("--wells", default="1,10", help="wells per call, e.g. 1,10")
    parser.add_argument("--calls", type=int, default=300, help="timed calls per figure")
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--methods",
        default=",".join(text for _, text in METHODS),
        help="three method texts: without the factor, with it, pooled",
    )
    args = parser.parse_args()
    texts = args.methods.split(",")
    if len(texts) != 3:
        parser.error("--methods takes three method texts")
    methods = tuple(zip(("without", "with", "pooled"), texts, strict=True))
    configure(1)  # torch's threads, glibc's malloc: as the vfm command (vfm_core.runtime)
    field = simulate_field(wells=10, years=2.0, seed=args.seed)
    frame = validate_frame(field.observations).frame
    print(
        f"{'model':<5} {'wells':>5} {'source':<9} {'without us':>10} {'with us':>8} "
        f"{'pooled us':>9} {'with/w.o.':>9} {'pool/w.o.':>9} {'pool/with':>9}"
        "   (median per well-update)"
    )
    for n_wells in (int(n) for n in args.wells.split(",")):
        history, cols = _stream(frame, n_wells, args.calls + args.warmup)
        for model_name in args.models.split(","):
            cost = update_costs(model_name, history, cols, args.warmup, methods)
            for source in ("mpfm", "well_test"):
                off, on, pool = (cost[(label, source)] / n_wells for label, _ in methods)
                print(
                    f"{model_name:<5} {n_wells:>5} {source:<9} {off:10.1f} {on:8.1f} "
                    f"{pool:9.1f} {on / off:9.2f} {pool / off:9.2f} {pool / on:9.2f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
