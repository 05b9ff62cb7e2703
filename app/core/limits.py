"""Request body limits, enforced before and while a body streams in."""

from __future__ import annotations

import re

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.core.live import MAX_PREVIEW_BYTES
from app.core.problems import problem_response

UPLOAD_PATH = "/api/v1/captures"
FRAME_SET_PATH = re.compile(r"^/api/v1/streams/[^/]+/frames/[^/]+/?$")
PREVIEW_PATH = re.compile(r"^/api/v1/streams/[^/]+/preview/?$")
_MULTIPART_SLACK = 1024 * 1024


class BodyLimitMiddleware:
    """413 for bodies over the limit: uploads get the upload limit, a stream's frame-sets the
    frame-set limit, its live previews the largest well-formed preview, everything else the
    JSON one.

    A declared Content-Length over the limit is refused before the app runs; a chunked body is
    counted as it arrives and stopped at the limit.
    """

    def __init__(self, app: ASGIApp, upload_limit: int, json_limit: int,
                 frame_set_limit: int | None = None) -> None:
        self.app = app
        self.upload_limit = upload_limit + _MULTIPART_SLACK
        self.json_limit = json_limit
        self.frame_set_limit = json_limit if frame_set_limit is None else frame_set_limit

    def _limit(self, scope: Scope) -> tuple[int, str]:
        """The limit of this request's body, and what to call the body."""
        path, method = scope["path"], scope["method"]
        if method == "POST" and path.rstrip("/") == UPLOAD_PATH:
            return self.upload_limit, "capture upload"
        if method == "PUT" and FRAME_SET_PATH.match(path):
            return self.frame_set_limit, "frame-set"
        if method == "PUT" and PREVIEW_PATH.match(path):
            return MAX_PREVIEW_BYTES, "preview"
        return self.json_limit, "request body"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit, what = self._limit(scope)
        declared = _content_length(scope)
        if declared is not None and declared > limit:
            response = problem_response(
                413, f"The {what} of {declared} bytes is larger than the limit of {limit} bytes.",
                kind="body-too-large", instance=scope["path"])
            await response(scope, receive, send)
            return
        received = 0

        async def counted() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise HTTPException(413, f"The request body passed the limit of {limit} "
                                        "bytes.")
            return message

        await self.app(scope, counted, send)


def _content_length(scope: Scope) -> int | None:
    for name, value in scope.get("headers", ()):
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None
