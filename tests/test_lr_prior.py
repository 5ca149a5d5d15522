"""``lr``'s slope prior in physical units (elasticities), against the old one per spread of
the well's own history (docs/guide/bayes.md, "lr's slopes as elasticities", session 53)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import DTYPE, make_batch
from vfm_core.errors import ConfigError
from vfm_core.learning import DEFAULT_TRAIN, fit_batch
from vfm_core.models import load_model, make_model, save_model

#: the choke law's elasticities of the synthetic well's rate: to the opening and to p_up
_E_CHOKE, _E_P_UP = 1.0, 0.85


#: lr's training before session 53: early stopping (the prior per spread is no regulariser)
_BEFORE = replace(DEFAULT_TRAIN["lr"], early_stopping=True)


def _well(seed: int, n_hist: int = 5) -> tuple[pd.DataFrame, int]:
    """A well with ``n_hist`` well tests at p_up 109-117 bar, then three at 100, 95 and 90
    bar (its other inputs stay where they were, with day-to-day noise); the rate follows
    the choke law's elasticities, with 1 % well-test noise (Sm3/h)."""
    rng = np.random.default_rng(seed)
    n = n_hist + 3
    p_up = np.r_[rng.uniform(109.0, 117.0, n_hist), [100.0, 95.0, 90.0]]
    choke = rng.uniform(0.50, 0.52, n)
    q = 1000.0 * (choke / 0.5) ** _E_CHOKE * (p_up / 113.0) ** _E_P_UP
    frame = pd.DataFrame(
        {
            "time": pd.date_range("2020-01-01", periods=n, freq="21D", tz="UTC"),
            "well": "W1",
            "choke": choke,
            "p_up": p_up,
            "p_down": 20.0 + 0.3 * rng.standard_normal(n),
            "t_up": 60.0 + 0.5 * rng.standard_normal(n),
            "eta_gas": 0.2 + 0.003 * rng.standard_normal(n),
            "eta_oil": 0.6 + 0.005 * rng.standard_normal(n),
            "q_total": q * (1.0 + 0.01 * rng.standard_normal(n)),
            "source": "well_test",
        }
    )
    return frame, n_hist


def _elasticities(model) -> np.ndarray:
    """The fitted slopes as elasticities d ln q / d ln x at the well's mean (x absolute)."""
    offset = torch.tensor([0.0, 0.0, 0.0, 273.15, 0.0, 0.0], dtype=DTYPE)
    e = model.w.detach() * (model.x_mean + offset).abs() / model.x_std
    return e[0].numpy()  # type: ignore[no-any-return]


def test_a_well_with_few_well_tests_extrapolates_less_wildly_off_its_range() -> None:
    """Five well tests over a narrow p_up range, then p_up falls 12-20 %: with the slopes'
    prior in elasticities the fitted elasticities stay of physical size and the error on
    the later well tests falls (eight draws of the noise; the old prior, per spread of the
    well's history, lets the day-to-day noise of t_up or the fractions carry steep slopes)."""
    errors: dict[str, list[float]] = {"spread": [], "elasticity": []}
    largest: dict[str, float] = {"spread": 0.0, "elasticity": 0.0}
    for seed in range(8):
        frame, n_hist = _well(seed)
        history = make_batch(frame, ["W1"], np.arange(n_hist))
        later = make_batch(frame, ["W1"], np.arange(n_hist, len(frame)))
        for slopes in errors:
            model = make_model("lr", ["W1"], slopes=slopes)
            fit_batch(model, history, _BEFORE if slopes == "spread" else DEFAULT_TRAIN["lr"])
            q = model.predict_batch(later)[0]
            errors[slopes].append(float((q / later.y[0] - 1.0).abs().mean()))
            largest[slopes] = max(largest[slopes], float(np.abs(_elasticities(model)).max()))
    spread, elasticity = np.mean(errors["spread"]), np.mean(errors["elasticity"])
    assert elasticity < 0.7 * spread, (errors, spread, elasticity)
    assert largest["elasticity"] < 1.5 < 5.0 < largest["spread"], largest


def test_the_slope_precision_is_the_inputs_magnitude_over_their_spread() -> None:
    frame, n_hist = _well(0)
    history = make_batch(frame, ["W1"], np.arange(n_hist))
    model = make_model("lr", ["W1"])
    model.setup(history)
    x = history.x[0, :n_hist]
    magnitude = x.mean(0).abs() + torch.tensor([0.0, 0.0, 0.0, 273.15, 0.0, 0.0], dtype=DTYPE)
    spread = x.std(0, unbiased=False)
    torch.testing.assert_close(model.w_prec[0], (magnitude / spread) ** 2)
    assert float(model.w_prec[0, 1]) > 100.0  # p_up: about 113 bar over 2-3 bar
    old = make_model("lr", ["W1"], slopes="spread")
    old.setup(history)
    assert torch.equal(old.w_prec, torch.ones_like(old.w_prec))
    assert old.hyper == {"seed": 0, "slopes": "spread"} and model.hyper == {"seed": 0}


def test_a_fraction_near_zero_keeps_the_prior_per_spread() -> None:
    """Where an input's spread exceeds its magnitude the precision is 1 (never weaker than
    the old prior)."""
    frame, n_hist = _well(1)
    frame.loc[: n_hist - 1, "eta_gas"] = [0.0, 0.0, 0.0, 0.0, 0.05]  # mean 0.01, sd 0.02
    model = make_model("lr", ["W1"])
    model.setup(make_batch(frame, ["W1"], np.arange(n_hist)))
    assert float(model.w_prec[0, 4]) == 1.0
    assert bool((model.w_prec[0, [0, 1, 2, 3, 5]] > 1.0).all())


def test_a_model_file_from_before_the_prior_loads_with_the_old_precision(tmp_path) -> None:
    frame, n_hist = _well(2)
    history = make_batch(frame, ["W1"], np.arange(n_hist))
    model = make_model("lr", ["W1"])
    fit_batch(model, history, DEFAULT_TRAIN["lr"])
    path = save_model(model, tmp_path / "lr.pt")
    again = load_model(path)
    torch.testing.assert_close(again.w_prec, model.w_prec)
    payload = torch.load(path, weights_only=True)
    del payload["state"]["w_prec"]  # as saved before session 53: fitted under the old prior
    torch.save(payload, path)
    old = load_model(path)
    assert torch.equal(old.w_prec, torch.ones_like(old.w_prec))
    torch.testing.assert_close(old.predict_batch(history), model.predict_batch(history))


def test_an_unknown_slope_prior_is_refused_with_the_choices() -> None:
    with pytest.raises(ConfigError, match="elasticity, spread"):
        make_model("lr", ["W1"], slopes="log")
