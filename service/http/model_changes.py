"""``PUT /wells/{well}/model``: replace a well's model, e.g. add the effect ``vfm diagnose`` found."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from service.http.deps import EngineDep, TokenDep, WellPath
from service.http.schemas import ErrorOut, ModelChangeIn, ModelChangeOut

__all__ = ["router"]

router = APIRouter(prefix="/wells", tags=["wells"])


@router.put(
    "/{well}/model",
    response_model=ModelChangeOut,
    summary="Replace the well's model (e.g. add an effect found by vfm diagnose)",
    description=(
        "Fits the new model on the well's stored history, compares it with the current one on "
        "the latest 20 % of that history, then swaps it in between two messages with a higher "
        "version; learning goes on during the fit and nothing is lost. Needs the bearer token. "
        "GET /wells/{well} then shows the new model, its parameters and its rolling MAPE."
    ),
    responses={
        401: {"model": ErrorOut},
        403: {"model": ErrorOut, "description": "no token configured, or a module not allowed"},
        404: {"model": ErrorOut},
        409: {"model": ErrorOut},
        422: {"model": ErrorOut},
        503: {"model": ErrorOut},
    },
)
def change_model(
    well: WellPath, body: ModelChangeIn, _: TokenDep, engine: EngineDep
) -> dict[str, Any]:
    # a plain def: FastAPI runs it on a worker thread, since the refit takes seconds
    return engine.change_model(well, body.model, body.effects, body.method)
