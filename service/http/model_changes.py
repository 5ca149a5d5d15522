"""``PUT /wells/{well}/model``: replace a well's model, e.g. add the effect ``vfm diagnose``
found; ``POST /wells/{well}/model/rollback``: bring back an earlier version;
``GET /wells/{well}/model/versions``: the versions kept (see docs/guide/trials.md)."""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter

from service.http.deps import EngineDep, KnownWell, StoreDep, TokenDep, WellPath
from service.http.schemas import (
    ErrorOut,
    ModelChangeIn,
    ModelChangeOut,
    ModelVersionOut,
    RollbackIn,
)
from service.store import Store
from vfm_core.timeutil import iso

__all__ = ["router", "versions_of"]

router = APIRouter(prefix="/wells", tags=["wells"])

_REFUSALS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut},
    403: {"model": ErrorOut, "description": "no token configured, or a module not allowed"},
    404: {"model": ErrorOut},
    409: {"model": ErrorOut},
    422: {"model": ErrorOut},
    503: {"model": ErrorOut},
}


@router.put(
    "/{well}/model",
    response_model=ModelChangeOut,
    summary="Replace the well's model (e.g. add an effect found by vfm diagnose)",
    description=(
        "Fits the new model on the well's stored history, compares it with the current one on "
        "the latest 20 % of that history, then swaps it in between two messages with a higher "
        "version; learning goes on during the fit and nothing is lost. When that held-out "
        "check says the new model is worse the change is refused (409, both MAPEs in the "
        "sentence) unless confirm_worse is true. The replaced model then runs on as a shadow "
        "for a trial (trial.* settings) that keeps the change or rolls it back; the reply's "
        "trial and GET /wells/{well} show both errors. Needs the bearer token."
    ),
    responses=_REFUSALS,
)
def change_model(
    well: WellPath, body: ModelChangeIn, _: TokenDep, engine: EngineDep
) -> dict[str, Any]:
    # a plain def: FastAPI runs it on a worker thread, since the refit takes seconds
    return engine.change_model(
        well, body.model, body.effects, body.method, confirm_worse=body.confirm_worse
    )


@router.post(
    "/{well}/model/rollback",
    response_model=ModelChangeOut,
    summary="Bring back an earlier model version of the well",
    description=(
        "The kept checkpoint of that version (GET /wells/{well}: versions) re-learns every "
        "measurement the well learned since it was replaced, then is swapped in with a higher "
        "version, as a model change is (recorded in model_changes with kind 'rollback'); a "
        "running trial ends 'superseded'. Needs the bearer token."
    ),
    responses=_REFUSALS,
)
def rollback_model(
    well: WellPath, body: RollbackIn, _: TokenDep, engine: EngineDep
) -> dict[str, Any]:
    return engine.rollback_model(well, body.version)


def versions_of(store: Store, well: str) -> list[dict[str, Any]]:
    """The well's kept earlier models, newest first, as GET /wells/{well} shows them."""
    out = []
    for row in store.model_versions(well):
        try:
            spec = json.loads(row.spec)
        except ValueError:  # pragma: no cover - written by this service as JSON
            spec = [row.model, [], row.method]
        out.append(
            {
                "version": row.version,
                "model": row.model,
                "effects": list(spec[1]) if len(spec) > 1 else [],
                "method": row.method,
                "replaced": iso(row.data_time_ns),
                "note": row.note,
            }
        )
    return out


@router.get(
    "/{well}/model/versions",
    response_model=list[ModelVersionOut],
    summary="Earlier model versions kept for a rollback",
    responses={404: {"model": ErrorOut}},
)
def model_versions(well: KnownWell, store: StoreDep) -> list[dict[str, Any]]:
    return versions_of(store, well)
