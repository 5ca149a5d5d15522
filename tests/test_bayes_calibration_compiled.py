"""The well tests' variance factor on the compiled filter (issue 38): the compiled update
computes each well test's standardised forecast error in its own pass, from the state the
filter had before the batch, instead of a second forecast in Python. The errors, the
factor and the intervals must be those of the reference, ``BayesianFilter._forecast_errors``
(the torch path's, and what the compiled filter used before).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from vfm_core.data import Batch, make_batch, target_mask
from vfm_core.features import standard_features
from vfm_core.jobs.study import wells_of
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, parse_method
from vfm_core.learning.bayes import BayesianFilter
from vfm_core.models import make_model
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

DAY_NS = 86_400 * 10**9
#: the filter state the factor and the intervals are read from
_STATE = ("_P", "_last", "_noise", "_h", "_scale", "_cal", "_started", "_run")


@pytest.fixture(scope="module")
def field() -> Batch:
    """Three simulated wells with a drifting discharge coefficient, every measured row."""
    sim = simulate_field(wells=3, years=2.0, seed=23, hidden=["erosion"])
    frame = validate_frame(sim.observations).frame
    frame = frame.join(standard_features(frame))  # the effects' features
    rows = np.flatnonzero(target_mask(frame, "all"))
    return make_batch(frame, wells_of(frame), rows, extra_columns=("throughput_years", "years_on"))


def _days(field: Batch, rank: torch.Tensor, first: int) -> list[Batch]:
    """The rows after each well's ``first`` - 1 ones, one batch per calendar day (as the
    study learns: a day's MPFM readings and well tests of a well in one batch), with a
    well test 40 % off on well 0 every fifth day it has one (refused: its error counts at
    the gate), a zero rate on well 1's first well test (not taken, not counted)."""
    later = field.mask & (rank >= first)
    day = torch.div(field.time_ns, DAY_NS, rounding_mode="floor")
    out = []
    seen = [0, 0]
    for d in torch.unique(day[later]).tolist():
        batch = field.select(later & (day == d))
        assert batch.well_test is not None
        y = batch.y.clone()
        for w in (0, 1):
            tests = torch.nonzero(batch.mask[w] & batch.well_test[w]).flatten()
            if len(tests):
                seen[w] += 1
                if w == 0 and seen[0] % 5 == 0:
                    y[0, tests[-1]] *= 1.4
                if w == 1 and seen[1] == 1:
                    y[1, tests[0]] = 0.0
        out.append(replace(batch, y=y))
    return out


def _fitted(
    monkeypatch: pytest.MonkeyPatch, field: Batch, name: str, effects: list[str], text: str
) -> tuple[BayesianFilter, list[Batch]]:
    """``text`` on ``name`` fitted on each well's first 150 rows (well 2: none, its filter
    starts at its first measurement), and the later rows by day."""
    monkeypatch.setenv("VFM_FIT_KERNEL", "0")  # the same fit for every run of a test
    rank = torch.cumsum(field.mask.long(), 1)
    history = field.select((rank <= 150) & torch.tensor([True, True, False]).unsqueeze(1))
    model = make_model(name, history.wells, effects=effects)
    method = parse_method(text)
    assert isinstance(method, BayesianFilter)
    train = replace(DEFAULT_TRAIN[name], max_iter=60, early_stopping=False)
    method.bind(model, train=train, online=DEFAULT_ONLINE[name])
    method.fit(history)
    method.start(int(history.time_ns[history.mask].max()))
    return method, _days(field, rank, 151)


def _as_well_tests(batch: Batch) -> Batch:
    """``batch`` with every row a well test (the intervals the factor widens)."""
    return replace(batch, well_test=batch.mask.clone())


def _state(method: BayesianFilter) -> dict[str, torch.Tensor]:
    state = {k: getattr(method, k).clone() for k in _STATE}
    for i, p in enumerate(method.model.parameters()):
        state[f"param{i}"] = p.detach().clone()
    return state


def _close(a: torch.Tensor, b: torch.Tensor, rel: float, key: str) -> None:
    if a.dtype in (torch.bool, torch.int64):
        assert torch.equal(a, b), key
    else:
        scale = max(float(b.abs().max()), 1e-300)
        assert torch.allclose(a, b, rtol=0, atol=rel * scale, equal_nan=True), key


def _old_path(method: BayesianFilter, handed: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """Make ``method`` learn as the compiled filter did before: the errors from a forecast
    in Python (``_forecast_errors``, kept in ``handed``) before the compiled update, then
    ``_learn_calibration``."""
    compiled_learn = method._compiled_learn

    def learn(batch: Batch, wanted: bool) -> tuple[torch.Tensor, bool]:
        errors = method._forecast_errors(batch) if wanted else None
        changed, learned = compiled_learn(batch, False)
        assert not learned
        if errors is not None:
            handed.append(errors)
            method._learn_calibration(*errors)
        return changed, errors is not None

    method._compiled_learn = learn  # type: ignore[method-assign]


@pytest.mark.parametrize(
    ("name", "effects"), [("mm", []), ("ham", []), ("mm", ["mpfm_bias"]), ("hem", ["erosion"])]
)
def test_compiled_errors_factor_and_intervals_are_the_reference_ones(
    monkeypatch: pytest.MonkeyPatch, field: Batch, name: str, effects: list[str]
) -> None:
    """One measurement a well per batch, then day by day (MPFM readings before a well
    test in one batch: the compiled pass forecasts that well test before its updates; a
    well test first: from its own step), with an outlier refused, a zero rate and a well
    whose filter starts mid-way: a filter that learns the old way (a forecast in Python,
    ``_forecast_errors``, then the compiled update) and one that learns the errors in its
    compiled pass hold the same factor statistics after every batch (so the same errors),
    and end with the same state and intervals."""
    new, days = _fitted(monkeypatch, field, name, effects, "bayes")
    old, _ = _fitted(monkeypatch, field, name, effects, "bayes")
    assert new.compiled and old.compiled
    handed: list[tuple[np.ndarray, np.ndarray]] = []
    _old_path(old, handed)
    first_row, later_row = 0, 0  # well tests counted at a well's first row of a batch, later
    half = len(days) // 2
    for batch in _columns(days[:half]) + days[half:]:
        before = len(handed)
        new.on_measurement(batch)
        old.on_measurement(batch)
        _close(new._cal, old._cal, 1e-12, "cal")
        _close(new._scale, old._scale, 1e-12, "scale")
        if len(handed) > before:
            live = handed[-1][1]
            later = np.arange(live.shape[1]) > np.argmax(batch.mask.numpy(), axis=1)[:, None]
            first_row += int((live & ~later).sum())
            later_row += int((live & later).sum())
    capped = sum(int((z2[live] >= 36.0).sum()) for z2, live in handed)
    # the errors were learned from, and the batch shapes that tell the two ways apart
    assert first_row >= 10 and later_row >= 3 and capped >= 1, (first_row, later_row, capped)
    assert float(new._cal[:, 1, 0].min()) > 2  # every well, the one started mid-way too
    one, two = _state(new), _state(old)
    for key in one:
        _close(one[key], two[key], 1e-12, key)
    probe = _as_well_tests(days[-1])
    for a, b in zip(new.predict(probe), old.predict(probe), strict=True):
        _close(a, b, 1e-12, "forecast")


def test_compiled_factor_matches_the_torch_filter(
    monkeypatch: pytest.MonkeyPatch, field: Batch
) -> None:
    """``mm`` learning the same days compiled and on the torch path (``VFM_KERNELS=0``:
    ``_forecast_errors`` and ``_update``): the same variance factor and intervals, to the
    rounding by which the two paths' updates differ."""
    monkeypatch.setenv("VFM_KERNELS", "1")
    fast, days = _fitted(monkeypatch, field, "mm", [], "bayes")
    monkeypatch.setenv("VFM_KERNELS", "0")
    slow, _ = _fitted(monkeypatch, field, "mm", [], "bayes")
    assert not slow.compiled
    for batch in days:
        monkeypatch.setenv("VFM_KERNELS", "1")
        fast.on_measurement(batch)
        monkeypatch.setenv("VFM_KERNELS", "0")
        slow.on_measurement(batch)
    assert float(slow._cal[:, 1, 0].min()) > 2
    monkeypatch.setenv("VFM_KERNELS", "1")
    one, two = _state(fast), _state(slow)
    for key in one:
        _close(one[key], two[key], 1e-9, key)
    probe = _as_well_tests(days[-1])
    for a, b in zip(fast.predict(probe), slow.predict(probe), strict=True):
        _close(a, b, 1e-9, "forecast")


def _old_torch_path(method: BayesianFilter, handed: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """Make ``method`` learn as the torch path did before: the errors from a forecast in
    Python (``_forecast_errors``, kept in ``handed``) before the updates, whatever the
    batch."""

    def learn(batch: Batch, wanted: bool) -> tuple[torch.Tensor, bool]:
        errors = method._forecast_errors(batch) if wanted else None
        changed = torch.zeros(batch.n_wells, dtype=torch.bool)
        counts = batch.count()
        for k in range(int(counts.max()) if counts.numel() else 0):
            changed |= method._update(batch.select(torch.cumsum(batch.mask.long(), 1) == k + 1))
        if errors is not None:
            handed.append(errors)
            method._learn_calibration(*errors)
        return changed, errors is not None

    method._torch_learn = learn  # type: ignore[method-assign]


def _columns(days: list[Batch]) -> list[Batch]:
    """The same rows one measurement a well per batch (as the service learns): the k-th
    row of every well's day together."""
    out = []
    for day in days:
        rank = torch.cumsum(day.mask.long(), 1)
        out += [day.select(rank == k + 1) for k in range(int(rank.max()))]
    return out


@pytest.mark.parametrize("name", ["mm", "lr"])
def test_the_torch_path_takes_the_errors_from_its_update(
    monkeypatch: pytest.MonkeyPatch, field: Batch, name: str
) -> None:
    """On the torch path (``VFM_KERNELS=0``; ``lr`` has no compiled filter), a batch of
    one measurement a well takes its well test's error from the update's own forecast,
    a day's batch from a forecast first: either way the factor statistics after every
    batch, the state and the intervals are those of the old path (a forecast in Python
    first, always), to rounding."""
    monkeypatch.setenv("VFM_KERNELS", "0")
    new, days = _fitted(monkeypatch, field, name, [], "bayes")
    old, _ = _fitted(monkeypatch, field, name, [], "bayes")
    assert not new.compiled and not old.compiled
    handed: list[tuple[np.ndarray, np.ndarray]] = []
    _old_torch_path(old, handed)
    paths = {"forecast": 0, "update": 0}  # well tests counted by either way
    forecast, own = new._forecast_errors, new._own_errors

    def by_forecast(batch: Batch) -> tuple[np.ndarray, np.ndarray] | None:
        errors = forecast(batch)
        paths["forecast"] += 0 if errors is None else int(errors[1].sum())
        return errors

    def by_update(*args: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        errors = own(*args)
        paths["update"] += int(errors[1].sum())
        return errors

    monkeypatch.setattr(new, "_forecast_errors", by_forecast)
    monkeypatch.setattr(new, "_own_errors", by_update)
    half = len(days) // 2
    batches = _columns(days[:half]) + days[half:]  # one a well, then by day
    for batch in batches:
        new.on_measurement(batch)
        old.on_measurement(batch)
        _close(new._cal, old._cal, 1e-12, "cal")
        _close(new._scale, old._scale, 1e-12, "scale")
    assert paths["update"] >= 10 and paths["forecast"] >= 3, paths
    assert paths["update"] + paths["forecast"] == sum(int(h[1].sum()) for h in handed)
    assert float(new._cal[:, 1, 0].min()) > 2
    one, two = _state(new), _state(old)
    for key in one:
        _close(one[key], two[key], 1e-12, key)
    probe = _as_well_tests(days[-1])
    for a, b in zip(new.predict(probe), old.predict(probe), strict=True):
        _close(a, b, 1e-12, "forecast")


def test_without_the_factor_the_compiled_pass_computes_no_errors(
    monkeypatch: pytest.MonkeyPatch, field: Batch
) -> None:
    """``cal_prior=0``: no errors asked of the compiled pass, the factor stays 1, and the
    filter learns as with the factor (the factor widens intervals only)."""
    plain, days = _fitted(monkeypatch, field, "mm", [], "bayes:cal_prior=0")
    rule, _ = _fitted(monkeypatch, field, "mm", [], "bayes")
    asked: list[bool] = []
    compiled_learn = plain._compiled_learn

    def spy(batch: Batch, wanted: bool) -> tuple[torch.Tensor, bool]:
        asked.append(wanted)
        return compiled_learn(batch, wanted)

    monkeypatch.setattr(plain, "_compiled_learn", spy)
    for batch in days:
        plain.on_measurement(batch)
        rule.on_measurement(batch)
    assert asked and not any(asked)
    assert float(plain._cal.abs().max()) == 0.0
    assert float(rule._cal[:, 1, 0].min()) > 2
    probe = _as_well_tests(days[-1])
    a, b = plain.predict(probe), rule.predict(probe)
    assert torch.equal(a.mean, b.mean)
    assert not torch.allclose(a.p95, b.p95)  # the factor moved the intervals
