"""The steady-state choke models of the paper, batched over wells, behind one registry.

Registry names (:data:`MODELS`): ``last`` (benchmark), ``lr``, ``nn``, ``mtl``
(:mod:`vfm_core.models.networks`), ``mm``, ``hem`` and ``ham``
(:mod:`vfm_core.models.physical`). :func:`make_model` builds one by name, the physics
models with ``effects=[...]`` (:mod:`vfm_core.effects`); the protocol every model keeps is
in :mod:`vfm_core.models.base`. Models are saved and loaded as tensors plus JSON
hyperparameters, never pickle (:func:`save_model`, :func:`load_model`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from vfm_core.errors import ConfigError
from vfm_core.fileio import write_with
from vfm_core.models.base import ChokeModel, PhysicalParameters, WellMLP
from vfm_core.models.networks import LastValue, LinearRegression, MultiTask, NeuralNet
from vfm_core.models.physical import (
    PHYSICAL_NAMES,
    HybridArea,
    HybridError,
    Mechanistic,
    mechanistic_rate,
)

__all__ = [
    "MODELS",
    "EFFECT_MODELS",
    "PHYSICAL_NAMES",
    "ChokeModel",
    "PhysicalParameters",
    "WellMLP",
    "LastValue",
    "LinearRegression",
    "NeuralNet",
    "MultiTask",
    "Mechanistic",
    "HybridError",
    "HybridArea",
    "mechanistic_rate",
    "make_model",
    "save_model",
    "load_model",
]

MODELS: dict[str, type[ChokeModel]] = {
    cls.key: cls
    for cls in (
        LastValue,
        LinearRegression,
        NeuralNet,
        MultiTask,
        Mechanistic,
        HybridError,
        HybridArea,
    )
}
#: the models that physical effects extend
EFFECT_MODELS: tuple[str, ...] = tuple(k for k, c in MODELS.items() if issubclass(c, Mechanistic))


def make_model(
    name: str, wells: Sequence[str], *, effects: Sequence[Any] = (), **hyper: Any
) -> ChokeModel:
    """Build a registered model by name; an unknown name lists the valid ones.

    ``effects`` (names, ``name:key=value``, ``module:Class`` or Effect classes) extend
    ``mm``, ``hem`` or ``ham``; other keywords are the model's hyperparameters.
    """
    try:
        cls = MODELS[name]
    except KeyError:
        raise ConfigError(f"Unknown model '{name}'; choose one of {', '.join(MODELS)}.") from None
    if effects:
        if name not in EFFECT_MODELS:
            raise ConfigError(
                f"Effects extend the models {', '.join(EFFECT_MODELS)}, not '{name}'."
            )
        hyper["effects"] = list(effects)
    try:
        return cls(wells, **hyper)
    except TypeError as exc:
        raise ConfigError(f"Invalid settings {hyper} for model '{name}': {exc}.") from None


def save_model(model: ChokeModel, path: str | Path) -> Path:
    """Save a model's tensors and hyperparameters to one file, without pickle.

    The file holds only a dict of strings, lists and tensors and is read back with
    ``torch.load(weights_only=True)``, which refuses anything that could run code.
    """
    payload = {
        "format": "vfm-model/1",
        "name": model.name,
        "key": model.key,
        "wells": list(model.wells),
        "hyper": json.dumps(model.hyper),
        "state": {k: v.detach().clone() for k, v in model.state_dict().items()},
    }
    return write_with(path, lambda temp: torch.save(payload, temp))


def load_model(path: str | Path) -> ChokeModel:
    """Load a model written by :func:`save_model` (tensors only, never pickle)."""
    try:
        payload = torch.load(Path(path), weights_only=True)
    except FileNotFoundError:
        raise ConfigError(f"No model file at {path}.") from None
    except Exception as exc:  # a corrupt file or one that is not a vfm model
        raise ConfigError(f"{path} is not a readable VFM model file: {exc}") from None
    if not isinstance(payload, dict) or payload.get("format") != "vfm-model/1":
        raise ConfigError(f"{path} is not a VFM model file (format vfm-model/1).")
    hyper = json.loads(payload["hyper"])
    key = payload.get("key") or str(payload["name"]).split("+")[0]
    model = make_model(key, payload["wells"], **hyper)
    model.load_state_dict(payload["state"])
    return model
