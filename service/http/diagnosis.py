"""Diagnosis from the service: ``POST /wells/{well}/diagnosis`` starts one (bearer token),
``GET /diagnosis/{job}`` follows it, ``GET /diagnosis/{job}/report.html`` is its report.

The job (:mod:`service.diagnosis`) runs ``vfm diagnose`` on the well's stored history in a
process of its own; one runs at a time (409 for a second) within
``http.diagnosis_budget_s``. Once done, the answer carries the diagnosis JSON (the fields
``vfm diagnose`` writes to diagnosis.json) and a link to its report; each candidate's
``spec`` is what ``PUT /wells/{well}/model`` takes as an effect. The diagnosis replays the
well's own learning method (the live error the service shows, and the outage error) and
tests each candidate on the other wells that run the same model too (the field's evidence
beside the well's): see the diagnosis guide.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Path
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict, Field

from service.diagnosis import KEEP_JOBS, MODELS, DiagnosisJobs, Job
from service.errors import Starting
from service.http.deps import KnownWell, ServiceDep, TokenDep
from service.http.schemas import ErrorOut

__all__ = ["router", "DiagnosisIn", "request_method"]

router = APIRouter(tags=["diagnosis"])


class DiagnosisIn(BaseModel):
    """What to diagnose: the base model and its effects, the candidate effects, the split."""

    model_config = ConfigDict(extra="forbid")

    model: str | None = Field(
        default=None,
        description="base model: mm, hem or ham; default: the well's model when it is one of "
        "these, else mm",
    )
    method: str | None = Field(
        default=None,
        max_length=40,
        description="the learning method replayed for the live and outage errors (ol, "
        "pbl:<period>, bayes, ...); default: the well's own, as the service runs it",
    )
    pool: bool = Field(
        default=True,
        description="test the candidates on every well that runs the same model and method "
        "too (the field's evidence beside the well's); false: the well's data alone",
    )
    candidates: list[str] | None = Field(
        default=None,
        max_length=50,
        description="candidate effects (library names, e.g. erosion); default: the library's set",
    )
    base_effects: list[str] | None = Field(
        default=None,
        max_length=20,
        description="effects the model already has: every run has them and the diagnosis "
        "looks for what is missing beyond them; default: the effects in the well's model now "
        "([] for the bare model)",
    )
    split: str | None = Field(default=None, description="first day scored, e.g. 2019-01-01")
    suggest: bool = Field(
        default=True, description="fit a generic correction for a driver outside the library"
    )


def request_base(
    running: dict[str, Any], model: str | None, base: list[str] | None
) -> tuple[str, list[str], bool]:
    """The base model and effects of a diagnosis request, and whether the effects are the
    well's own: what the request gives, else the model the well runs (``running``, its
    API snapshot) when it is mm, hem or ham, else mm; its effects only with its own base
    model (another base model starts without effects)."""
    runs = running.get("base_model")
    if model is None:
        model = runs if runs in MODELS else "mm"
    if base is not None:
        return model, list(base), False
    return model, list(running.get("effects") or []) if model == runs else [], True


def request_method(running: dict[str, Any], method: str | None) -> str:
    """The learning method a diagnosis replays: the request's, else the well's own (its
    API snapshot), else ol."""
    if method is not None:
        return method
    own = running.get("method")
    return own if isinstance(own, str) and own else "ol"


def get_jobs(service: ServiceDep) -> DiagnosisJobs:
    jobs = getattr(service, "diagnoses", None)
    if jobs is None:
        raise Starting("The service is starting; retry in a few seconds.")
    return jobs  # type: ignore[no-any-return]


JobsDep = Annotated[DiagnosisJobs, Depends(get_jobs)]


def _job(job: str, jobs: DiagnosisJobs) -> Job:
    found = jobs.get(job)
    if found is None:
        raise HTTPException(
            404,
            f"No diagnosis job '{job[:40]}' is known (the last {KEEP_JOBS} are kept, across "
            "restarts); start one with POST /wells/{well}/diagnosis.",
        )
    return found


JobPath = Annotated[str, Path(max_length=64, description="the job id POST answered with")]


@router.post(
    "/wells/{well}/diagnosis",
    status_code=202,
    summary="Start a diagnosis of the well's stored history (background job)",
    description=(
        "Runs vfm diagnose on the well's history in the service's store, off the engine's "
        "workers; answers at once with the job (follow it with GET /diagnosis/{job}). One "
        "runs at a time: a second answers 409. Needs the bearer token."
    ),
    responses={
        401: {"model": ErrorOut},
        403: {"model": ErrorOut},
        404: {"model": ErrorOut},
        409: {"model": ErrorOut},
        422: {"model": ErrorOut},
    },
)
def start_diagnosis(
    well: KnownWell,
    _: TokenDep,
    jobs: JobsDep,
    service: ServiceDep,
    body: DiagnosisIn | None = None,
) -> dict[str, Any]:
    body = body or DiagnosisIn()
    engine = service.engine
    st = engine.wells.get(well) if engine is not None else None
    snapshot = st.snapshot if st is not None else {}
    model, base, own = request_base(snapshot, body.model, body.base_effects)
    job = jobs.start(
        well,
        model=model,
        method=request_method(snapshot, body.method),
        pool=body.pool,
        candidates=body.candidates,
        split=body.split,
        suggest=body.suggest,
        base_effects=base,
        base_from_model=own,
    )
    return job.view() | {"status": f"/diagnosis/{job.id}"}


@router.get(
    "/diagnosis/{job}",
    summary="A diagnosis job: state, progress, and the diagnosis once done",
    responses={404: {"model": ErrorOut}},
)
def diagnosis_job(job: JobPath, jobs: JobsDep) -> dict[str, Any]:
    return _job(job, jobs).view()


@router.get(
    "/diagnosis/{job}/report.html",
    summary="The diagnosis report (HTML)",
    response_class=FileResponse,
    responses={200: {"content": {"text/html": {}}}, 404: {"model": ErrorOut}},
)
def diagnosis_report(job: JobPath, jobs: JobsDep) -> FileResponse:
    found = _job(job, jobs)
    page = found.folder / "report.html"
    if found.state != "done" or not page.is_file():
        raise HTTPException(
            404,
            f"The diagnosis {found.id} has no report (state {found.state}); wait until it is done.",
        )
    return FileResponse(page, media_type="text/html")
