"""Building the per-well learners from config and history.

:func:`fit_history` fits all wells of a history file in one batched MAP fit (every model
but ``mtl`` keeps its own parameters per well, so this is the same as fitting each well
alone, only faster), exactly as :func:`vfm_core.jobs.study.run_prequential` fits before its
split; that is what lets a replay through the service reproduce ``vfm evaluate``. Each
well's slice of the fitted model is then loaded into its :class:`WellLearner`.

A field-wide model (``mtl``, ``model.field_wide``) runs as one
:class:`vfm_core.learning.field.FieldLearner` per engine for all the wells it serves; each
well's learner is that field's :class:`~vfm_core.learning.field.FieldWell` facade.
:func:`new_field` starts the engine's field (at start-up), :func:`new_learner` adds a well
to it (a well first seen live grows the model by a task vector at its prior), and
:func:`fit_history` fits the whole field at once, exactly as the study does before its
split.
"""

from __future__ import annotations

import logging
import weakref
from dataclasses import replace
from datetime import datetime
from typing import Any

import numpy as np
import pandas as pd
import torch

from service.config import ModelSettings
from vfm_core.data import make_batch, target_mask
from vfm_core.features import FeatureTracker, standard_features
from vfm_core.jobs.study import wells_of
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, fit_batch, settings_from_dict
from vfm_core.learning.field import FieldLearner
from vfm_core.learning.streaming import Learner, WellLearner
from vfm_core.models import make_model
from vfm_core.observations import load_observations
from vfm_core.schema import INPUT_COLUMNS, SOURCE, TARGET, TIME, WELL, WELL_TEST

__all__ = [
    "Learner",
    "new_learner",
    "new_field",
    "field_of",
    "load_history",
    "fit_history",
    "train_settings",
    "apply_budget",
    "fit_budget",
]

logger = logging.getLogger("vfm.service.engine.learners")

#: the field-wide learner of each live ModelSettings object (one engine each), by id; an
#: entry goes when its settings do
_FIELDS: dict[int, FieldLearner] = {}


def fit_budget(cfg: ModelSettings) -> float:
    return float(cfg.train.get("time_budget_s", cfg.retrain_budget_s))


def train_settings(cfg: ModelSettings) -> Any:
    """The batch-training settings of a live well: the model's defaults, ``model.train``,
    and the wall-clock budget of one fit (``model.retrain_budget_s`` unless
    ``model.train.time_budget_s`` is given), so no retrain can keep a worker busy for long."""
    return replace(
        settings_from_dict(DEFAULT_TRAIN[cfg.name], cfg.train), time_budget_s=fit_budget(cfg)
    )


def apply_budget(learner: Learner, cfg: ModelSettings) -> Learner:
    """Give a restored or refitted learner the configured retrain budget and bound on the
    measurements it remembers (its other settings stay those it was built with)."""
    budget = fit_budget(cfg)
    if learner.train.time_budget_s != budget:
        learner.train = replace(learner.train, time_budget_s=budget)
    if learner.method.train.time_budget_s != budget:
        learner.method.train = replace(learner.method.train, time_budget_s=budget)
    learner.remember_at_most(cfg.remember_max)  # where it can bound them alone
    return learner


def new_field(cfg: ModelSettings, field: FieldLearner | None = None) -> FieldLearner:
    """The engine's field-wide learner for ``cfg`` from now on: ``field`` (one restored from a
    checkpoint) or a new one with no wells, priors only. Called once at start-up."""
    if field is None:
        field = FieldLearner(
            cfg.name,
            cfg.method,
            train=train_settings(cfg),
            online=settings_from_dict(DEFAULT_ONLINE[cfg.name], cfg.online),
            model_kwargs=cfg.model_kwargs,
            seed=cfg.seed,
        )
    key = id(cfg)
    if key not in _FIELDS:
        weakref.finalize(cfg, _FIELDS.pop, key, None)
    _FIELDS[key] = field
    return field


def field_of(cfg: ModelSettings) -> FieldLearner:
    """The engine's field-wide learner for ``cfg`` (a new one if none was started)."""
    field = _FIELDS.get(id(cfg))
    return field if field is not None else new_field(cfg)


def new_learner(well: str, cfg: ModelSettings) -> Learner:
    """A learner for ``well`` with the configured model, method and settings (priors only);
    for a field-wide model, the well's facade on the engine's field (added at its prior)."""
    if cfg.field_wide:
        return field_of(cfg).fresh(well)
    return WellLearner(
        well,
        cfg.name,
        cfg.method,
        train=train_settings(cfg),
        online=settings_from_dict(DEFAULT_ONLINE[cfg.name], cfg.online),
        model_kwargs=cfg.model_kwargs,
        seed=cfg.seed,
        effects=cfg.effects,
        remember_max=cfg.remember_max,
    )


def load_history(cfg: ModelSettings) -> pd.DataFrame:
    """The rows of the history file before ``history_until``, with the standard features
    (:class:`vfm_core.features.FeatureTracker`) as extra columns; :func:`fit_history` fits
    on the measured ones (MPFM and well tests)."""
    if cfg.history is None:
        return pd.DataFrame()
    loaded = load_observations(cfg.history)
    frame = loaded.frame
    # the file's wells as `vfm evaluate` lays them out (first measured appearance), those
    # measured only after history_until included: fit_history builds its model over them
    field_wells = wells_of(frame.loc[target_mask(frame, "all")])
    keep = np.ones(len(frame), dtype=bool)
    if cfg.history_until is not None:
        keep = (frame[TIME] < pd.Timestamp(cfg.history_until)).to_numpy()
    frame = frame.loc[keep].reset_index(drop=True)
    feats = standard_features(frame)
    for name in FeatureTracker.names:
        frame[name] = feats[name].to_numpy()
    frame.attrs["field_wells"] = field_wells
    logger.info(
        "History %s: %d measured rows before %s.",
        cfg.history,
        int(target_mask(frame, "all").sum()),
        cfg.history_until.isoformat() if cfg.history_until else "its end",
    )
    return frame


def _slice_state(
    full: dict[str, torch.Tensor], single: dict[str, torch.Tensor], j: int, n: int
) -> dict[str, torch.Tensor]:
    """Well j's part of a multi-well state dict, shaped like a one-well model's."""
    out: dict[str, torch.Tensor] = {}
    for key, mine in single.items():
        value = full[key]
        if value.shape == mine.shape:
            out[key] = value.clone()
        elif value.dim() >= 1 and value.shape[0] == n and value.shape[1:] == mine.shape[1:]:
            out[key] = value[j : j + 1].clone()
        else:  # pragma: no cover - a model whose state is not stacked by well
            raise ValueError(f"state '{key}' {tuple(value.shape)} does not split into wells")
    return out


def fit_history(
    learners: dict[str, Learner], history: pd.DataFrame, cfg: ModelSettings
) -> list[str]:
    """Fit the learners of the wells in ``history`` (one batched fit); returns the wells fitted."""
    if history.empty:
        return []
    measured = history.loc[target_mask(history, "all")]
    wells = [w for w in wells_of(measured) if w in learners]
    if not wells:
        return []
    if cfg.field_wide:
        return _fit_field(learners, measured, wells, cfg)
    trackers = {
        w: FeatureTracker.from_frame(g)[0]
        for w, g in history[history[WELL].isin(wells)].groupby(WELL, sort=False)
    }
    frame = measured[measured[WELL].isin(wells)].reset_index(drop=True)
    train = settings_from_dict(DEFAULT_TRAIN[cfg.name], cfg.train)
    # the model over the history file's wells in vfm evaluate's order, so that each well
    # starts from the same random draw as there (a network's later layers are drawn after
    # the earlier layers of every well); the wells not fitted here have no rows in it
    layout = list(dict.fromkeys([*history.attrs.get("field_wells", []), *wells]))
    try:
        model = make_model(cfg.name, layout, seed=cfg.seed, effects=cfg.effects, **cfg.model_kwargs)
        batch = make_batch(frame, layout, extra_columns=model.extra_columns)
        summary = fit_batch(model, batch, train)
        full = model.state_dict()
        for well in wells:
            j = layout.index(well)
            learner = _per_well(learners[well])
            learner.model.load_state_dict(
                _slice_state(full, learner.model.state_dict(), j, len(layout))
            )
            _adopt_fit(
                learner,
                frame[frame[WELL] == well],
                summary["iterations"][j : j + 1],
                cfg.history_until,
                trackers[well],
            )
    except (ValueError, RuntimeError) as exc:
        # WellLearner's private layout changed: fall back to one fit per well (slower)
        logger.warning("Batched history fit unavailable (%s); fitting well by well.", exc)
        for well in wells:
            own = frame[frame[WELL] == well]
            fresh = _per_well(new_learner(well, cfg))
            x, y, t = _tensors(own)
            fresh.fit_history(
                x, y, t, well_test=_well_tests(own), features=_features(own), tracker=trackers[well]
            )
            learners[well] = fresh
    return wells


def _per_well(learner: Learner) -> Learner:
    if learner.shares_model:  # pragma: no cover - the config decides for all
        raise TypeError(f"{learner.well} has a field-wide learner among per-well ones.")
    return learner


def _fit_field(
    learners: dict[str, Learner], measured: pd.DataFrame, wells: list[str], cfg: ModelSettings
) -> list[str]:
    """The field-wide model fitted on every well's history at once, as ``vfm evaluate`` fits
    it before its split: the same rows, wells in the same order (first appearance), the
    same settings, and retrains on split + k periods (the split: ``model.history_until``)."""
    field = field_of(cfg)  # the engine builds every learner of the field from this one
    if any(learners[w].checkpoint_group is not field for w in wells):  # pragma: no cover
        raise ValueError("the wells of a field-wide model must share one FieldLearner")
    rows = {}
    for well in wells:
        own = measured[measured[WELL] == well]
        x, y, t = _tensors(own)
        rows[well] = (x, y, t, _well_tests(own))
    field.fit_history(
        rows, cfg.history_until, settings_from_dict(DEFAULT_TRAIN[cfg.name], cfg.train)
    )
    return wells


def _tensors(rows: pd.DataFrame) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    x = torch.tensor(rows[list(INPUT_COLUMNS)].to_numpy(dtype=np.float64))
    y = torch.tensor(rows[TARGET].to_numpy(dtype=np.float64))
    t = torch.tensor(pd.DatetimeIndex(rows[TIME]).as_unit("ns").asi8)
    return x, y, t


def _well_tests(rows: pd.DataFrame) -> torch.Tensor:
    return torch.tensor((rows[SOURCE] == WELL_TEST).to_numpy())


def _features(rows: pd.DataFrame) -> torch.Tensor:
    return torch.tensor(rows[list(FeatureTracker.names)].to_numpy(dtype=np.float64))


def _adopt_fit(
    learner: Learner,
    rows: pd.DataFrame,
    iterations: torch.Tensor,
    split: datetime | None,
    tracker: FeatureTracker,
) -> None:
    """What WellLearner.fit_history does after its fit, for a model fitted elsewhere.

    With a split (``history_until``) the periodic retrains fall on split + k periods, the
    calendar of ``vfm evaluate``; without one, a period after the last history row.
    """
    x, y, t = _tensors(rows)
    learner.adopt_fit(
        x,
        y,
        t,
        iterations,
        first_retrain_base=split,
        well_test=_well_tests(rows),
        features=_features(rows),
        tracker=tracker,
    )


def describe(learner: Learner) -> dict[str, Any]:
    """The learner's public state, for the API."""
    last: datetime | None = learner.last_update
    return {
        "model": learner.name,
        # the model without its effects (mm, hem, ham, ...; what a diagnosis starts from)
        "base_model": getattr(learner, "model_name", None),
        # the effects in the model, as the texts that rebuild them (what PUT .../model takes)
        "effects": list(getattr(learner, "effects", [])),
        "method": learner.method.text,
        "ready": learner.ready,
        "version": learner.version,
        "n_updates": learner.n_updates,
        "last_update": last.isoformat() if last else None,
        "parameters": learner.physical_parameters() if learner.ready else {},
        "measurements_remembered": learner.remembered,
    }
