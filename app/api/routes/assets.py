"""GET /assets/{id} and its files (mesh.glb, mesh.ply, report.json; a sequence's
sequence.json); POST /assets/{id}/share.

An asset is read with an API key of its owner, or with a share token (``?share=TOKEN``) that
its owner made: a link that works for anyone, for this asset only (a sequence's: also its
frames' assets), until it expires.

Files never change once written, so they carry strong ETags (their SHA-256), immutable cache
headers, and answer ``Range`` requests (one range) and ``If-None-Match``.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import Response, StreamingResponse
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.api.deps import BearerDep, CallerDep, GatewayDep, SessionDep, StorageDep, authenticate
from app.core.problems import BODY, READ, WRITE, ProblemError, problem_responses
from app.core.sharing import share_token, token_grants_any
from app.schemas import (
    API_PREFIX,
    ID_PATTERN,
    AssetFileName,
    AssetPublic,
    AssetShareCreate,
    AssetSharePublic,
)
from workers.models import Asset, Job

router = APIRouter(prefix="/assets", tags=["assets"])

AssetId = Annotated[str, Path(pattern=ID_PATTERN, description="An asset id.")]
# Private: an asset is its owner's, so no shared cache may keep it; it never changes, so the
# browser keeps it for good.
IMMUTABLE = "private, max-age=31536000, immutable"
_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")
# mesh.glb, report.json and mesh.ply (binary PLY) in that order.
_FILE_TYPES: dict[str, Any] = {media: {"schema": {"type": "string", "format": "binary"}}
                               for media in ("model/gltf-binary", "application/json",
                                             "application/octet-stream")}
ShareToken = Annotated[str | None, Query(
    min_length=3, max_length=80, pattern=r"^[0-9]{1,12}\.[A-Za-z0-9_-]{43}$",
    description="A share token (POST /assets/{asset_id}/share) in place of an API key.")]
# An API key or a share token: the key is not required, so the empty requirement is listed.
_KEY_OR_SHARE: dict[str, Any] = {"security": [{"HTTPBearer": []}, {}]}
_NO_ASSET = {404: "There is no such asset (or another owner's)."}
_READ = {**READ, 401: "No valid API key and no valid share token (`unauthorized`, "
                      "`WWW-Authenticate: Bearer`)."}
# Read from the request itself (one range, strong ETags), declared so that clients and the
# contract tests know them.
_FILE_EXTRA: dict[str, Any] = {**_KEY_OR_SHARE, "parameters": [
    {"name": name, "in": "header", "required": False, "description": text,
     "schema": {"type": "string"}}
    for name, text in (("Range", "One `bytes=first-last` range: a 206, or a 416 outside it."),
                       ("If-None-Match", "The file's ETag: a 304 when it matches."),
                       ("If-Range", "Send the range only while the file's ETag is this."))]}


def _owned_asset(session: Session, asset_id: str) -> tuple[Asset, str | None] | None:
    """The asset and its owner (its job's), or None."""
    found = session.execute(select(Asset, Job.owner).join(Job, Job.id == Asset.job_id)
                            .where(Asset.id == asset_id)).first()
    return None if found is None else (found[0], found[1])


def _share_scopes(session: Session, asset_id: str) -> list[str]:
    """The assets whose share link opens this one: itself, and the sequence's asset when it
    is a frame's."""
    sequence_asset = session.scalar(
        select(Job.asset_id).where(Job.id == select(Job.parent_id).join(
            Asset, Asset.job_id == Job.id).where(Asset.id == asset_id).scalar_subquery()))
    return [asset_id] if sequence_asset is None else [asset_id, sequence_asset]


def _readable_asset(session: Session, gateway: Any, asset_id: str, credentials: Any,
                    share: str | None) -> tuple[Asset, bool]:
    """The asset, when the request's share token or key may read it; and whether it was the
    token (a viewer that holds a key of its own also opens links shared with it)."""
    shared = share is not None and token_grants_any(
        gateway.share_secret, _share_scopes(session, asset_id), share, time.time())
    if share is not None and not shared and credentials is None:
        raise ProblemError(401, "The share link is not valid for this asset, or it has "
                           "expired; ask its owner for a new one.", kind="unauthorized",
                           headers={"WWW-Authenticate": 'Bearer realm="volumesh"'})
    caller = None if shared else authenticate(gateway, credentials)
    found = _owned_asset(session, asset_id)
    if found is None or (caller is not None and not caller.sees(found[1])):
        raise ProblemError(404, f"There is no asset {asset_id}.", kind="not-found")
    return found[0], shared


@router.get("/{asset_id}", response_model=AssetPublic, openapi_extra=_KEY_OR_SHARE,
            responses=problem_responses(_READ, _NO_ASSET))
def get_asset(asset_id: AssetId, session: SessionDep, gateway: GatewayDep,
              credentials: BearerDep, share: ShareToken = None) -> AssetPublic:
    row, shared = _readable_asset(session, gateway, asset_id, credentials, share)
    return AssetPublic.of(row, share if shared else None)


@router.post("/{asset_id}/share", status_code=201, response_model=AssetSharePublic,
             summary="Make a link that shows the asset to anyone who has it",
             responses=problem_responses(WRITE, BODY, _NO_ASSET))
def share_asset(asset_id: AssetId, body: AssetShareCreate, session: SessionDep,
                gateway: GatewayDep, caller: CallerDep) -> AssetSharePublic:
    """A token that reads this asset and its files with no API key until it expires (for the
    viewer, a three.js page, a client). Links cannot be revoked one by one: share for as
    short a time as will do."""
    found = _owned_asset(session, asset_id)
    if found is None or not caller.sees(found[1]):
        raise ProblemError(404, f"There is no asset {asset_id}.", kind="not-found")
    expires_unix_s = int(time.time()) + body.expires_in_s
    token = share_token(gateway.share_secret, asset_id, expires_unix_s)
    files = {name: f"{API_PREFIX}/assets/{asset_id}/{name}?share={token}"
             for name in found[0].files or {}}
    if "sequence.json" in files:  # the viewer plays it; the token opens its frames too
        manifest = quote(f"{API_PREFIX}/assets/{asset_id}/sequence.json?share={token}", safe="/")
        viewer_url = f"/?sequence={manifest}"
    else:
        viewer_url = f"/?asset={asset_id}&share={token}"
    return AssetSharePublic(asset_id=asset_id, share=token,
                            expires_at=datetime.fromtimestamp(expires_unix_s, UTC),
                            viewer_url=viewer_url, files=files)


def parse_range(header: str, size: int) -> tuple[int, int] | None:
    """(first, last) byte of a single ``bytes=`` range; None to send the whole file.

    Raises a 416 problem for a range outside the file. Several ranges are answered whole
    (allowed by RFC 9110), as are ranges in other units.
    """
    match = _RANGE.match(header.strip())
    if match is None:
        return None
    first_text, last_text = match.groups()
    if not first_text and not last_text:
        return None
    if not first_text:  # the last N bytes
        suffix = int(last_text)
        if suffix == 0:
            raise _unsatisfiable(size)
        return max(0, size - suffix), size - 1
    first = int(first_text)
    last = min(int(last_text), size - 1) if last_text else size - 1
    if first >= size or (last_text and int(last_text) < first):
        raise _unsatisfiable(size)
    return first, last


def _unsatisfiable(size: int) -> ProblemError:
    return ProblemError(416, f"The requested range lies outside the file of {size} bytes.",
                        kind="range-not-satisfiable", headers={"Content-Range": f"bytes */{size}"})


def _etag_matches(header: str | None, etag: str) -> bool:
    if not header:
        return False
    tags = [t.strip().removeprefix("W/") for t in header.split(",")]
    return "*" in tags or etag in tags


@router.head("/{asset_id}/{name}", include_in_schema=False)
@router.get("/{asset_id}/{name}", response_class=Response, openapi_extra=_FILE_EXTRA,
            responses={200: {"content": _FILE_TYPES, "description": "The file."},
                       206: {"content": _FILE_TYPES, "description": "Part of the file (Range)."},
                       304: {"description": "Not modified (If-None-Match)."},
                       **problem_responses(_READ, {
                           404: "There is no such asset (or another owner's), or it has no "
                                "such file.",
                           416: "The range lies outside the file (`range-not-satisfiable`)."})})
def get_asset_file(asset_id: AssetId, name: AssetFileName, request: Request,
                   session: SessionDep, storage: StorageDep, gateway: GatewayDep,
                   credentials: BearerDep, share: ShareToken = None) -> Response:
    """mesh.glb (Draco-compressed glTF binary), mesh.ply or report.json; a sequence job's
    asset holds sequence.json (the viewer's manifest; its frames' GLBs are linked relative to
    it, ``../{frame asset id}/mesh.glb``)."""
    row, _ = _readable_asset(session, gateway, asset_id, credentials, share)
    entry = (row.files or {}).get(name)
    if entry is None:
        raise ProblemError(404, f"Asset {asset_id} has no {name}.", kind="not-found")
    etag = f'"{entry["sha256"]}"'
    size = int(entry["bytes"])
    headers = {"ETag": etag, "Cache-Control": IMMUTABLE, "Accept-Ranges": "bytes"}
    if _etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    status, first, last = 200, 0, size - 1
    wanted = request.headers.get("range")
    if wanted and _if_range_ok(request.headers.get("if-range"), etag):
        span = parse_range(wanted, size)
        if span is not None:
            status, (first, last) = 206, span
            headers["Content-Range"] = f"bytes {first}-{last}/{size}"
    headers["Content-Length"] = str(last - first + 1 if size else 0)
    media = entry.get("content_type", "application/octet-stream")
    if name == "mesh.glb":
        headers["Content-Disposition"] = f'inline; filename="{asset_id}.glb"'
    if request.method == "HEAD" or size == 0:
        return Response(status_code=status, headers=headers, media_type=media)
    body: Iterator[bytes] = storage.iter_range(entry["key"], first, last)
    return StreamingResponse(body, status_code=status, headers=headers, media_type=media)


def _if_range_ok(if_range: str | None, etag: str) -> bool:
    return if_range is None or if_range.strip() == etag
