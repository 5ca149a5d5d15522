"""The per-well streaming learner reproduces the study's prequential run and survives a restart."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import target_mask
from vfm_core.errors import ConfigError
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field
from vfm_core.streaming import WellLearner
from vfm_core.jobs.study import run_prequential


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
    if method.startswith("pbl"):
        learner.next_retrain = split + pd.Timedelta(days=30)  # the study's calendar
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


def test_a_first_format_checkpoint_still_restores() -> None:
    """Checkpoints written before effects existed (format 1: no sources, no features)."""
    import io

    from vfm_core.streaming import WellLearner

    learner = WellLearner("W01", "mm", "ol")
    x = torch.tensor([[0.5, 60.0, 20.0, 70.0, 0.1, 0.6]] * 20, dtype=torch.float64)
    y = torch.linspace(900.0, 1100.0, 20, dtype=torch.float64)
    t = torch.arange(20, dtype=torch.int64) * 3_600_000_000_000 + 1_500_000_000_000_000_000
    learner.fit_history(x, y, t)
    payload = torch.load(io.BytesIO(learner.checkpoint()), weights_only=True)
    for key in ("effects", "features", "w", "e"):
        payload.pop(key)
    payload["format"] = "vfm-well-learner/1"
    buf = io.BytesIO()
    torch.save(payload, buf)
    back = WellLearner.restore(buf.getvalue())
    sample = [0.5, 60.0, 20.0, 70.0, 0.1, 0.6]
    assert back.predict(sample) == learner.predict(sample)
    assert back.remembered == 20 and not bool(back._w.any())
    # the features are rebuilt from the remembered rows: 19 hours on stream at the last row
    assert float(back._e[-1, 0]) == pytest.approx(19 / (365.25 * 24))
