"""A young well's features when its MPFM reports often: the cost of one measured rate and
the next sample's features while the throughput scale is still the median of the first 90
days' rates, for a growing number of those rates.

The tracker keeps the early rates sorted (``bisect.insort``), so the median is read in
O(1); the figure beside it is what recomputing ``np.median`` over the list after every
rate (the tracker before) costs on the same list, in the same run.

    python benchmarks/bench_young_well.py [--rates 1000,10000,100000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vfm_core.features import FeatureTracker


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", default="1000,10000,100000", help="early rates held")
    parser.add_argument("--repeat", type=int, default=200, help="measurements timed at each size")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    t0 = 1_500_000_000 * 10**9
    print("early rates | measured + next sample, tracker | np.median of the list | ratio")
    for n in (int(v) for v in args.rates.split(",")):
        tracker = FeatureTracker()
        tracker.advance(t0, 0.1, 0.8)
        step = 60 * 10**9  # a rate a minute: n of them stay within the first 90 days
        rates = rng.lognormal(4.0, 0.5, n + args.repeat).tolist()
        for i in range(n):
            tracker.measured(t0 + i * step, rates[i])
        unsorted = rates[:n]
        t = t0 + n * step
        start = time.perf_counter()
        for q in rates[n:]:
            t += step
            tracker.measured(t, q)
            tracker.advance(t + 1, 0.1, 0.8)
        ours = (time.perf_counter() - start) / args.repeat
        start = time.perf_counter()
        for q in rates[n:]:
            unsorted.append(q)
            float(np.median(unsorted))
        before = (time.perf_counter() - start) / args.repeat
        assert tracker._scale() == float(np.median(unsorted))
        print(
            f"{n:>11,} | {ours * 1e6:>10.1f} us | {before * 1e6:>10.1f} us | {before / ours:,.0f}x"
        )


if __name__ == "__main__":
    main()
