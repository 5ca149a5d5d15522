"""A check suite for models, learning methods and effects, the project's own and yours.

As scikit-learn's ``check_estimator``: each function runs the contract every registered
model, method or effect of the project passes (the project's tests call them for each),
on a small simulated field, and raises :class:`AssertionError` with a sentence naming
what failed; it returns the names of the checks that ran::

    from vfm_core.checks import check_effect, check_method, check_model

    check_effect("my_effects:TemperatureScale")   # an effect class of your own
    check_method("pbl:30d")                       # a registered method, by its text
    check_model("mm", effects=["erosion"])        # a model, extended with effects

- :func:`check_model`: no guess before learning (NaN), then finite positive rates; the
  inputs are never changed; a model file gives the same predictions; the same seed gives
  the same fit; one online step lowers the error on the measurement it learned from; a
  batch fit follows targets shifted by 15 %; and where the fast paths apply: many wells
  learning in one call (:func:`vfm_core.learning.streaming.learn_many`) equals each well learning
  on its own, and the compiled kernels (:mod:`vfm_core.learning.kernels`) equal torch.
- :func:`check_method`: its text parses back; NaN before its fit; it runs with every
  registered model; inputs unchanged; a state round trip continues identically; the same
  seed gives the same result; wells are independent; it follows a well whose rates rose;
  and a streaming method reproduces the study sample by sample in the service's learner
  (one that cannot stream is refused there).
- :func:`check_effect`: a valid prior; the physics models take it (named
  ``mm+<effect>``, its parameters reported); gradients reach every parameter it adds and
  the projection keeps them in their bounds; the model rebuilds from its hyperparameters;
  then :func:`check_model` on ``mm`` with it, fast paths included.

The individual checks are public too (``check_model_*``, ``check_method_*``,
``check_effect_*``), each taking the same first argument. Rates in Sm3/h, as everywhere.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import io
import os
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

__all__ = [
    "check_model",
    "check_method",
    "check_effect",
    "model_checks_for",
    "MODEL_CHECKS",
    "METHOD_CHECKS",
    "EFFECT_CHECKS",
    "check_field",
]

#: a model given by name (``"mm"``) or by a factory ``factory(wells, seed) -> ChokeModel``
ModelSpec = str | Callable[[list[str], int], Any]


# --- data -----------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _simulated(wells: int, years: float, seed: int, start: str) -> pd.DataFrame:
    from vfm_core.simulate import simulate_field

    return simulate_field(wells=wells, years=years, seed=seed, start=start).observations


def check_field(effects: Sequence[Any] = (), *, kind: str = "model") -> pd.DataFrame:
    """The small simulated field a check runs on (a fresh copy; with the features that
    ``effects`` read): 3 wells x 1.5 years for models, 2 wells x 1.6 years for methods."""
    from vfm_core.effects import add_features

    if kind == "method":
        frame = _simulated(2, 1.6, 11, "2017-09-01")
    else:
        frame = _simulated(3, 1.5, 3, "2018-01-01")
    frame = frame.copy()
    return add_features(frame, list(effects)) if effects else frame


def _fail(condition: bool, sentence: str) -> None:
    if not condition:
        raise AssertionError(sentence)


def _wells(frame: pd.DataFrame) -> list[str]:
    from vfm_core.jobs.study import wells_of

    return wells_of(frame)


# --- models ---------------------------------------------------------------------------------
class _Model:
    """What a model check needs: a factory, a label, the effects whose features it reads."""

    def __init__(self, spec: ModelSpec, effects: Sequence[Any] = ()) -> None:
        from vfm_core.models import make_model

        if isinstance(spec, str):
            name, extra = spec, list(effects)

            def factory(wells: list[str], seed: int = 0) -> Any:
                return make_model(name, wells, seed=seed, effects=extra)

            self.factory: Callable[..., Any] = factory
        else:
            self.factory = spec
        probe = self.factory(["W0"], 0)
        self.label = str(probe.name)
        self.key = str(probe.key)
        self.gradient_free = bool(getattr(probe, "gradient_free", False))
        self.effects = list(effects) or list(getattr(probe, "hyper", {}).get("effects", []))

    def make(self, wells: list[str], seed: int = 0) -> Any:
        return self.factory(wells, seed)

    def train(self, quick: bool = True) -> Any:
        from vfm_core.learning import DEFAULT_TRAIN
        from vfm_core.learning.training import TrainSettings

        base = DEFAULT_TRAIN.get(self.key, TrainSettings())
        return replace(base, max_iter=30, patience=10, default_iter=20) if quick else base


def _batch(frame: pd.DataFrame, rows: np.ndarray, model: Any) -> Any:
    from vfm_core.data import make_batch

    return make_batch(frame, _wells(frame), rows, extra_columns=model.extra_columns)


def _train_rows(frame: pd.DataFrame) -> np.ndarray:
    from vfm_core.data import target_mask

    return np.flatnonzero(target_mask(frame, "all") & (frame["time"] < "2018-12-01").to_numpy())


def check_model_predicts_nan_before_learning(m: _Model, frame: pd.DataFrame) -> None:
    """No data, no guess (NaN); after ``setup`` (statistics only) finite positive rates."""
    model = m.make(_wells(frame))
    batch = _batch(frame, _train_rows(frame), model)
    before = model.predict_batch(batch)
    _fail(
        before.shape == batch.y.shape,
        f"{m.label}: predictions of shape {tuple(before.shape)} "
        f"for targets of shape {tuple(batch.y.shape)}.",
    )
    _fail(
        bool(torch.isnan(before).all()),
        f"{m.label}: a model with no data must say so (NaN), not guess.",
    )
    model.setup(batch)
    q = model.predict_batch(batch)
    _fail(
        bool(torch.isfinite(q[batch.mask]).all()),
        f"{m.label}: after setup the predictions are not all finite.",
    )
    _fail(bool((q[batch.mask] > 0).all()), f"{m.label}: after setup a predicted rate is <= 0.")


def check_model_input_not_mutated(m: _Model, frame: pd.DataFrame) -> None:
    """Fitting and predicting leave the batch's tensors as they were."""
    from vfm_core.learning import fit_batch

    model = m.make(_wells(frame))
    batch = _batch(frame, _train_rows(frame), model)
    x, y, extra = batch.x.clone(), batch.y.clone(), batch.extra.clone()
    fit_batch(model, batch, m.train())
    model.predict_batch(batch)
    for name, a, b in (("x", x, batch.x), ("y", y, batch.y), ("extra", extra, batch.extra)):
        _fail(bool(torch.equal(a, b)), f"{m.label}: fitting or predicting changed batch.{name}.")


def check_model_save_load_keeps_predictions(m: _Model, frame: pd.DataFrame) -> None:
    """A model file is a plain tensor archive that gives the same predictions, to the bit."""
    from vfm_core.learning import fit_batch
    from vfm_core.models import load_model, save_model

    model = m.make(_wells(frame), 1)
    batch = _batch(frame, _train_rows(frame), model)
    fit_batch(model, batch, m.train())
    with tempfile.TemporaryDirectory() as folder:
        path = save_model(model, Path(folder) / "model.pt")
        try:  # torch refuses pickled objects with weights_only
            torch.load(path, weights_only=True)
        except Exception as exc:
            raise AssertionError(
                f"{m.label}: the model file is not a plain tensor archive ({exc})."
            ) from exc
        loaded = load_model(path)
    _fail(loaded.name == model.name, f"{m.label}: the file loads as {loaded.name}.")
    _fail(
        bool(torch.equal(_nan0(loaded.predict_batch(batch)), _nan0(model.predict_batch(batch))))
        and _same_nan(loaded.predict_batch(batch), model.predict_batch(batch)),
        f"{m.label}: the loaded model predicts differently from the saved one.",
    )


def _nan0(t: torch.Tensor) -> torch.Tensor:
    return torch.nan_to_num(t, nan=0.0)


def _same_nan(a: torch.Tensor, b: torch.Tensor) -> bool:
    return bool(torch.equal(torch.isnan(a), torch.isnan(b)))


def _identical(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.shape == b.shape and _same_nan(a, b) and bool(torch.equal(_nan0(a), _nan0(b)))


def check_model_same_seed_same_result(m: _Model, frame: pd.DataFrame) -> None:
    """Two fits with the same seed give the same predictions, to the bit."""
    from vfm_core.learning import fit_batch

    preds = []
    for _ in range(2):
        model = m.make(_wells(frame), 7)
        batch = _batch(frame, _train_rows(frame), model)
        fit_batch(model, batch, m.train())
        preds.append(model.predict_batch(batch))
    _fail(_identical(preds[0], preds[1]), f"{m.label}: the same seed gave different fits.")


def check_model_one_online_step_lowers_error(m: _Model, frame: pd.DataFrame) -> None:
    """A new measurement per well 10 % above the prediction (a clear surprise): after one
    ``ol`` update the error on it is smaller, for every well."""
    from vfm_core.data import target_mask
    from vfm_core.learning import fit_batch, parse_method

    model = m.make(_wells(frame))
    fit_batch(model, _batch(frame, _train_rows(frame), model), m.train())
    rows = np.flatnonzero(target_mask(frame, "all") & (frame["time"] >= "2019-01-01").to_numpy())
    new = _batch(frame, rows, model)
    one = new.select(torch.cumsum(new.mask.long(), 1) == 1)
    pred = model.predict_batch(one)
    one.y = torch.where(one.mask, pred * 1.10, one.y)
    err_before = (model.predict_batch(one) - one.y).abs()[one.mask]
    parse_method("ol").bind(model).on_measurement(one)
    err_after = (model.predict_batch(one) - one.y).abs()[one.mask]
    _fail(
        bool((err_after < err_before).all()),
        f"{m.label}: one online step did not lower the error on the measurement it learned "
        f"from ({err_before.tolist()} -> {err_after.tolist()} Sm3/h).",
    )


def check_model_batch_fit_learns_a_shift(m: _Model, frame: pd.DataFrame) -> None:
    """Set up on the data, then fit to targets 15 % higher: the error at least halves
    (models with gradients; a gradient-free model passes by having none to follow)."""
    from vfm_core.learning import fit_batch

    if m.gradient_free:
        return
    model = m.make(_wells(frame))
    batch = _batch(frame, _train_rows(frame), model)
    model.setup(batch)
    shifted = replace(batch, y=batch.y * 1.15)
    mask = batch.mask

    def err() -> float:
        q = model.predict_batch(shifted)
        return float(((q - shifted.y).abs() / shifted.y.abs())[mask].mean())

    before = err()
    fit_batch(model, shifted, m.train(quick=False))
    after = err()
    _fail(
        after < 0.5 * before,
        f"{m.label}: fitted to rates 15 % higher, its mean relative error went from "
        f"{before:.4f} to {after:.4f}, not below half.",
    )


@contextlib.contextmanager
def _kernels(on: bool) -> Iterator[None]:
    """The compiled kernels on or off (``VFM_KERNELS``) for the block."""
    old = os.environ.get("VFM_KERNELS")
    os.environ["VFM_KERNELS"] = "1" if on else "0"
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("VFM_KERNELS", None)
        else:
            os.environ["VFM_KERNELS"] = old


def _well_learners(m: _Model, frame: pd.DataFrame, spec: ModelSpec) -> list[Any] | None:
    """One service learner per well (``ol``), fitted on histories of different lengths;
    None where the streaming learner cannot take the model (a factory, a field-wide one)."""
    from vfm_core.data import target_mask
    from vfm_core.learning import DEFAULT_TRAIN
    from vfm_core.learning.streaming import WellLearner
    from vfm_core.learning.training import TrainSettings
    from vfm_core.models import MODELS
    from vfm_core.schema import INPUT_COLUMNS

    if not isinstance(spec, str) or MODELS[spec].shared or m.gradient_free:
        return None
    rows = frame[target_mask(frame, "all")]
    train = replace(DEFAULT_TRAIN.get(m.key, TrainSettings()), max_iter=40, patience=10)
    learners = []
    for j, well in enumerate(_wells(frame)):
        own = rows[rows["well"] == well].iloc[: 60 + 10 * j]
        learner = WellLearner(well, spec, "ol", train=train, effects=m.effects)
        learner.fit_history(
            torch.tensor(own[list(INPUT_COLUMNS)].to_numpy()),
            torch.tensor(own["q_total"].to_numpy()),
            torch.tensor(pd.DatetimeIndex(own["time"]).as_unit("ns").asi8),
        )
        learners.append(learner)
    return learners


def _measurements(frame: pd.DataFrame, wells: list[str], rounds: int) -> list[list[Any]]:
    """Per round, each well's next measurement after its history: (inputs, q, time)."""
    from vfm_core.data import target_mask
    from vfm_core.schema import INPUT_COLUMNS

    rows = frame[target_mask(frame, "all")]
    out: list[list[Any]] = []
    per_well = [
        rows[rows["well"] == w].iloc[60 + 10 * j :].iloc[:rounds] for j, w in enumerate(wells)
    ]
    for r in range(rounds):
        out.append(
            [
                (
                    p.iloc[r][list(INPUT_COLUMNS)].tolist(),
                    float(p.iloc[r]["q_total"]),
                    p.iloc[r]["time"],
                )
                for p in per_well
            ]
        )
    return out


def _learner_state(learner: Any) -> dict[str, torch.Tensor]:
    out = {f"model.{k}": v.detach().clone() for k, v in learner.model.state_dict().items()}
    opt = (learner.method.state_dict().get("optimizer") or {}).get("state", {})
    for pid, state in opt.items():
        for key, value in state.items():
            if isinstance(value, torch.Tensor):
                out[f"optimizer.{pid}.{key}"] = value.detach().clone()
    return out


def _close_states(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor], what: str) -> None:
    _fail(a.keys() == b.keys(), f"{what}: the states hold different tensors.")
    for key, x in a.items():
        y = b[key]
        if x.dtype.is_floating_point:
            scale = float(torch.nan_to_num(x.abs()).max()) if x.numel() else 0.0
            close = x.shape == y.shape and bool(
                torch.allclose(x, y, rtol=1e-12, atol=1e-12 * scale + 1e-300, equal_nan=True)
            )
        else:
            close = bool(torch.equal(x, y))
        _fail(close, f"{what}: {key} differs (beyond 1e-12 relative).")


def check_model_fast_paths(m: _Model, frame: pd.DataFrame, spec: ModelSpec = "") -> None:
    """Where the fast paths apply: the wells' ``ol`` updates in one stacked call
    (:func:`~vfm_core.learning.streaming.learn_many`) leave each well's parameters and Adam state as
    learning one by one does, and with the compiled kernels as without them (1e-12
    relative). Runs for registered per-well gradient models (the service's learners)."""
    from vfm_core.learning.kernels import hybrid_applies, kernels_enabled, mm_online_applies
    from vfm_core.learning.streaming import learn_many

    learners = _well_learners(m, frame, spec or m.label)
    if learners is None:
        return
    rounds = _measurements(frame, [lrn.well for lrn in learners], 8)
    twins = copy.deepcopy(learners)
    for r in rounds:
        for learner, (x, q, t) in zip(learners, r, strict=True):
            learner.learn(x, q, t)
        learn_many(twins, [x for x, _, _ in r], [q for _, q, _ in r], [t for _, _, t in r])
    for one, many in zip(learners, twins, strict=True):
        _fail(one.n_updates > 0, f"{m.label}: the learner never updated its model.")
        _close_states(
            _learner_state(one),
            _learner_state(many),
            f"{m.label}: learning in one call (learn_many) and one by one ({one.well})",
        )
    model = learners[0].model
    if not kernels_enabled() or not (mm_online_applies(model) or hybrid_applies(model)):
        return  # no compiled path for this model: the torch path is the only one
    runs = []
    for on in (True, False):
        with _kernels(on):
            copies = _well_learners(m, frame, spec or m.label)
            assert copies is not None
            for r in rounds:
                for learner, (x, q, t) in zip(copies, r, strict=True):
                    learner.learn(x, q, t)
            runs.append([_learner_state(lrn) for lrn in copies])
    for fast, slow in zip(runs[0], runs[1], strict=True):
        _close_states(fast, slow, f"{m.label}: the compiled kernels and torch")


#: the model checks, in the order :func:`check_model` runs them
MODEL_CHECKS: tuple[Callable[..., None], ...] = (
    check_model_predicts_nan_before_learning,
    check_model_input_not_mutated,
    check_model_save_load_keeps_predictions,
    check_model_same_seed_same_result,
    check_model_one_online_step_lowers_error,
    check_model_batch_fit_learns_a_shift,
    check_model_fast_paths,
)


def _fast_paths_apply(m: _Model, spec: ModelSpec) -> bool:
    from vfm_core.models import MODELS

    return isinstance(spec, str) and not MODELS[spec].shared and not m.gradient_free


def model_checks_for(
    name_or_factory: ModelSpec, effects: Sequence[Any] = ()
) -> list[Callable[..., None]]:
    """The model checks that apply: the batch-fit check needs gradients, the fast-path
    check a registered per-well gradient model (what the service's learner stacks)."""
    m = _Model(name_or_factory, effects)
    out = []
    for check in MODEL_CHECKS:
        if check is check_model_batch_fit_learns_a_shift and m.gradient_free:
            continue
        if check is check_model_fast_paths and not _fast_paths_apply(m, name_or_factory):
            continue
        out.append(check)
    return out


def check_model(
    name_or_factory: ModelSpec,
    *,
    effects: Sequence[Any] = (),
    checks: Sequence[Callable[..., None]] | None = None,
    frame: pd.DataFrame | None = None,
) -> list[str]:
    """Run the model ``checks`` (default: :func:`model_checks_for`) on a registered model
    (by name, with ``effects``) or on ``factory(wells, seed)``'s; AssertionError with a
    sentence on the first failure. ``frame``: the observations to use (default
    :func:`check_field`). Returns the names of the checks that ran."""
    m = _Model(name_or_factory, effects)
    data = check_field(m.effects) if frame is None else frame
    if checks is None:
        checks = model_checks_for(name_or_factory, effects)
    for check in checks:
        if check is check_model_fast_paths:
            check(m, data, name_or_factory if isinstance(name_or_factory, str) else "")
        else:
            check(m, data)
    return [c.__name__ for c in checks]


# --- methods --------------------------------------------------------------------------------
_SPLIT = pd.Timestamp("2019-01-01", tz="UTC")


def _setup(field: pd.DataFrame, text: str, model: str = "mm", seed: int = 0) -> tuple:
    """A method bound to a fitted model, its memory and the test rows as rounds."""
    from vfm_core.data import make_batch, target_mask
    from vfm_core.learning import FrameMemory, parse_method
    from vfm_core.models import make_model

    is_target = target_mask(field, "all")
    wells = _wells(field)
    method = parse_method(text).bind(make_model(model, wells, seed=seed))
    memory = FrameMemory(field, is_target, wells)
    method.fit(memory.batch(_SPLIT.value))
    method.start(_SPLIT.value)
    rows = np.flatnonzero(is_target & (field["time"] >= _SPLIT).to_numpy())
    return method, memory, make_batch(field, wells, rows)


def _now(rb: Any) -> torch.Tensor:
    from vfm_core.learning import NEVER

    t = torch.where(rb.mask, rb.time_ns, torch.full_like(rb.time_ns, NEVER))
    return t.min(dim=1).values


def _stream(method: Any, memory: Any, test: Any, k0: int, k1: int) -> list[torch.Tensor]:
    """Predict-then-learn columns k0..k1 of the test batch; the predictions."""
    out = []
    for k in range(k0, k1):
        rb = test.column(k)
        method.retrain_due(memory, _now(rb))
        out.append(method.predict(rb).mean)
        method.on_measurement(rb, memory)
    return out


def check_method_text_parses_back(text: str, field: pd.DataFrame) -> None:
    """The text names the method and parses back; an unknown option is refused."""
    from vfm_core.errors import ConfigError
    from vfm_core.learning import METHODS, parse_method

    method = parse_method(text)
    _fail(str(method) == text and method.text == text, f"{text}: the method reads as {method}.")
    _fail(type(parse_method(method)) is type(method), f"{text}: a copy is of another class.")
    _fail(method.key in METHODS and bool(method.kind), f"{text}: not registered with a kind.")
    try:
        parse_method(f"{method.key}:nonsense=1")
    except ConfigError as exc:
        _fail(
            any(w in str(exc) for w in ("unknown option", "needs", "not a positive")),
            f"{text}: an unknown option is refused without saying so: {exc}",
        )
    else:
        raise AssertionError(f"{text}: the unknown option 'nonsense=1' was accepted.")


def check_method_predict_before_fit_is_nan(text: str, field: pd.DataFrame) -> None:
    """NaN before the fit; finite after it, with a positive sd where it has intervals."""
    from vfm_core.data import make_batch, target_mask
    from vfm_core.learning import parse_method
    from vfm_core.models import make_model

    wells = _wells(field)
    method = parse_method(text).bind(make_model("mm", wells))
    rows = np.flatnonzero(target_mask(field, "all"))
    batch = make_batch(field, wells, rows[:50])
    _fail(bool(torch.isnan(method.predict(batch).mean).all()), f"{text}: guesses before its fit.")
    method, _, test = _setup(field, text)
    forecast = method.predict(test)
    _fail(bool(torch.isfinite(forecast.mean[test.mask]).all()), f"{text}: a non-finite forecast.")
    if method.intervals:
        _fail(
            forecast.std is not None and bool((forecast.std[test.mask] > 0).all()),
            f"{text}: a method with intervals gave no positive sd.",
        )
    else:
        _fail(forecast.std is None, f"{text}: an sd from a method without intervals.")


def check_method_runs_every_model(
    text: str, field: pd.DataFrame, models: Sequence[str] = ()
) -> None:
    """It binds to every registered model (``models``: these only), including one without
    parameters to filter (``last``), predicts and learns without error."""
    from vfm_core.models import MODELS

    for model in models or list(MODELS):
        method, memory, test = _setup(field, text, model=model)
        out = _stream(method, memory, test, 0, min(5, test.time_ns.shape[1]))
        for k, pred in enumerate(out):
            _fail(
                bool(torch.isfinite(pred[test.mask[:, k]]).all()),
                f"{text} with {model}: a non-finite prediction at round {k}.",
            )


def check_method_input_not_mutated(text: str, field: pd.DataFrame) -> None:
    """Learning leaves the batch's tensors as they were."""
    method, memory, test = _setup(field, text)
    before = [t.clone() for t in (test.x, test.y, test.mask, test.time_ns)]
    _stream(method, memory, test, 0, 20)
    for name, a, b in zip(
        ("x", "y", "mask", "time_ns"),
        before,
        (test.x, test.y, test.mask, test.time_ns),
        strict=True,
    ):
        _fail(bool(torch.equal(a, b)), f"{text}: learning changed batch.{name}.")


def check_method_state_round_trip(text: str, field: pd.DataFrame) -> None:
    """A copy restored from ``state_dict`` (through torch.save, weights_only) learns the
    same, to the bit, and has the same next retrain."""
    from vfm_core.learning import parse_method
    from vfm_core.models import make_model

    method, memory, test = _setup(field, text)
    _stream(method, memory, test, 0, 40)
    buf = io.BytesIO()
    torch.save({"model": method.model.state_dict(), "method": method.state_dict()}, buf)
    saved = torch.load(io.BytesIO(buf.getvalue()), weights_only=True)
    twin_model = make_model("mm", method.model.wells)
    twin_model.load_state_dict(saved["model"])
    twin = parse_method(text).bind(twin_model)
    twin.load_state_dict(saved["method"])
    a = _stream(method, memory, test, 40, 120)
    b = _stream(twin, memory, test, 40, 120)
    for k, (x, y) in enumerate(zip(a, b, strict=True)):
        _fail(_identical(x, y), f"{text}: the restored copy predicts differently at round {k}.")
    _fail(twin.next_due() == method.next_due(), f"{text}: the restored copy's next retrain moved.")


def check_method_same_seed_same_result(text: str, field: pd.DataFrame) -> None:
    """Two runs with the same seed give the same predictions, to the bit."""
    runs = []
    for _ in range(2):
        method, memory, test = _setup(field, text, seed=3)
        runs.append(torch.stack(_stream(method, memory, test, 0, 60)))
    _fail(_identical(runs[0], runs[1]), f"{text}: the same seed gave different predictions.")


def check_method_wells_are_independent(text: str, field: pd.DataFrame) -> None:
    """Well 1 predicts the same whether or not well 0 received measurements."""
    results = []
    for feed_well0 in (True, False):
        method, memory, test = _setup(field, text)
        if not feed_well0:
            test = test.select(torch.arange(test.n_wells).unsqueeze(1) != 0)
        results.append(torch.stack(_stream(method, memory, test, 0, 80))[:, 1])
    _fail(
        _identical(results[0], results[1]),
        f"{text}: well 1's predictions depend on whether well 0 was measured.",
    )


def check_method_follows_a_shifted_well(text: str, field: pd.DataFrame) -> None:
    """Measurements 20 % above the model (inputs shifted too, as a changed well's are):
    once learned, and every retrain due has run, the error at those inputs is below 0.9
    times what it was."""
    from vfm_core.data import Batch, target_mask
    from vfm_core.learning import FrameMemory

    method, memory, test = _setup(field, text)
    first = test.select(torch.cumsum(test.mask.long(), 1) <= 60)
    shifted = first.x.clone()
    shifted[..., 0] = torch.clamp(shifted[..., 0] + 0.15, max=1.0)  # choke opened
    probe = Batch(first.wells, shifted, first.y, first.mask, first.time_ns, first.row)
    target = method.predict(probe).mean * 1.2
    err_before = float(((method.predict(probe).mean - target).abs() / target)[first.mask].mean())
    frame = field.copy()  # the shifted measurements, as the memory of a retrain will see them
    rows = first.row[first.mask].numpy()
    frame.loc[frame.index[rows], "choke"] = shifted[first.mask][:, 0].numpy()
    frame.loc[frame.index[rows], "q_total"] = target[first.mask].numpy()
    memory = FrameMemory(frame, target_mask(frame, "all"), first.wells)
    live = Batch(first.wells, shifted, target, first.mask, first.time_ns, first.row)
    for k in range(live.x.shape[1]):
        rb = live.column(k)
        method.retrain_due(memory, _now(rb))
        method.on_measurement(rb, memory)
    later = int(first.time_ns[first.mask].max()) + 1
    due = method.next_due()
    method.retrain_due(memory, torch.full((live.n_wells,), max(later, due or 0), dtype=torch.int64))
    err_after = float(((method.predict(probe).mean - target).abs() / target)[first.mask].mean())
    _fail(
        err_after < 0.9 * err_before,
        f"{text}: after learning a well whose rates rose 20 %, its mean relative error went "
        f"from {err_before:.4f} to {err_after:.4f}, not below 0.9 times.",
    )


def check_method_in_the_streaming_learner(text: str, field: pd.DataFrame) -> None:
    """A streaming method: one well through the service's learner sample by sample
    predicts what :func:`~vfm_core.jobs.study.run_prequential` predicts (1e-6 relative);
    one that cannot stream is refused there with a sentence."""
    from vfm_core.data import target_mask
    from vfm_core.errors import ConfigError
    from vfm_core.jobs.study import run_prequential
    from vfm_core.learning import parse_method
    from vfm_core.learning.streaming import WellLearner
    from vfm_core.schema import INPUT_COLUMNS
    from vfm_core.simulate import simulate_field

    if not type(parse_method(text)).streaming:
        try:
            WellLearner("W1", "mm", text)
        except ConfigError as exc:
            _fail("cannot run" in str(exc), f"{text}: refused without saying why: {exc}")
            return
        raise AssertionError(f"{text}: cannot stream, yet the streaming learner took it.")
    one = simulate_field(
        wells=1, years=1.2, seed=9, start="2018-04-01", hidden=["erosion"]
    ).observations
    study = run_prequential(one, "mm", text, targets="all", split=_SPLIT)
    rows = one[target_mask(one, "all")]
    hist, live = rows[rows["time"] < _SPLIT], rows[rows["time"] >= _SPLIT]
    learner = WellLearner("W01", "mm", text)
    learner.fit_history(
        torch.tensor(hist[list(INPUT_COLUMNS)].to_numpy()),
        torch.tensor(hist["q_total"].to_numpy()),
        torch.tensor(pd.DatetimeIndex(hist["time"]).as_unit("ns").asi8),
        well_test=torch.tensor((hist["source"] == "well_test").to_numpy()),
    )
    learner.method.start(_SPLIT.value)  # the study's calendar
    predicted: list[Any] = []
    for _, row in live.iterrows():
        inputs = row[list(INPUT_COLUMNS)].tolist()
        predicted.append(learner.predict(inputs, when=row["time"])["q_total"])
        learner.learn(inputs, row["q_total"], row["time"], row["source"])
    try:
        np.testing.assert_allclose(predicted, study.predictions["predicted"].to_numpy(), rtol=1e-6)
    except AssertionError as exc:
        raise AssertionError(
            f"{text}: the streaming learner does not reproduce the study: {exc}"
        ) from exc


#: the method checks, in the order :func:`check_method` runs them
METHOD_CHECKS: tuple[Callable[..., None], ...] = (
    check_method_text_parses_back,
    check_method_predict_before_fit_is_nan,
    check_method_runs_every_model,
    check_method_input_not_mutated,
    check_method_state_round_trip,
    check_method_same_seed_same_result,
    check_method_wells_are_independent,
    check_method_follows_a_shifted_well,
    check_method_in_the_streaming_learner,
)


def check_method(
    text: str,
    *,
    checks: Sequence[Callable[..., None]] = METHOD_CHECKS,
    frame: pd.DataFrame | None = None,
) -> list[str]:
    """Run the method ``checks`` on a learning method given by its text (``"pbl:30d"``,
    registered in :data:`vfm_core.learning.METHODS`, e.g. by your own module);
    AssertionError with a sentence on the first failure. Returns the checks' names."""
    data = check_field(kind="method") if frame is None else frame
    for check in checks:
        check(text, data)
    return [c.__name__ for c in checks]


# --- effects --------------------------------------------------------------------------------
def check_effect_prior(effect: Any, field: pd.DataFrame) -> None:
    """It resolves (a name, a valid prior: std > 0, low < mean < high) to an Effect."""
    from vfm_core.effects import Effect, resolve_effect

    cls = resolve_effect(effect)  # ConfigError with a sentence on a bad prior
    _fail(isinstance(cls, type) and issubclass(cls, Effect), f"{effect}: not an Effect.")
    _fail(bool(cls.name), f"{effect}: an effect needs a name.")


def check_effect_in_the_physics_models(effect: Any, field: pd.DataFrame) -> None:
    """``mm``, ``hem`` and ``ham`` take it: named ``<model>+<effect>``, finite rates after
    setup, its parameters reported; and each rebuilds from its hyperparameters."""
    from vfm_core.effects import resolve_effect
    from vfm_core.models import make_model

    cls = resolve_effect(effect)
    wells = _wells(field)
    for base in ("mm", "hem", "ham"):
        model = make_model(base, wells, effects=[effect])
        _fail(model.name == f"{base}+{cls.name}", f"{cls.name}: {base} with it is {model.name}.")
        batch = _batch(field, _train_rows(field), model)
        model.setup(batch)
        q = model.predict_batch(batch)
        _fail(bool(torch.isfinite(q[batch.mask]).all()), f"{cls.name}: {base} predicts non-finite.")
        reported = model.physical_parameters()
        for name in cls.parameters:
            _fail(f"{cls.name}.{name}" in reported, f"{cls.name}: {name} is not reported.")
        again = make_model(base, wells, effects=model.hyper["effects"])
        _fail(
            list(again.state_dict()) == list(model.state_dict()),
            f"{cls.name}: {base} does not rebuild from its hyperparameters.",
        )


def check_effect_gradients_and_bounds(effect: Any, field: pd.DataFrame) -> None:
    """Gradients reach the parameters it adds (finite, not all zero); pushed far out, the
    projection brings every one back within its prior's bounds."""
    from vfm_core.effects import resolve_effect
    from vfm_core.models import make_model

    cls = resolve_effect(effect)
    model = make_model("mm", _wells(field), effects=[effect])
    batch = _batch(field, _train_rows(field), model)
    model.setup(batch)
    if not cls.parameters:
        return
    model.forward_batch(batch).sum().backward()
    z: torch.Tensor = model.effect_params[cls.name].z  # type: ignore[index, union-attr]
    grad = z.grad
    _fail(
        grad is not None and bool(torch.isfinite(grad).all()),
        f"{cls.name}: no finite gradient reaches its parameters.",
    )
    assert grad is not None
    # all of them together: one may rightly have none on these data (a valve's slope on a
    # stretch of openings the wells never used)
    _fail(float(grad.abs().sum()) > 0, f"{cls.name}: no gradient reaches its parameters.")
    for far in (-50.0, 50.0):
        with torch.no_grad():
            z[:] = far
        model.project_()
        values = model.physical_parameters()
        for name, prior in cls.parameters.items():
            got = np.asarray(values[f"{cls.name}.{name}"], dtype=float)
            _fail(
                bool((got >= prior.low - 1e-9).all() and (got <= prior.high + 1e-9).all()),
                f"{cls.name}: {name} left its bounds [{prior.low}, {prior.high}] after the "
                f"projection ({got.tolist()}).",
            )


def check_effect_model_contract(effect: Any, field: pd.DataFrame) -> None:
    """:func:`check_model` on ``mm`` with the effect, fast paths included."""
    check_model("mm", effects=[effect], frame=field)


#: the effect checks, in the order :func:`check_effect` runs them
EFFECT_CHECKS: tuple[Callable[..., None], ...] = (
    check_effect_prior,
    check_effect_in_the_physics_models,
    check_effect_gradients_and_bounds,
    check_effect_model_contract,
)


def check_effect(
    effect: Any,
    *,
    checks: Sequence[Callable[..., None]] = EFFECT_CHECKS,
    frame: pd.DataFrame | None = None,
) -> list[str]:
    """Run the effect ``checks`` on an effect: a registered name, ``module:Class`` or an
    :class:`~vfm_core.effects.Effect` subclass; AssertionError with a sentence on the
    first failure. Returns the checks' names."""
    data = check_field([effect]) if frame is None else frame
    for check in checks:
        check(effect, data)
    return [c.__name__ for c in checks]
