"""The per-well streaming learner reproduces the study's prequential run and survives a restart."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import target_mask
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import run_prequential
from vfm_core.learning.streaming import WellLearner
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field


@pytest.fixture(scope="module")
def one_well() -> pd.DataFrame:
    return simulate_field(
        wells=1, years=1.2, seed=9, start="2018-04-01", hidden=["erosion"]
    ).observations


@pytest.mark.parametrize("method", ["ol", "pbl:30d"])
def test_streaming_matches_prequential_study(one_well: pd.DataFrame, method: str) -> None:
    split = pd.Timestamp("2019-01-01", tz="UTC")
    study = run_prequential(one_well, "mm", method, targets="all", split=split)
    rows = one_well[target_mask(one_well, "all")]
    hist, live = rows[rows["time"] < split], rows[rows["time"] >= split]
    learner = WellLearner("W01", "mm", method)
    learner.fit_history(
        torch.tensor(hist[list(INPUT_COLUMNS)].to_numpy()),
        torch.tensor(hist["q_total"].to_numpy()),
        torch.tensor(pd.DatetimeIndex(hist["time"]).as_unit("ns").asi8),
    )
    learner.method.start(split.value)  # the study's calendar of retrains
    predicted = []
    for _, row in live.iterrows():
        predicted.append(
            learner.predict(row[list(INPUT_COLUMNS)].tolist(), when=row["time"])["q_total"]
        )
        learner.learn(row[list(INPUT_COLUMNS)].tolist(), row["q_total"], row["time"])
    np.testing.assert_allclose(predicted, study.predictions["predicted"].to_numpy(), rtol=1e-6)


def test_checkpoint_restores_the_same_model(one_well: pd.DataFrame) -> None:
    rows = one_well[target_mask(one_well, "all")]
    x = torch.tensor(rows[list(INPUT_COLUMNS)].to_numpy())
    y = torch.tensor(rows["q_total"].to_numpy())
    t = torch.tensor(pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8)
    learner = WellLearner("W01", "ham", "ol")
    learner.fit_history(x[:300], y[:300], t[:300])
    for i in range(300, 320):
        learner.learn(x[i].tolist(), float(y[i]), rows["time"].iloc[i])
    clone = WellLearner.restore(learner.checkpoint())
    assert clone.version == learner.version == 21
    for i in range(320, 330):  # they keep learning identically (optimiser state included)
        for lrn in (learner, clone):
            lrn.learn(x[i].tolist(), float(y[i]), rows["time"].iloc[i])
    assert clone.predict(x[400].tolist()) == learner.predict(x[400].tolist())
    assert set(learner.physical_parameters()) >= {"rho_oil", "kappa", "a_max"}


def test_priors_only_learner_waits_for_data_and_rejects_bad_blobs() -> None:
    learner = WellLearner("W9", "mm", "ol")
    assert learner.predict([0.5, 100.0, 30.0, 60.0, 0.1, 0.6])["q_total"] is None
    learner.learn(
        [0.5, 100.0, 30.0, 60.0, 0.1, 0.6], 20_000.0, pd.Timestamp("2020-01-01", tz="UTC")
    )
    q = learner.predict([0.5, 100.0, 30.0, 60.0, 0.1, 0.6])["q_total"]
    assert q is not None and abs(q - 20_000.0) / 20_000.0 < 0.05
    with pytest.raises(ConfigError, match="checkpoint"):
        WellLearner.restore(b"not a checkpoint")
    with pytest.raises(ConfigError, match="shares parameters"):
        WellLearner("W9", "mtl", "ol")


def _old_format(learner: WellLearner, version: int) -> bytes:
    """The learner's checkpoint written as formats 1 or 2 did (before the method protocol):
    the method's state in fields of the learner; format 1 also had no sources or features."""
    import io
    import json

    p = torch.load(io.BytesIO(learner.checkpoint()), weights_only=True)
    state, memory = p.pop("method_state"), p.pop("memory")
    p.update(
        format=f"vfm-well-learner/{version}",
        optimizer=state.get("optimizer", {}),
        iterations=state["iterations"],
        next_retrain=(
            pd.Timestamp(state["next_due"], tz="UTC").isoformat() if state.get("next_due") else ""
        ),
        x=memory["x"],
        y=memory["y"],
        t=memory["t"],
    )
    if version == 2:
        p.update(w=memory["w"], e=memory["e"])
    else:
        for key in ("effects", "features"):
            p.pop(key)
    assert json.loads(p["train"])  # plain JSON, as then
    buf = io.BytesIO()
    torch.save(p, buf)
    return buf.getvalue()


@pytest.mark.parametrize("method", ["ol", "pbl:30d"])
def test_earlier_checkpoint_formats_still_restore(method: str) -> None:
    """Format 1 (before effects: no sources, no features) and 2 (before the method protocol)."""
    learner = WellLearner("W01", "mm", method)
    x = torch.tensor([[0.5, 60.0, 20.0, 70.0, 0.1, 0.6]] * 20, dtype=torch.float64)
    y = torch.linspace(900.0, 1100.0, 20, dtype=torch.float64)
    t = torch.arange(20, dtype=torch.int64) * 3_600_000_000_000 + 1_500_000_000_000_000_000
    learner.fit_history(x[:15], y[:15], t[:15])
    for i in range(15, 18):  # ol: the optimiser now has momentum, which must come back
        learner.learn(x[i].tolist(), float(y[i]), pd.Timestamp(int(t[i]), tz="UTC"))
    sample = [0.5, 60.0, 20.0, 70.0, 0.1, 0.6]
    for version in (1, 2):
        back = WellLearner.restore(_old_format(learner, version))
        assert back.predict(sample) == learner.predict(sample)
        assert back.remembered == 18 and not bool(back.memory.well_test.any())
        assert (
            back.method.state_dict()["next_due"] == learner.method.state_dict().get("next_due")
            if method != "ol"
            else True
        )
        # both keep learning alike (the optimiser's moments and the calendar came back)
        twin = WellLearner.restore(learner.checkpoint())
        for lrn in (back, twin):
            lrn.learn(x[18].tolist(), float(y[18]), pd.Timestamp(int(t[18]), tz="UTC"))
        assert back.predict(sample) == twin.predict(sample)
        if version == 1:
            # the features are rebuilt from the remembered rows: 17 hours on stream at the last
            assert float(back.memory.features[17, 0]) == pytest.approx(17 / (365.25 * 24))


def test_memory_keeps_the_latest_rows_within_its_bound(one_well: pd.DataFrame) -> None:
    """remember_max: appending overshoots by a tenth at most, then keeps the latest rows;
    a checkpoint stores only those, and a restored learner is cut back when it is set."""
    from service.config import ModelSettings
    from service.engine.learners import apply_budget
    from vfm_core.features import FeatureTracker
    from vfm_core.learning.memory import WellMemory

    memory = WellMemory("W", FeatureTracker.names, (), max_rows=100)
    for i in range(135):
        x = torch.full((1, 6), float(i), dtype=torch.float64)
        memory.append(x, torch.tensor([float(i)], dtype=torch.float64), torch.tensor([i]))
        assert len(memory) <= 110
    # cut back to the latest 100 whenever it reached 111 (last at row 132), then two more
    assert memory.t.tolist() == list(range(33, 135))
    memory.set_max_rows(20)
    assert memory.y.tolist() == [float(i) for i in range(115, 135)]
    memory.set_max_rows(None)
    memory.append(torch.zeros(50, 6, dtype=torch.float64), torch.zeros(50), torch.arange(50))
    assert len(memory) == 70  # no bound: every row

    rows = one_well[target_mask(one_well, "all")]
    x = torch.tensor(rows[list(INPUT_COLUMNS)].to_numpy())
    y = torch.tensor(rows["q_total"].to_numpy())
    t = torch.tensor(pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8)
    learner = WellLearner("W01", "mm", "ol", remember_max=50)
    learner.fit_history(x[:40], y[:40], t[:40])
    for i in range(40, 140):
        learner.learn(x[i].tolist(), float(y[i]), rows["time"].iloc[i])
        assert learner.remembered <= 55
    assert learner.memory.t[-1] == t[139] and learner.remembered >= 50
    unbounded = WellLearner.restore(learner.checkpoint())
    assert unbounded.remembered == learner.remembered  # the checkpoint held only those
    restored = apply_budget(unbounded, ModelSettings(remember_max=10))
    assert restored.remembered == 10 and restored.memory.t.tolist() == t[130:140].tolist()
