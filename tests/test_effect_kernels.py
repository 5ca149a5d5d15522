"""Effects that multiply the rate, and the two that change the flux (real gas, slip), run
on the compiled path (issue 37, item 2) and compute what the torch path computes.

- ``ol`` on ``mm`` with each compiled library effect (and three at once): after 60 updates
  the parameters, Adam's moments and step counts and the predictions equal the torch
  path's to 1e-10 relative; so do ``bayes``'s parameters, filter state and forecasts
  (``mm`` and ``ham``);
- the many-well path (``learn_many`` / ``predict_many``) likewise;
- a derivative broken on purpose (dF/dp, or the flux effects' dq/dp or dq/dtheta, off by
  0.1 %) fails the comparison: it can fail;
- the compiled rate with real gas and slip and its derivatives (through Z, through the
  slip factor, and by the effects' parameters) equal autograd's through the torch model;
- ``suggest`` (a generic correction in one driver: linear, log, season, or fixed) runs
  there too, as a rate factor of per-sample columns the effect computes; its compiled
  factor and derivatives equal autograd's through ``Suggest.output_factor``, in and out of
  the clamps;
- ``critical_ratio`` runs there too: the kernels solve Sachdeva's ratio by the same
  bisection (equal to ``physics.sachdeva_critical_ratio``) and, like the torch hook, pass no
  gradient through it (dq/dp_cr times 1 - weight, dq/dweight through y_c - p_cr); a broken
  weight derivative fails the comparison;
- effects without a compiled form (a user's subclass that rewrites a hook, two effects of
  one flux kind, the critical ratio beside real gas) keep the torch path.
"""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import Batch, make_batch, target_mask
from vfm_core.effects import EffectInputs, Erosion, RealGas, Slip, add_features
from vfm_core.jobs.study import wells_of
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, kernels, parse_method
from vfm_core.learning import _mm_numba as numba_kernels
from vfm_core.learning.online import OnlineSettings
from vfm_core.models import make_model
from vfm_core.observations import validate_frame
from vfm_core.schema import INPUT_COLUMNS, TARGET
from vfm_core.simulate import simulate_field
from vfm_core.units import bar_to_pa, degc_to_k

pytestmark = pytest.mark.skipif(not kernels.kernels_enabled(), reason="numba is not installed")

#: a step inside the simulated year of the stream (erosion's optional C_D step)
_STEP = "erosion:step_at=2016-09-01"
#: suggested corrections, one of each form (linear, log, season) and one fixed
_T_UP = "suggest:driver=t_up:x0=60:scale=10"
_LOG = "suggest:driver=p_ratio:form=log"
_SEASON = "suggest:driver=day_of_year"
_FIXED = "suggest:driver=water_cut:k=0.2"
#: a large step, so that the critical ratio's weight (whose gradient is small on these
#: wells) moves well clear of the comparison's rounding
_FAST = OnlineSettings(lr=1e-1, steps=3)


@pytest.fixture(scope="module")
def frame() -> pd.DataFrame:
    """Three simulated wells over a year (MPFM rows and well tests), every feature column."""
    frame = validate_frame(simulate_field(wells=3, years=1.0, seed=8).observations).frame
    return add_features(frame, ["erosion", "erosion_time", "mpfm_bias"])


def _stream(frame: pd.DataFrame, effects: list[str]) -> tuple[Batch, list[Batch]]:
    """A history of 150 measurements per well, then 60 one-sample columns."""
    probe = make_model("mm", ["w"], effects=effects)
    rows = np.flatnonzero(target_mask(frame, "all"))
    batch = make_batch(frame, wells_of(frame), rows, probe.extra_columns)
    rank = torch.cumsum(batch.mask.long(), 1)
    return batch.select(rank <= 150), [batch.select(rank == 151 + k) for k in range(60)]


def _close(fast: torch.Tensor, slow: torch.Tensor, what: str, rtol: float = 1e-10) -> None:
    """Equal to ``rtol`` relative to the tensor's own scale (NaN where the other has NaN)."""
    assert fast.shape == slow.shape, what
    nan = torch.isnan(slow)
    assert torch.equal(nan, torch.isnan(fast)), what
    fast, slow = fast.to(torch.float64), slow.to(torch.float64)
    scale = float(slow[~nan].abs().max()) if bool((~nan).any()) else 0.0
    err = float((fast[~nan] - slow[~nan]).abs().max()) if bool((~nan).any()) else 0.0
    assert err <= rtol * max(scale, 1e-300), f"{what}: off by {err:.3g} of {scale:.3g}"


def _online_run(
    monkeypatch: pytest.MonkeyPatch,
    flag: str,
    stream: tuple[Batch, list[Batch]],
    effects: list[str],
    online: OnlineSettings,
    name: str = "mm",
) -> tuple[dict[str, torch.Tensor], list[torch.Tensor]]:
    monkeypatch.setenv("VFM_KERNELS", flag)
    monkeypatch.setenv("VFM_FIT_KERNEL", "0")  # the same initial fit for both
    history, cols = stream
    model = make_model(name, history.wells, effects=effects)
    method = parse_method("ol")
    method.bind(
        model, train=replace(DEFAULT_TRAIN[name], max_iter=60, early_stopping=False), online=online
    )
    method.fit(history)
    method.start(int(history.time_ns[history.mask].max()))
    applies = kernels.effects_applies if name == "mm" else kernels.hybrid_effects_applies
    assert applies(model) is (flag == "1")
    answers = []
    for k, col in enumerate(cols):
        if k % 3 == 1:  # the middle well has no measurement this time: it is held still
            col = col.select(col.mask & torch.tensor([True, False, True]).unsqueeze(1))
        method.on_measurement(col)  # type: ignore[attr-defined]
        answers.append(method.predict(col)[0].clone())
    assert method._compiled is True  # type: ignore[attr-defined]
    if name == "mm":
        assert method._effects is True  # type: ignore[attr-defined]
    else:
        assert method._hybrid is not None  # type: ignore[attr-defined]
    state: dict[str, torch.Tensor] = {}
    for i, p in enumerate(model.parameters()):
        state[f"param{i}"] = p.detach().clone()
        for key, value in method._opt.state.get(p, {}).items():  # type: ignore[attr-defined]
            state[f"param{i}.{key}"] = value.clone()
    return state, answers


def _compare(fast: tuple, slow: tuple) -> None:
    (fast_state, fast_answers), (slow_state, slow_answers) = fast, slow
    assert set(fast_state) == set(slow_state)
    for key in slow_state:
        _close(fast_state[key], slow_state[key], key)
    for k, (a, b) in enumerate(zip(fast_answers, slow_answers, strict=True)):
        _close(a, b, f"answer {k}")


@pytest.mark.parametrize(
    ("effects", "online"),
    [
        (["erosion"], DEFAULT_ONLINE["mm"]),
        ([_STEP], DEFAULT_ONLINE["mm"]),
        (["erosion_time"], OnlineSettings(optimizer="sgd", lr=1e-3, steps=10)),
        (["valve"], DEFAULT_ONLINE["mm"]),
        (["valve_equal_percentage"], DEFAULT_ONLINE["mm"]),
        (["valve_sigmoid"], OnlineSettings(lr=1e-1, steps=3, max_grad_norm=0.05)),  # clipped
        (["mpfm_bias"], DEFAULT_ONLINE["mm"]),
        (["erosion", "valve_quick_opening", "mpfm_bias"], DEFAULT_ONLINE["mm"]),
        (["real_gas"], DEFAULT_ONLINE["mm"]),
        (["slip"], DEFAULT_ONLINE["mm"]),
        (["slip"], OnlineSettings(optimizer="sgd", lr=1e-3, steps=10)),
        (["real_gas", "slip", "valve"], DEFAULT_ONLINE["mm"]),
        (["mpfm_bias", "slip", "real_gas"], OnlineSettings(lr=1e-1, steps=3, max_grad_norm=0.05)),
        ([_T_UP], DEFAULT_ONLINE["mm"]),
        ([_LOG], OnlineSettings(optimizer="sgd", lr=1e-3, steps=10)),
        ([_SEASON], DEFAULT_ONLINE["mm"]),
        (["suggest:driver=years_on", "slip"], OnlineSettings(lr=1e-1, steps=3, max_grad_norm=0.05)),
        (["erosion", _FIXED], DEFAULT_ONLINE["mm"]),
        (["critical_ratio"], _FAST),
        (["critical_ratio", "slip", "mpfm_bias"], OnlineSettings(lr=1e-1, steps=3)),
    ],
)
def test_ol_with_an_effect_compiled_matches_the_torch_steps(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame, effects: list[str], online
) -> None:
    stream = _stream(frame, effects)
    fast = _online_run(monkeypatch, "1", stream, effects, online)
    slow = _online_run(monkeypatch, "0", stream, effects, online)
    # the effect learned something (its parameters left the prior mean for some well)
    n_phys = 1
    moved = [v for k, v in slow[0].items() if k.startswith("param") and "." not in k][n_phys:]
    assert any(float(v.abs().max()) > 1e-6 for v in moved)
    _compare(fast, slow)


@pytest.mark.parametrize(
    ("name", "effects"),
    [
        ("ham", ["erosion"]),
        ("ham", ["valve", "mpfm_bias"]),
        ("hem", ["valve_convex"]),
        ("ham", ["real_gas", "slip"]),
        ("hem", ["slip", "erosion"]),
        ("hem", ["real_gas"]),
        ("ham", [_T_UP]),
        ("hem", [_SEASON, "valve"]),
        ("ham", ["critical_ratio"]),
        ("hem", ["critical_ratio", "erosion"]),
    ],
)
def test_ol_on_a_hybrid_with_effects_compiled_matches_the_torch_steps(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame, name: str, effects: list[str]
) -> None:
    stream = _stream(frame, effects)
    online = replace(DEFAULT_ONLINE[name], steps=3)
    fast = _online_run(monkeypatch, "1", stream, effects, online, name)
    slow = _online_run(monkeypatch, "0", stream, effects, online, name)
    _compare(fast, slow)


#: the compiled factor, as it is (the tests below replace the module's name)
_FACTOR = numba_kernels.effect_factor


def _broken_factor(*args: object) -> float:
    """:func:`_mm_numba.effect_factor` with every derivative 0.1 % too large."""
    value = _FACTOR(*args)
    d_f = args[-1]
    assert isinstance(d_f, np.ndarray)
    d_f *= 1.001
    return value  # type: ignore[no-any-return]


@pytest.mark.parametrize("broken", [False, True])
@pytest.mark.parametrize("effects", [["erosion", "mpfm_bias"], [_T_UP]])
def test_a_broken_derivative_fails_the_comparison(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame, broken: bool, effects: list[str]
) -> None:
    """The steps as Python (numba's ``py_func``) over the compiled factor: exact as they
    are (the comparison passes), and off with the derivative broken (it fails)."""
    stream = _stream(frame, effects)
    stream = (stream[0], stream[1][:20])
    slow = _online_run(monkeypatch, "0", stream, effects, DEFAULT_ONLINE["mm"])
    kernel = kernels._kernel()
    assert kernel is not None
    monkeypatch.setattr(kernel, "effect_online", numba_kernels.effect_online.py_func)
    monkeypatch.setattr(numba_kernels, "_factor_at", numba_kernels._factor_at.py_func)
    if broken:
        monkeypatch.setattr(numba_kernels, "effect_factor", _broken_factor)
    fast = _online_run(monkeypatch, "1", stream, effects, DEFAULT_ONLINE["mm"])
    if broken:
        with pytest.raises(AssertionError, match="off by"):
            _compare(fast, slow)
    else:
        _compare(fast, slow)


def _bayes_run(
    monkeypatch: pytest.MonkeyPatch,
    flag: str,
    stream: tuple[Batch, list[Batch]],
    effects: list[str],
    name: str,
) -> tuple[dict[str, torch.Tensor], list[torch.Tensor]]:
    monkeypatch.setenv("VFM_KERNELS", flag)
    monkeypatch.setenv("VFM_FIT_KERNEL", "0")
    history, cols = stream
    model = make_model(name, history.wells, effects=effects)
    method = parse_method("bayes")
    method.bind(
        model,
        train=replace(DEFAULT_TRAIN[name], max_iter=60, early_stopping=False),
        online=DEFAULT_ONLINE[name],
    )
    method.fit(history)
    method.start(int(history.time_ns[history.mask].max()))
    assert method.compiled is (flag == "1")  # type: ignore[attr-defined]
    answers = []
    for k, col in enumerate(cols):
        y = col.y.clone()
        if k % 3 == 1:
            col = col.select(col.mask & torch.tensor([True, False, True]).unsqueeze(1))
        if k % 7 == 3:
            y[0] *= 4.0  # an outlier on well 0: refused
        answers.append(method.on_measurement(replace(col, y=y)).clone())  # type: ignore[attr-defined]
        answers += [t.clone() for t in method.predict(col)]
    state = {n: getattr(method, n).clone() for n in ("_P", "_h", "_noise", "_scale", "_last")}
    state.update({f"count_{k}": v.clone() for k, v in method.stats().items()})  # type: ignore[attr-defined]
    for i, p in enumerate(model.parameters()):
        state[f"param{i}"] = p.detach().clone()
    assert int(state["count_updates"].min()) >= len(cols) // 2  # the filter took most
    return state, answers


@pytest.mark.parametrize(
    ("name", "effects"),
    [
        ("mm", ["erosion"]),
        ("mm", [_STEP, "valve"]),
        ("mm", ["valve_convex", "mpfm_bias"]),
        ("ham", ["erosion_time"]),
        ("hem", ["mpfm_bias"]),
        ("mm", ["real_gas"]),
        ("mm", ["slip", "erosion"]),
        ("ham", ["real_gas", "slip"]),
        ("hem", ["slip"]),
        ("mm", ["suggest:driver=p_up"]),
        ("mm", [_LOG, "mpfm_bias"]),
        ("ham", [_SEASON]),
        ("hem", [_FIXED]),
        ("mm", ["critical_ratio"]),
        ("ham", ["critical_ratio", "slip"]),
    ],
)
def test_bayes_with_an_effect_compiled_matches_the_torch_filter(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame, name: str, effects: list[str]
) -> None:
    stream = _stream(frame, effects)
    _compare(
        _bayes_run(monkeypatch, "1", stream, effects, name),
        _bayes_run(monkeypatch, "0", stream, effects, name),
    )


def test_a_broken_filter_derivative_fails_the_comparison(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame
) -> None:
    effects = ["mpfm_bias"]
    stream = _stream(frame, effects)
    stream = (stream[0], stream[1][:20])
    slow = _bayes_run(monkeypatch, "0", stream, effects, "mm")
    kernel = kernels._kernel()
    assert kernel is not None
    monkeypatch.setattr(kernel, "bayes", numba_kernels.bayes.py_func)
    monkeypatch.setattr(numba_kernels, "log_rate_grad", numba_kernels.log_rate_grad.py_func)
    monkeypatch.setattr(numba_kernels, "_factor_at", numba_kernels._factor_at.py_func)
    monkeypatch.setattr(numba_kernels, "effect_factor", _broken_factor)
    fast = _bayes_run(monkeypatch, "1", stream, effects, "mm")
    with pytest.raises(AssertionError, match="off by"):
        _compare(fast, slow)


def _many_run(
    monkeypatch: pytest.MonkeyPatch,
    flag: str,
    frame: pd.DataFrame,
    method: str,
    effect: str | None,
    name: str,
) -> list[list[float]]:
    """Four learners of one well's history (one more so the group is stacked), 30 calls of
    ``learn_many`` and ``predict_many``; every answer and the parameters at the end."""
    import copy

    from vfm_core.learning.streaming import WellLearner, learn_many, predict_many

    monkeypatch.setenv("VFM_KERNELS", flag)
    monkeypatch.setenv("VFM_FIT_KERNEL", "0")
    well = wells_of(frame)[0]
    rows = frame[(frame["well"] == well) & frame[TARGET].notna()]
    hist, live = rows.iloc[:150], rows.iloc[150:180]
    learner = WellLearner(
        "W",
        name,
        method,
        train=replace(DEFAULT_TRAIN[name], max_iter=60, early_stopping=False),
        effects=[effect] if effect else [],
    )
    learner.fit_history(
        torch.tensor(hist[list(INPUT_COLUMNS)].to_numpy(dtype=float)),
        torch.tensor(hist[TARGET].to_numpy(dtype=float)),
        torch.tensor(pd.DatetimeIndex(hist["time"]).as_unit("ns").asi8),
        well_test=torch.tensor(hist["source"].eq("well_test").to_numpy()),
    )
    many = [copy.deepcopy(learner) for _ in range(4)]
    answers: list[list[float]] = []
    for k in range(len(live)):
        row = live.iloc[k]
        x = [float(row[c]) for c in INPUT_COLUMNS]
        xs = [[v * (1.0 + 0.01 * i) for v in x] for i in range(4)]  # each well its own
        when = pd.Timestamp(row["time"])
        learn_many(many, xs, [float(row[TARGET])] * 4, [when] * 4, [str(row["source"])] * 4)
        for out in predict_many(many, xs, [when] * 4):
            answers.append([float("nan") if v is None else float(v) for v in out.values()])
    for m in many:
        answers.append([float(v) for p in m.model.parameters() for v in p.detach().flatten()])
    return answers


@pytest.mark.parametrize(
    ("name", "method", "effect"),
    [
        ("mm", "ol", "valve"),
        ("mm", "bayes", "erosion"),
        ("ham", "ol", "mpfm_bias"),
        ("mm", "ol", "real_gas"),
        ("mm", "bayes", "slip"),
        ("ham", "ol", "slip"),
        ("mm", "ol", _T_UP),
        ("ham", "bayes", _SEASON),
        ("mm", "bayes", "critical_ratio"),
        ("mm", "ol", None),  # the plain models' compiled steps, on the same route
        ("ham", "ol", None),
    ],
)
def test_the_many_well_path_with_an_effect_matches_the_torch_path(
    monkeypatch: pytest.MonkeyPatch,
    frame: pd.DataFrame,
    name: str,
    method: str,
    effect: str | None,
) -> None:
    fast = _many_run(monkeypatch, "1", frame, method, effect, name)
    slow = _many_run(monkeypatch, "0", frame, method, effect, name)
    for k, (a, b) in enumerate(zip(fast, slow, strict=True)):
        _close(torch.tensor(a), torch.tensor(b), f"row {k}")


class _OwnErosion(Erosion):
    """A user's variant that rewrites the hook: other arithmetic than the compiled form."""

    name = "own_erosion"

    def area_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        return 1.0 + p["rate"] * inputs.feature(self.basis) ** 2


class _OwnSlip(Slip):
    """A second slip effect under another name (its hooks Slip's): the kernels take one."""

    name = "own_slip"


@pytest.mark.parametrize("effect", [_OwnErosion])
def test_effects_without_a_compiled_form_keep_the_torch_path(effect: object) -> None:
    model = make_model("mm", ["a", "b"], effects=[effect])
    assert model.effects[0].compiled_factor() is None
    assert kernels.compiled_effects(model) is None and not kernels.effects_applies(model)
    method = parse_method("ol")
    method.bind(model)
    method._optimiser()  # type: ignore[attr-defined]
    assert not method._compiled and not method._effects  # type: ignore[attr-defined]
    filt = parse_method("bayes")
    filt.bind(model)
    assert not filt.compiled  # type: ignore[attr-defined]
    # with one of them beside a compiled effect, the whole model stays on torch
    mixed = make_model("mm", ["a"], effects=["erosion", effect])
    assert kernels.compiled_effects(mixed) is None


def test_the_critical_ratio_beside_real_gas_keeps_the_torch_path() -> None:
    """The kernels solve the critical ratio with the ideal gas: beside real gas, torch."""
    assert kernels.compiled_effects(make_model("mm", ["a"], effects=["critical_ratio"])) == "mm"
    both = make_model("mm", ["a"], effects=["critical_ratio", "real_gas"])
    assert kernels.compiled_effects(both) is None


def test_the_compiled_critical_ratio_equals_the_torch_bisection() -> None:
    """Sachdeva's ratio by the kernels' bisection equals physics.sachdeva_critical_ratio
    over random samples (dry gas to wet, light to heavy gas)."""
    from vfm_core import physics as ph

    gen = np.random.default_rng(4)
    n = 200
    eta_gas = np.concatenate([[0.0, 1e-12, 1.0], gen.uniform(0, 1, n - 3)])
    rho_g1 = gen.uniform(5, 150, n)
    v_liq = gen.uniform(0, 1.2e-3, n)
    kappa = gen.uniform(1.1, 1.4, n)
    want = ph.sachdeva_critical_ratio(
        torch.tensor(eta_gas), torch.tensor(rho_g1), torch.tensor(v_liq), torch.tensor(kappa),
        iterations=30,
    ).numpy()  # fmt: skip
    got = np.array([
        numba_kernels.sachdeva_critical_ratio(eta_gas[i], rho_g1[i], v_liq[i], kappa[i], 30)
        for i in range(n)
    ])  # fmt: skip
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert float(want.min()) < 0.3 and float(want.max()) > 0.5  # a spread of ratios


_RATE_AT = numba_kernels._rate_at


def _broken_weight(*args: object) -> float:
    """:func:`_mm_numba._rate_at` with the critical ratio's dq/dweight 0.1 % too large."""
    value = _RATE_AT(*args)
    fx, scratch = args[0], args[2]
    for t in range(fx[0].shape[0]):  # type: ignore[index]
        if fx[0][t, 0] == numba_kernels.FX_CRITICAL:  # type: ignore[index]
            scratch[2][fx[0][t, 1]] *= 1.001  # type: ignore[index]
    return value  # type: ignore[no-any-return]


@pytest.mark.parametrize("broken", [False, True])
def test_a_broken_critical_ratio_derivative_fails_the_comparison(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame, broken: bool
) -> None:
    effects = ["critical_ratio"]
    stream = _stream(frame, effects)
    stream = (stream[0], stream[1][:20])
    slow = _online_run(monkeypatch, "0", stream, effects, _FAST)
    kernel = kernels._kernel()
    assert kernel is not None
    monkeypatch.setattr(kernel, "effect_online", numba_kernels.effect_online.py_func)
    monkeypatch.setattr(numba_kernels, "_rate_at", _broken_weight if broken else _RATE_AT)
    fast = _online_run(monkeypatch, "1", stream, effects, _FAST)
    if broken:
        with pytest.raises(AssertionError, match="off by"):
            _compare(fast, slow)
    else:
        _compare(fast, slow)


def test_two_effects_of_one_flux_kind_keep_the_torch_path() -> None:
    """Two slip exponents add in torch; the kernels take one per kind: torch it is."""
    assert _OwnSlip().compiled_factor() is not None
    assert kernels.compiled_effects(make_model("mm", ["a"], effects=["slip", _OwnSlip])) is None
    assert kernels.compiled_effects(make_model("ham", ["a"], effects=["slip", "real_gas"])) == (
        "ham"
    )


def test_the_kernels_switch_off_for_effects_too(monkeypatch: pytest.MonkeyPatch) -> None:
    model = make_model("mm", ["a"], effects=["erosion"])
    assert kernels.compiled_effects(model) == "mm" and kernels.effects_applies(model)
    monkeypatch.setenv("VFM_KERNELS", "0")
    assert not kernels.effects_applies(model)
    assert os.environ["VFM_KERNELS"] == "0"


def test_the_compiled_codes_are_the_kernels() -> None:
    """The codes an effect's compiled form names are the ones the kernels branch on."""
    from vfm_core.effects import CompiledFactor

    assert (
        CompiledFactor.EROSION,
        CompiledFactor.VALVE,
        CompiledFactor.FAMILY,
        CompiledFactor.BIAS,
        CompiledFactor.GAS,
        CompiledFactor.SLIP,
        CompiledFactor.SUGGEST,
        CompiledFactor.CRITICAL,
    ) == (
        numba_kernels.FX_EROSION,
        numba_kernels.FX_VALVE,
        numba_kernels.FX_FAMILY,
        numba_kernels.FX_BIAS,
        numba_kernels.FX_GAS,
        numba_kernels.FX_SLIP,
        numba_kernels.FX_SUGGEST,
        numba_kernels.FX_CRITICAL,
    )
    assert kernels._SUGGEST == CompiledFactor.SUGGEST


@pytest.mark.parametrize(
    "spec",
    [
        "suggest:driver=t_up:x0=60:scale=10",
        "suggest:driver=p_up",
        "suggest:driver=water_cut:form=log",
        "suggest:driver=years_on:k=-0.04",
        "suggest:driver=p_ratio:form=log:scale=0.01",  # large steps: the clamp at +-5
        "suggest:driver=choke:x0=0.9:scale=0.05",  # 1 + k x below 0.05: the floor
        "suggest:driver=day_of_year",
        "suggest:driver=t_up:k=0.3",
        "suggest:driver=day_of_year:k_sin=0.1:k_cos=-0.2",
    ],
)
def test_the_compiled_suggest_factor_and_its_derivatives_equal_autograd(spec: str) -> None:
    """Each sample's compiled factor (from the effect's own columns) and dF / dk equal
    ``Suggest.output_factor`` and autograd's through it, for k on both sides of the clamps."""
    from vfm_core.effects import CompiledFactor, resolve_effect

    effect = resolve_effect(spec)()
    form = effect.compiled_factor()
    assert form is not None and form.code == CompiledFactor.SUGGEST
    gen = torch.Generator().manual_seed(5)
    n = 40
    # the six inputs in file units (fraction, bar, bar, degC, -, -), as a batch has them
    low = torch.tensor([0.0, 60.0, 10.0, 30.0, 0.0, 0.0], dtype=torch.float64)
    span = torch.tensor([1.0, 80.0, 40.0, 60.0, 0.3, 0.5], dtype=torch.float64)
    x = low + span * torch.rand(1, n, 6, generator=gen, dtype=torch.float64)
    time_ns = torch.randint(0, 2**62, (1, n), generator=gen)
    years = torch.rand(1, n, generator=gen, dtype=torch.float64) * 5
    inputs = EffectInputs(
        u=x[..., 0],
        p_up=bar_to_pa(x[..., 1]),
        p_down=bar_to_pa(x[..., 2]),
        t_up=degc_to_k(x[..., 3]),
        eta_gas=x[..., 4],
        eta_oil=x[..., 5],
        theta={},
        well_test=torch.zeros(1, n, dtype=torch.bool),
        u_ref=torch.full((1, 1), 0.5, dtype=torch.float64),
        extra={"years_on": years},
        time_ns=time_ns,
    )
    cols = effect.compiled_columns(x.numpy(), {"years_on": years.numpy()}, time_ns.numpy())
    names = list(effect.parameters)
    terms = np.array([[CompiledFactor.SUGGEST, 0, len(names), 0, *form.settings]], np.int64)
    clamped = 0
    for k_value in (-0.9, -0.3, 0.05, 0.4, 0.95):
        p = {k: torch.full((1, 1), k_value * (1 - 0.5 * i), requires_grad=True,
                           dtype=torch.float64) for i, k in enumerate(names)}  # fmt: skip
        pe = np.array([float(v.detach()) for v in p.values()])
        want = effect.output_factor(inputs, p)
        for j in range(n):
            d_f, f = np.zeros(len(names)), np.zeros(1)
            got = numba_kernels.effect_factor(terms, pe, 0.5, cols[0, j], False, 0, 0.5, f, d_f)
            assert got == pytest.approx(float(want[0, j].detach()), rel=1e-11, abs=1e-300)
            if not names:
                continue
            grads = torch.autograd.grad(want[0, j], list(p.values()), retain_graph=True)
            np.testing.assert_allclose(d_f, [float(g) for g in grads], rtol=1e-11, atol=1e-300)
            clamped += all(float(g) == 0.0 for g in grads)
    if "scale=0.01" in spec or "x0=0.9" in spec:
        assert clamped > 0  # the clamp's side was reached (no gradient there)


# -- the effects that change the flux: real gas (Z) and slip -----------------------------------
_FLUX = numba_kernels.flux_rate_grad


def _broken_flux(part: str):  # type: ignore[no-untyped-def]
    """:func:`_mm_numba.flux_rate_grad` with one derivative 0.1 % too large: ``effect`` the
    effects' parameters' (strength, exponent), ``theta`` the mechanistic ones'."""

    def broken(*args: object) -> float:
        value = _FLUX(*args)
        target = args[-1] if part == "effect" else args[3]
        assert isinstance(target, np.ndarray)
        target *= 1.001
        return value  # type: ignore[no-any-return]

    return broken


@pytest.mark.parametrize("broken", [None, "effect", "theta"])
def test_a_broken_flux_derivative_fails_the_comparison(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame, broken: str | None
) -> None:
    """``ol`` with real gas and slip, the steps as Python over the compiled flux: exact as
    it is, off with the effects' or the mechanistic parameters' derivative broken."""
    effects = ["real_gas", "slip"]
    stream = _stream(frame, effects)
    stream = (stream[0], stream[1][:20])
    slow = _online_run(monkeypatch, "0", stream, effects, DEFAULT_ONLINE["mm"])
    kernel = kernels._kernel()
    assert kernel is not None
    monkeypatch.setattr(kernel, "effect_online", numba_kernels.effect_online.py_func)
    monkeypatch.setattr(numba_kernels, "_rate_at", numba_kernels._rate_at.py_func)
    if broken:
        monkeypatch.setattr(numba_kernels, "flux_rate_grad", _broken_flux(broken))
    fast = _online_run(monkeypatch, "1", stream, effects, DEFAULT_ONLINE["mm"])
    if broken:
        with pytest.raises(AssertionError, match="off by"):
            _compare(fast, slow)
    else:
        _compare(fast, slow)


def test_a_broken_flux_derivative_fails_the_filter_comparison(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame
) -> None:
    effects = ["real_gas"]
    stream = _stream(frame, effects)
    stream = (stream[0], stream[1][:20])
    slow = _bayes_run(monkeypatch, "0", stream, effects, "mm")
    kernel = kernels._kernel()
    assert kernel is not None
    monkeypatch.setattr(kernel, "bayes", numba_kernels.bayes.py_func)
    monkeypatch.setattr(numba_kernels, "log_rate_grad", numba_kernels.log_rate_grad.py_func)
    monkeypatch.setattr(numba_kernels, "_rate_at", numba_kernels._rate_at.py_func)
    monkeypatch.setattr(numba_kernels, "flux_rate_grad", _broken_flux("effect"))
    fast = _bayes_run(monkeypatch, "1", stream, effects, "mm")
    with pytest.raises(AssertionError, match="off by"):
        _compare(fast, slow)


_THETA_NAMES = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr", "c_d")


@pytest.mark.parametrize(("gas", "slip"), [(True, False), (False, True), (True, True)])
def test_the_flux_derivatives_equal_autograd(gas: bool, slip: bool) -> None:
    """The compiled rate with real gas and/or slip and dq / d(theta, strength, exponent)
    against autograd through the torch model's rate (models.physical._sachdeva_rate), on
    random samples and parameters (p_cr below and above p_down/p_up, Z clamped too)."""
    from vfm_core.models.physical import _plain_batch, _sachdeva_rate, _si_inputs
    from vfm_core.physics import DTYPE

    rng = np.random.default_rng(37)
    for trial in range(40):
        p_up = rng.uniform(30.0, 150.0)
        eta_gas = rng.uniform(0.01, 0.6)
        x = np.array(
            [
                rng.uniform(0.1, 1.0),
                p_up,
                rng.uniform(0.05, 0.95) * p_up,
                rng.uniform(20.0, 90.0),
                eta_gas,
                rng.uniform(0.0, 1.0 - eta_gas),
            ]
        )
        theta = np.array(
            [
                rng.normal(840.0, 20.0),
                rng.normal(1017.5, 8.0),
                rng.normal(1.28, 0.015),
                rng.normal(0.0205, 0.0018),
                rng.uniform(0.3, 0.8),
                rng.normal(0.825, 0.04),
            ]
        )
        # strength 8 at high pressure: Z's floor 0.2 (no derivative through it)
        strength = 8.0 if trial == 0 else rng.uniform(-1.0, 3.0)
        if trial == 0:
            x[1], x[2], x[3] = 300.0, 100.0, 20.0
        exponent = rng.uniform(-2.0, 4.0)
        dq, d_e = np.zeros(6), np.zeros(2)
        q = numba_kernels.flux_rate_grad(theta, x, 2e-3, dq, gas, strength, slip, exponent, d_e)
        th = {
            n: torch.tensor([v], dtype=DTYPE, requires_grad=True)
            for n, v in zip(_THETA_NAMES, theta, strict=True)
        }
        s = torch.tensor([[strength]], dtype=DTYPE, requires_grad=True)
        w = torch.tensor([[exponent]], dtype=DTYPE, requires_grad=True)
        xt = torch.tensor(x, dtype=DTYPE).reshape(1, 1, 6)
        effects, values = [], {}
        if gas:
            effects.append(RealGas())
            values["real_gas"] = {"strength": s}
        if slip:
            effects.append(Slip())
            values["slip"] = {"exponent": w}
        area = (th["c_d"] * 2e-3).unsqueeze(1) * xt[..., 0]
        rate = _sachdeva_rate(_si_inputs(_plain_batch(xt), th, None), area, effects, values)
        grads = torch.autograd.grad(rate.sum(), [*th.values(), s, w], allow_unused=True)
        want = np.array([0.0 if g is None else float(g.sum()) for g in grads])
        got = np.array([*dq, d_e[0] if gas else 0.0, d_e[1] if slip else 0.0])
        assert q == pytest.approx(float(rate.detach()), rel=1e-12), trial
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-12 * np.abs(want).max())
        if trial == 0 and gas:
            assert float(want[6]) == 0.0  # Z at its floor: autograd's zero, ours too
        if gas and trial > 0:
            assert float(want[6]) != 0.0  # a derivative that is there, compared


def test_slip_on_a_dry_gas_has_a_finite_gradient_in_both_paths() -> None:
    """A sample of gas only (eta_gas = 1) has no slip; torch's gradient there was NaN (the
    unchosen branch's root at 0), which would have turned an ``ol`` model's parameters to
    NaN. Both paths now give the same finite gradient."""
    from vfm_core.models.physical import _plain_batch, _sachdeva_rate, _si_inputs
    from vfm_core.physics import DTYPE

    x = np.array([0.5, 80.0, 30.0, 60.0, 1.0, 0.0])
    theta = np.array([840.0, 1017.5, 1.28, 0.0205, 0.55, 0.825])
    dq, de = np.zeros(6), np.zeros(2)
    q = numba_kernels.flux_rate_grad(theta, x, 2e-3, dq, False, 0.0, True, 1.0, de)
    names = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr", "c_d")
    th = {
        n: torch.tensor([v], dtype=DTYPE, requires_grad=True)
        for n, v in zip(names, theta, strict=True)
    }
    w = torch.tensor([[1.0]], dtype=DTYPE, requires_grad=True)
    xt = torch.tensor(x, dtype=DTYPE).reshape(1, 1, 6)
    area = (th["c_d"] * 2e-3).unsqueeze(1) * xt[..., 0]
    rate = _sachdeva_rate(
        _si_inputs(_plain_batch(xt), th, None), area, [Slip()], {"slip": {"exponent": w}}
    )
    grads = torch.autograd.grad(rate.sum(), [*th.values(), w])
    got = np.array([float(g.reshape(-1)[0]) for g in grads])
    assert np.isfinite(got).all()
    assert float(rate.detach().reshape(-1)[0]) == pytest.approx(q, rel=1e-12)
    np.testing.assert_allclose(got[:6], dq, rtol=1e-9, atol=1e-9 * np.abs(dq).max())
    assert got[6] == pytest.approx(de[1], abs=1e-9)


# -- fit_batch's training steps with compiled effects (kernels.FitSteps) -------------------
#: the compiled loops, as they are (the tests below watch them)
_FIT_RUN, _FIT_SEARCH = kernels.FitSteps.run, kernels.FitSteps.search


def _fit_run(
    monkeypatch: pytest.MonkeyPatch, flag: str, history: Batch, effects: list, name: str
) -> tuple[dict[str, torch.Tensor], list[list[int]], list[str]]:
    """An initial fit (early stopping on mini-batches), a retrain on mini-batches with given
    counts and one on the batch in one (the convergence stop), all on ``history``: the
    parameters, the counts run, and which compiled loops ran (``search``, ``run``) on a
    model with effects."""
    from vfm_core.learning.training import fit_batch

    monkeypatch.setenv("VFM_FIT_KERNEL", flag)
    ran: list[str] = []
    for what, original in (("run", _FIT_RUN), ("search", _FIT_SEARCH)):

        def spy(self, *a, _what=what, _original=original):  # type: ignore[no-untyped-def]
            ran.append(_what if self.effects else f"{_what} without effects")
            return _original(self, *a)

        monkeypatch.setattr(kernels.FitSteps, what, spy)
    model = make_model(name, history.wells, effects=effects)
    settings = replace(DEFAULT_TRAIN[name], batch_size=32, max_iter=80, patience=15)
    counts = [fit_batch(model, history, settings)["iterations"].tolist()]
    given = torch.tensor([50, 10, 35])
    counts.append(fit_batch(model, history, settings, iterations=given)["iterations"].tolist())
    whole = replace(settings, batch_size=1000, retrain_tol=0.2)
    counts.append(fit_batch(model, history, whole, iterations=given)["iterations"].tolist())
    state = {k: v.detach().clone() for k, v in model.named_parameters()}
    return state, counts, ran


@pytest.mark.parametrize(
    ("name", "effects"),
    [
        ("mm", ["slip"]),
        ("mm", ["critical_ratio", "slip", "mpfm_bias"]),
        ("mm", ["mpfm_bias"]),
        ("mm", [_STEP]),
        ("mm", ["valve_equal_percentage"]),
        ("mm", ["erosion", "valve", "real_gas"]),
        ("mm", [_SEASON]),
        ("ham", ["erosion", "mpfm_bias"]),
        ("hem", ["slip", "valve_sigmoid"]),
    ],
)
def test_the_fit_with_compiled_effects_matches_the_torch_loop(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame, name: str, effects: list[str]
) -> None:
    """``fit_batch`` on a model with compiled effects runs the compiled loops (early
    stopping's search and each pass 2), on the same mini-batches as torch's: the same
    counts, and every parameter (the effects' too) equal to 1e-9 of its scale. Every
    well's choke moves in these 150 samples: at one fixed opening a valve's parameters are
    undetermined (their gradient is rounding, which Adam's normalisation amplifies, in
    either path), as is the critical ratio's weight alone on these wells."""
    history, _ = _stream(frame, effects)
    slow, slow_counts, slow_ran = _fit_run(monkeypatch, "0", history, effects, name)
    fast, fast_counts, fast_ran = _fit_run(monkeypatch, "1", history, effects, name)
    assert slow_ran == [] and fast_ran == ["search", "run", "run", "run"]
    assert fast_counts == slow_counts and max(fast_counts[0]) > 0
    assert set(fast) == set(slow)
    for key in slow:
        _close(fast[key], slow[key], key, rtol=1e-9)
    # the effects learned: their parameters left the prior mean for some well
    moved = [v for k, v in slow.items() if k.startswith("effect_params.")]
    assert len(moved) == len(effects) and any(float(v.abs().max()) > 1e-3 for v in moved)


def test_the_fit_without_a_compiled_form_keeps_the_torch_loop(
    monkeypatch: pytest.MonkeyPatch, frame: pd.DataFrame
) -> None:
    """An effect without a compiled form (a user's own hook), or the critical ratio beside
    real gas: ``fit_batch`` runs the torch loop."""
    history, _ = _stream(frame, ["erosion"])
    history = history.select(torch.cumsum(history.mask.long(), 1) <= 40)
    for effects in ([_OwnErosion], ["critical_ratio", "real_gas"], ["erosion", _OwnErosion]):
        model = make_model("mm", history.wells, effects=effects)
        assert kernels.fit_parameters(model) is None
    assert kernels.fit_parameters(make_model("hem", ["a"], effects=["erosion"])) is not None
    state, _, ran = _fit_run(monkeypatch, "1", history, [_OwnErosion], "mm")
    assert ran == [] and float(state["effect_params.own_erosion.z"].abs().max()) > 0
