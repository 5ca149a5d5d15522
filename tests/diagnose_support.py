"""The simulated fields and their diagnoses that the diagnosis tests share
(``tests/test_diagnose.py``, ``tests/test_diagnose_library.py``): 3 wells over 3 years from
2017, split 2019-01-01, the online run with ``pbl:3650d`` (fit once: fast), each field and
diagnosis made once a test process (cached)."""

from __future__ import annotations

from functools import cache

import pandas as pd

from vfm_core.data import target_mask
from vfm_core.jobs.diagnose import Diagnosis, run_diagnosis
from vfm_core.jobs.study import mape
from vfm_core.simulate import SimulatedField, simulate_field

SPLIT = "2019-01-01"
METHOD = "pbl:3650d"


@cache
def field(hidden: str, seed: int = 1, wells: int = 3) -> SimulatedField:
    """The simulated field with ``hidden`` (``"none"``: clean)."""
    return simulate_field(
        wells=wells,
        years=3.0,
        seed=seed,
        start="2017-01-01",
        hidden=[] if hidden == "none" else [hidden],
    )


def floor_of(truth_rate: pd.Series, frame: pd.DataFrame, field: SimulatedField) -> float:
    """The MAPE % of the true rate (times the meter's own drift) after the split."""
    scored = target_mask(frame, "all") & (frame["time"] >= pd.Timestamp(SPLIT, tz="UTC")).to_numpy()
    meter = field.truth_samples["mpfm_factor"].where(frame["source"] == "mpfm", 1.0)
    return mape((truth_rate * meter)[scored], frame["q_total"][scored])


def floor(field: SimulatedField) -> float:
    """The noise floor of ``field``: :func:`floor_of` its true rate."""
    return floor_of(field.truth_samples["q_true"], field.observations, field)


#: each diagnosis's progress events (fraction, text), by (hidden, seed, wells)
PROGRESS: dict[tuple[str, int, int], list[tuple[float, str]]] = {}


@cache
def diagnose(hidden: str, seed: int = 1, wells: int = 3) -> Diagnosis:
    """``mm``'s diagnosis of :func:`field`, its progress kept in :data:`PROGRESS`."""
    events: list[tuple[float, str]] = []
    PROGRESS[(hidden, seed, wells)] = events
    return run_diagnosis(
        field(hidden, seed, wells).observations,
        "mm",
        method=METHOD,
        split=SPLIT,
        progress=lambda f, text: events.append((f, text)),
    )
