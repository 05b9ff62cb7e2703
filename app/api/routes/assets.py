"""GET /assets/{id} and its files (mesh.glb, mesh.ply, report.json).

Files never change once written, so they carry strong ETags (their SHA-256), immutable cache
headers, and answer ``Range`` requests (one range) and ``If-None-Match``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Annotated, Any

from fastapi import APIRouter, Path, Request
from fastapi.responses import Response, StreamingResponse

from app.api.deps import ReadAccessDep, SessionDep, StorageDep
from app.core.problems import OPTIONAL_AUTH, READ, ProblemError, problem_responses
from app.schemas import ID_PATTERN, AssetFileName, AssetPublic
from workers.models import Asset

router = APIRouter(prefix="/assets", tags=["assets"])

AssetId = Annotated[str, Path(pattern=ID_PATTERN, description="An asset id.")]
IMMUTABLE = "public, max-age=31536000, immutable"
_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")
# mesh.glb, report.json and mesh.ply (binary PLY) in that order.
_FILE_TYPES: dict[str, Any] = {media: {"schema": {"type": "string", "format": "binary"}}
                               for media in ("model/gltf-binary", "application/json",
                                             "application/octet-stream")}
# Read from the request itself (one range, strong ETags), declared so that clients and the
# contract tests know them.
_FILE_EXTRA: dict[str, Any] = {**OPTIONAL_AUTH, "parameters": [
    {"name": name, "in": "header", "required": False, "description": text,
     "schema": {"type": "string"}}
    for name, text in (("Range", "One `bytes=first-last` range: a 206, or a 416 outside it."),
                       ("If-None-Match", "The file's ETag: a 304 when it matches."),
                       ("If-Range", "Send the range only while the file's ETag is this."))]}


def _asset(session: Any, asset_id: str) -> Asset:
    row = session.get(Asset, asset_id)
    if row is None:
        raise ProblemError(404, f"There is no asset {asset_id}.", kind="not-found")
    return row


@router.get("/{asset_id}", response_model=AssetPublic, openapi_extra=OPTIONAL_AUTH,
            responses=problem_responses(READ, {404: "There is no such asset."}))
def get_asset(asset_id: AssetId, session: SessionDep, _read: ReadAccessDep) -> AssetPublic:
    return AssetPublic.of(_asset(session, asset_id))


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
                       **problem_responses(READ, {
                           404: "There is no such asset, or it has no such file.",
                           416: "The range lies outside the file (`range-not-satisfiable`)."})})
def get_asset_file(asset_id: AssetId, name: AssetFileName, request: Request,
                   session: SessionDep, storage: StorageDep, _read: ReadAccessDep) -> Response:
    """mesh.glb (Draco-compressed glTF binary), mesh.ply or report.json."""
    row = _asset(session, asset_id)
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
