"""``bayes`` on a shared model refits the network under its filter (the rule and its reason:
docs/guide/bayes.md, "A shared model's network: refitted under the filter").

The filter of ``mtl`` carries a posterior over each well's task vector only; the shared
layers are the same for every well, so only a joint fit on every well's measurements can
move them. Every 14 days the model is refitted (MAP, warm-started, as ``pbl`` retrains) and
the filter starts again from the refit.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import target_mask
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import mape, run_prequential, wells_of
from vfm_core.learning import DEFAULT_TRAIN, bayes, parse_method
from vfm_core.learning.memory import FrameMemory
from vfm_core.models import make_model
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

T0 = 1_500_000_000_000_000_000  # epoch ns
DAY = 86_400_000_000_000  # ns


def _due_after_start(text: str, model_name: str) -> int | None:
    """The next refit of ``text`` bound to a fresh two-well ``model_name``, started at T0
    (ns after T0; None: no refit)."""
    method = parse_method(text).bind(make_model(model_name, ["A", "B"]))
    method.start(T0)
    due = method.next_due()
    return None if due is None else due - T0


def test_the_refit_is_on_for_shared_models_and_can_be_set() -> None:
    """``auto`` (the default) refits a shared model every 14 days and no other; ``off``
    and a span set it; a bad span says what is wrong; ``period`` (read by the service)
    says the same, also before binding."""
    assert _due_after_start("bayes", "mtl") == 14 * DAY
    for name in ("nn", "hem", "ham", "mm", "lr"):
        assert _due_after_start("bayes", name) is None, name
    assert _due_after_start("bayes:refresh=off", "mtl") is None
    assert _due_after_start("bayes:refresh=0", "mtl") is None
    assert _due_after_start("bayes:refresh=30d", "nn") == 30 * DAY
    assert parse_method("bayes:refresh=30d").period == pd.Timedelta(days=30)
    assert parse_method("bayes:refresh=off").period is None
    assert parse_method("bayes").bind(make_model("ham", ["A"])).period is None
    assert parse_method("bayes").bind(make_model("mtl", ["A"])).period == pd.Timedelta(days=14)
    with pytest.raises(ConfigError, match="refresh period 'soon' is not a positive time span"):
        parse_method("bayes:refresh=soon")


def test_missed_refits_each_run_and_the_calendar_survives_a_checkpoint(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A gap of 100 days (seven refits due) runs the seven refits, each on the
    measurements before its due time, as ``pbl`` retrains; the filter starts again once,
    after the last (its two Kalman passes over the history); the next refit falls 14 days
    later, also after a restore."""
    frame = validate_frame(simulate_field(wells=2, years=1.0, seed=23).observations).frame
    wells = wells_of(frame)
    memory = FrameMemory(frame, target_mask(frame, "all"), wells)
    t_split = int(pd.Timestamp("2016-07-01", tz="UTC").value)
    model = make_model("mtl", wells)
    method = parse_method("bayes").bind(
        model, train=replace(DEFAULT_TRAIN["mtl"], max_iter=60, early_stopping=False)
    )
    method.fit(memory.batch(t_split))
    method.start(t_split)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    assert not method.retrain_due(memory, torch.full((2,), t_split + DAY)).any()
    assert method.n_retrains == 0
    passes = []
    history_pass = bayes._history_pass

    def counted(*args: Any) -> Any:
        passes.append(1)
        return history_pass(*args)

    monkeypatch.setattr(bayes, "_history_pass", counted)
    changed = method.retrain_due(memory, torch.full((2,), t_split + 100 * DAY))
    assert changed.all() and method.n_retrains == 7
    assert method.retrains == [t_split + k * 14 * DAY for k in range(1, 8)]
    assert len(passes) == 2  # one start of the filter: two passes over the history
    assert method.next_due() == t_split + 112 * DAY
    # the shared layers moved (refitted on the 98 more days), not only the task vectors
    assert not torch.allclose(model.state_dict()["w_in"], before["w_in"])
    twin = parse_method("bayes").bind(make_model("mtl", wells))
    twin.load_state_dict(method.state_dict())
    assert twin.next_due() == t_split + 112 * DAY


def test_a_wearing_field_is_followed_better_with_the_refit() -> None:
    """Case 2 (well tests only) on a field whose chokes wear: with the shared layers as
    first fitted, the filter on the task vectors cannot follow (the error grows); refitted
    every 14 days under the filter it learns the field, about as well as ``pbl:14d``
    alone retraining (and the filter's intervals stay)."""
    field = simulate_field(
        wells=3, years=2.5, seed=11, start="2016-01-01", hidden=["erosion:rate=0.08"]
    ).observations
    runs = {
        m: run_prequential(field, "mtl", m, targets="well_test")
        for m in ("bayes:refresh=off", "bayes", "pbl:14d")
    }
    score = {
        m: mape(r.predictions["predicted"], r.predictions["measured"]) for m, r in runs.items()
    }
    on, off = runs["bayes"], runs["bayes:refresh=off"]
    # the refit ran, on the 14-day calendar from the split, and moved the shared layers
    assert off.updates == [] and len(on.updates) >= 10
    gaps = np.diff([t.value for t in on.updates])
    assert (gaps > 0).all() and (gaps % (14 * DAY) == 0).all()
    assert on.final_model is not None and off.final_model is not None
    shared_on = on.final_model.state_dict()["w_in"]
    assert (shared_on - off.final_model.state_dict()["w_in"]).abs().max() > 1e-3
    # ... and the model learned the wear: a much smaller error than without the refit
    assert score["bayes"] < 0.6 * score["bayes:refresh=off"], score
    assert score["bayes"] < 1.25 * score["pbl:14d"], score
    assert on.predictions["predicted_p95"].notna().all()
