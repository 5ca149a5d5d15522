"""Many one-well models run as one multi-well model: what the methods' group operations use.

A service holds one :class:`~vfm_core.learning.streaming.WellLearner` per well, each with its own
one-well model. Models of the same class and hyperparameters (the same
:meth:`~vfm_core.models.base.ChokeModel.stack_key`) keep their per-well tensors with a
leading well dimension of one, so K of them concatenated along that dimension are the
state of one K-well model of that class. :class:`StackedModel` holds such a K-well model
(rebuilt once per thread and specification, :func:`stacked_model`) and runs it with the
wells' tensors in its place:

- :meth:`StackedModel.rates`: the rates of K wells' samples in one model call, the wells'
  tensors swapped in and the model's own put back (what a prediction reads);
- :meth:`StackedModel.load` / :meth:`StackedModel.store`: the wells' tensors copied into
  the model, and its parameters copied back into each well's own (what a stacked learning
  step changes).

A learning method decides whether and how its updates stack (its own ``learn_group``);
this module only moves tensors. Nothing here changes a well's model but :meth:`store`.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Hashable, Sequence
from typing import Any

import torch

from vfm_core.data import Batch
from vfm_core.learning.kernels import predict_rates
from vfm_core.models import ChokeModel, make_model

__all__ = [
    "StackedModel",
    "stacked_model",
    "stacked_rates",
    "concat_batches",
    "stack_for_learning",
    "well_of",
]

#: where a tensor lives: (its name in the state dict, the path to its module, its
#: attribute there, whether it is a parameter)
_Where = tuple[str, tuple[str, ...], str, bool]


def _slots(module: torch.nn.Module, path: tuple[str, ...], is_param: bool) -> dict[str, Any]:
    """The parameter or buffer dict of the module at ``path`` under ``module``.

    torch keeps a module's tensors in these dicts; a tensor put there is the one the module
    computes with. Swapping entries is what ``torch.func.functional_call`` does, without its
    per-call machinery (a prediction of a few wells costs less than that machinery)."""
    for part in path:
        module = module._modules[part]  # type: ignore[assignment]
    return module._parameters if is_param else module._buffers  # type: ignore[return-value]


class StackedModel:
    """A K-well model of one specification, run with K one-well models' tensors."""

    def __init__(self, one: ChokeModel) -> None:
        self.model = make_model(one.key, ["well 1", "well 2"], **one.hyper)
        mine = dict(one.named_parameters()) | dict(one.named_buffers())
        two = dict(self.model.named_parameters()) | dict(self.model.named_buffers())
        if set(mine) != set(two):
            raise ValueError(f"The model {one.name} cannot be rebuilt with the same tensors.")
        #: tensors with a leading well dimension
        self.per_well: list[_Where] = []
        #: tensors every well of the model shares (e.g. the priors), taken from the first
        self.shared: list[_Where] = []
        params = dict(one.named_parameters())
        for name, t in mine.items():
            t2 = two[name]
            *path, attr = name.split(".")
            where = (name, tuple(path), attr, name in params)
            if t.dim() > 0 and t.shape[0] == 1 and t2.shape[0] == 2 and t.shape[1:] == t2.shape[1:]:
                self.per_well.append(where)
            elif t.shape == t2.shape:
                self.shared.append(where)
            else:
                raise ValueError(f"The tensor {name} of {one.name} has no well dimension.")
        #: the stacked model's own slots, in the order of per_well + shared
        self._own = [
            (_slots(self.model, path, is_param), attr)
            for _, path, attr, is_param in self.per_well + self.shared
        ]
        #: per one-well model: where it keeps its tensors (forgotten with the model)
        self._places: weakref.WeakKeyDictionary[ChokeModel, list[tuple[dict[str, Any], str]]] = (
            weakref.WeakKeyDictionary()
        )

    # -- reading the wells' tensors ---------------------------------------------------------------
    def _places_of(self, model: ChokeModel) -> list[tuple[dict[str, Any], str]]:
        """Where ``model`` keeps each tensor (per_well, then shared): its module's dict and
        the name (a module's dicts live as long as the module)."""
        places = self._places.get(model)
        if places is None:
            places = [
                (_slots(model, path, is_param), attr)
                for _, path, attr, is_param in self.per_well + self.shared
            ]
            self._places[model] = places
        return places

    def tensor(self, model: ChokeModel, where: _Where) -> torch.Tensor:
        """One of ``model``'s tensors (``where`` from :attr:`per_well` or :attr:`shared`)."""
        _, path, attr, is_param = where
        return _slots(model, path, is_param)[attr]  # type: ignore[no-any-return]

    def state_of(self, models: Sequence[ChokeModel]) -> list[torch.Tensor]:
        """The models' tensors stacked along the well dimension (shared ones from the
        first), in the order of :attr:`per_well` then :attr:`shared`."""
        n = len(self.per_well)
        columns = zip(*[[d[a] for d, a in self._places_of(m)[:n]] for m in models], strict=True)
        state = [torch.cat(column, 0) for column in columns]
        state += [d[a] for d, a in self._places_of(models[0])[n:]]
        return state

    # -- predicting -------------------------------------------------------------------------------
    def rates(self, models: Sequence[ChokeModel], batch: Batch) -> torch.Tensor:
        """The rates [K, N] of ``batch`` (one row per model, in order) with the models'
        tensors in the stacked model's place, then its own put back. The stacked model is
        this thread's own (:func:`stacked_model`) and stacked updates use it too, so its own
        tensors are back in place after every call."""
        state = self.state_of(models)
        own = [holder[attr] for holder, attr in self._own]
        self.model.wells = list(batch.wells)
        try:
            for (holder, attr), tensor in zip(self._own, state, strict=True):
                holder[attr] = tensor
            with torch.no_grad():
                return predict_rates(self.model, batch)
        finally:
            for (holder, attr), tensor in zip(self._own, own, strict=True):
                holder[attr] = tensor

    # -- learning ---------------------------------------------------------------------------------
    def load(self, models: Sequence[ChokeModel], wells: Sequence[str]) -> None:
        """Copy the models' tensors into the stacked model (parameters as new data of its
        own parameters, buffers in their place), for a stacked learning step. Refused for a
        model with parameters its wells share (a step would have to split them)."""
        if any(w[3] for w in self.shared):
            raise ValueError(f"The model {self.model.name} has parameters shared by its wells.")
        with torch.no_grad():
            for where, value in zip(
                self.per_well + self.shared, self.state_of(models), strict=True
            ):
                _, path, attr, is_param = where
                if is_param:
                    self.tensor(self.model, where).data = value.detach().clone()
                else:
                    _slots(self.model, path, False)[attr] = value
        self.model.wells = list(wells)

    def parameters(self) -> list[_Where]:
        """The per-well parameters (where they live), in the stacked model's order."""
        return [w for w in self.per_well if w[3]]

    def store(self, models: Sequence[ChokeModel]) -> None:
        """Write the stacked model's parameters back into each well's own, in place (one
        call per parameter for all wells); their gradients are dropped."""
        with torch.no_grad():
            for where in self.parameters():
                p = self.tensor(self.model, where)
                p.grad = None
                torch._foreach_copy_([self.tensor(m, where) for m in models], list(p.split(1, 0)))


_local = threading.local()


def stacked_model(model: ChokeModel) -> StackedModel | None:
    """The cached multi-well model of ``model``'s specification, this thread's own (calls
    swap its tensors); None for a model that cannot be stacked (no stack key, or one that
    cannot be rebuilt for many wells)."""
    key: Hashable | None = model.stack_key()
    if key is None:
        return None
    cache: dict[Hashable, StackedModel | None] | None = getattr(_local, "stacked", None)
    if cache is None:
        cache = _local.stacked = {}
    if key not in cache:
        if len(cache) >= 64:  # many model specifications in one process: start again
            cache.clear()
        try:
            cache[key] = StackedModel(model)
        except Exception:
            cache[key] = None
    return cache[key]


def stacked_rates(models: Sequence[ChokeModel], batch: Batch) -> torch.Tensor:
    """The rates [K, N] of K one-well models of one specification, one row of ``batch``
    each, in one model call (or one call per model when they cannot be stacked)."""
    stacked = stacked_model(models[0]) if len(models) > 1 else None
    if stacked is None:
        with torch.no_grad():
            return torch.cat([predict_rates(m, well_of(batch, k)) for k, m in enumerate(models)], 0)
    return stacked.rates(models, batch)


def stack_for_learning(
    models: Sequence[ChokeModel], batches: Sequence[Batch]
) -> tuple[StackedModel, Batch]:
    """The stacked model holding ``models``' tensors (:meth:`StackedModel.load`) and their
    one-well ``batches`` as one batch, for a stacked learning step; an error when the
    models cannot be stacked (nothing changed then)."""
    stacked = stacked_model(models[0])
    if stacked is None:
        raise ValueError(f"The model {models[0].name} cannot be stacked.")
    wells = [m.wells[0] for m in models]
    stacked.load(models, wells)
    return stacked, concat_batches(batches, wells)


def well_of(batch: Batch, k: int) -> Batch:
    """Well ``k`` of ``batch`` as a one-well batch."""
    rows = slice(k, k + 1)
    return Batch(
        [batch.wells[k]],
        batch.x[rows],
        batch.y[rows],
        batch.mask[rows],
        batch.time_ns[rows],
        batch.row[rows],
        None if batch.well_test is None else batch.well_test[rows],
        None if batch.extra is None else batch.extra[rows],
        batch.extra_names,
    )


def concat_batches(batches: Sequence[Batch], wells: Sequence[str]) -> Batch:
    """One-well batches of the same width as one batch of their wells, in order."""
    cat = torch.cat
    return Batch(
        list(wells),
        cat([b.x for b in batches], 0),
        cat([b.y for b in batches], 0),
        cat([b.mask for b in batches], 0),
        cat([b.time_ns for b in batches], 0),
        cat([b.row for b in batches], 0),
        cat([b.well_test for b in batches if b.well_test is not None], 0),
        cat([b.extra for b in batches if b.extra is not None], 0),
        batches[0].extra_names,
    )
