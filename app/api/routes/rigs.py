"""POST /rigs, GET /rigs, GET /rigs/{id}, GET /rigs/{id}/rig.json: saved camera poses.

A rig is uploaded as the rig.json ``volumesh calibrate`` writes, or saved by a job that
calibrates first (``calibration_capture_id``); later jobs use it with ``rig_id``.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query, Response
from fastapi.responses import JSONResponse
from sqlalchemy import select

from app.api.deps import CallerDep, SessionDep
from app.api.pagination import PageLimit, PageOffset, fetch_page
from app.core.problems import BODY, READ, WRITE, ProblemError, located, problem_responses
from app.core.security import Caller
from app.schemas import API_PREFIX, ID_PATTERN, RigCreate, RigPage, RigPublic
from workers.models import Rig, new_id

router = APIRouter(prefix="/rigs", tags=["rigs"])

_NO_RIG = {404: "There is no such rig (or another owner's)."}
RigId = Annotated[str, Path(pattern=ID_PATTERN, description="A rig id.")]


def find_rig(session: SessionDep, caller: Caller, rig_id: str) -> Rig:
    row = session.get(Rig, rig_id)
    if row is None or not caller.sees(row.owner):
        raise ProblemError(404, f"There is no rig {rig_id}; upload one with POST "
                           f"{API_PREFIX}/rigs or calibrate with a job's "
                           "calibration_capture_id.", kind="not-found")
    return row


@router.post("", status_code=201, response_model=RigPublic, summary="Save a rig file",
             responses={**located(201, "The rig, saved."), **problem_responses(WRITE, BODY, {
                 422: "A bad body: the detail names the camera and why when a pose is not a "
                      "finite 4x4 rigid transform or a camera id is malformed "
                      "(`validation-error`)."})})
def create_rig(body: RigCreate, response: Response, session: SessionDep,
               caller: CallerDep) -> RigPublic:
    row = Rig(id=new_id(), name=body.name, owner=caller.owner,
              cameras=sorted(body.world_from_depth),
              document=body.document(), source="upload")
    session.add(row)
    session.commit()
    response.headers["Location"] = f"{API_PREFIX}/rigs/{row.id}"
    return RigPublic.of(row)


@router.get("", response_model=RigPage, summary="List rigs, newest first",
            responses=problem_responses(READ))
def list_rigs(session: SessionDep, caller: CallerDep, limit: PageLimit = 20,
              offset: PageOffset = 0,
              name: Annotated[str | None, Query(min_length=1, max_length=100)] = None
              ) -> RigPage:
    query = select(Rig) if caller.admin else select(Rig).where(Rig.owner == caller.owner)
    if name is not None:
        query = query.where(Rig.name == name)
    rows, total = fetch_page(session, query, (Rig.created_at.desc(), Rig.id), limit, offset)
    return RigPage(items=[RigPublic.of(r) for r in rows], total=total, limit=limit,
                   offset=offset)


@router.get("/{rig_id}", response_model=RigPublic, responses=problem_responses(READ, _NO_RIG))
def get_rig(rig_id: RigId, session: SessionDep, caller: CallerDep) -> RigPublic:
    return RigPublic.of(find_rig(session, caller, rig_id))


@router.get("/{rig_id}/rig.json", summary="The rig file, as `volumesh calibrate` writes it",
            responses={200: {"content": {"application/json": {"schema": {"type": "object"}}}},
                       **problem_responses(READ, _NO_RIG)})
def get_rig_file(rig_id: RigId, session: SessionDep, caller: CallerDep) -> JSONResponse:
    row = find_rig(session, caller, rig_id)
    return JSONResponse(row.document, headers={
        "Content-Disposition": f'attachment; filename="rig-{row.id}.json"'})
