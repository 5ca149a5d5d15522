"""One contract suite over every registered learning method (``vfm_core.learning.METHODS``).

A new method passes these by registering itself with an ``example`` text; nothing here
names a method, except where a test checks a property that only some methods promise
(``per_measurement``, ``intervals``, ``streaming``).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.checks import METHOD_CHECKS, check_method, check_method_runs_every_model
from vfm_core.data import make_batch, target_mask
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import wells_of
from vfm_core.learning import METHODS, FrameMemory, LearningMethod, parse_method
from vfm_core.models import MODELS, make_model
from vfm_core.simulate import simulate_field

EXAMPLES = [cls.example for cls in METHODS.values()]
SPLIT = pd.Timestamp("2019-01-01", tz="UTC")


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    return simulate_field(wells=2, years=1.6, seed=11, start="2017-09-01").observations


#: every registered method with every method check (the one running every model apart)
CASES = [
    (text, check)
    for text in EXAMPLES
    for check in METHOD_CHECKS
    if check is not check_method_runs_every_model
]


@pytest.mark.parametrize(
    ("text", "check"),
    CASES,
    ids=[f"{t}-{c.__name__.removeprefix('check_method_')}" for t, c in CASES],
)
def test_method_contract(text: str, check, field) -> None:
    """The public check suite (vfm_core.checks) over every registered method: its text
    parses back, NaN before its fit, inputs unchanged, a state round trip continues
    identically, same seed same result, wells independent, it follows a shifted well, and
    the streaming learner reproduces the study (or refuses a method it cannot run)."""
    assert check_method(text, checks=[check], frame=field) == [check.__name__]


@pytest.mark.parametrize("model", list(MODELS))
@pytest.mark.parametrize("text", EXAMPLES)
def test_every_method_runs_every_model(text: str, model: str, field) -> None:
    """Every method binds to every registered model, including one without parameters to
    filter (the benchmark ``last``), predicts, and learns without error."""
    check_method_runs_every_model(text, field, models=[model])


def test_an_unknown_method_lists_the_valid_ones() -> None:
    with pytest.raises(ConfigError) as err:
        parse_method("kalman")
    for key in METHODS:
        assert key in str(err.value)


def test_the_method_checks_can_fail(field, monkeypatch: pytest.MonkeyPatch) -> None:
    """A method whose copy restored from its state drifts from the original is caught."""
    from vfm_core.checks import check_method_state_round_trip
    from vfm_core.learning import OnlineLearning

    restore = OnlineLearning.load_state_dict

    def forgetful(self, state) -> None:
        restore(self, state)
        with torch.no_grad():
            for p in self.model.parameters():
                p.add_(1e-3)

    monkeypatch.setattr(OnlineLearning, "load_state_dict", forgetful)
    with pytest.raises(AssertionError, match="restored copy predicts differently"):
        check_method("ol", checks=[check_method_state_round_trip], frame=field)


def test_a_retrain_chooses_a_stale_iteration_count_again() -> None:
    """A count chosen by early stopping on few measurements (here one step, as a young
    well's few measurements can give) is chosen again by early stopping once the well holds
    twice as many; the retrain then fits the eroded choke better than one that keeps the
    stale count, and a count chosen on enough measurements is kept."""
    from vfm_core.learning.method import RECHOOSE_GROWTH

    frame = simulate_field(
        wells=2, years=2.0, seed=3, start="2017-01-01", hidden=["erosion"]
    ).observations
    is_target = target_mask(frame, "all")
    wells = wells_of(frame)
    memory = FrameMemory(frame, is_target, wells)
    start = pd.Timestamp("2017-07-01", tz="UTC").value
    end = int(frame["time"].max().value) + 1
    recent = np.flatnonzero(
        is_target & (frame["time"] >= frame["time"].max() - pd.Timedelta("90D"))
    )
    probe = make_batch(frame, wells, recent)

    def retrained(*chosen_on: int) -> tuple[LearningMethod, float]:
        method = parse_method("pbl:30d").bind(make_model("mm", wells))
        method.fit(memory.batch(start))
        method.iterations = torch.ones(len(wells), dtype=torch.int64)
        method.chosen_on = torch.tensor(chosen_on, dtype=torch.int64)
        method.retrain(memory, end)
        q = method.predict(probe).mean
        return method, float(((q - probe.y).abs() / probe.y)[probe.mask].mean())

    counts = memory.batch(end).count()
    enough = int(counts.max()) // RECHOOSE_GROWTH + 1
    stale, err_stale = retrained(1, 1)
    kept, err_kept = retrained(enough, enough)
    assert torch.equal(stale.chosen_on, counts) and bool((stale.iterations > 1).all())
    assert bool((kept.iterations == 1).all())  # chosen on more than half: not stale yet
    assert err_stale < 0.8 * err_kept, (err_stale, err_kept)
    # choosing one well's count again leaves the other's retrain as it was, to the bit
    one, _ = retrained(1, enough)
    assert int(one.iterations[0]) > 1 and int(one.iterations[1]) == 1
    z_one, z_kept = one.model.phys.z.detach(), kept.model.phys.z.detach()  # type: ignore[union-attr]
    assert torch.equal(z_one[1], z_kept[1]) and not torch.equal(z_one[0], z_kept[0])
