"""The browser viewer: serves ``static/`` and the vendored three.js (with its Draco decoder).

Everything the page needs comes from the gateway itself, so the viewer works offline:

- ``/``                      the viewer page (``/?asset=ID``, ``/?sequence=URL`` are read by it)
- ``/static/...``            the page's own ES modules and style sheet (``static/`` in the repo)
- ``/vendor/three/build/...``, ``/vendor/three/examples/jsm/...``
                             three.js and its add-ons from ``node_modules/three`` (npm set-up),
                             including the Draco decoder in ``examples/jsm/libs/draco/``
- ``/sequence-manifest.example.json``
                             an example of the sequence manifest the viewer plays; its schema
                             (:class:`SequenceManifest`) is in the OpenAPI document

The page's files live under prefixes rather than a catch-all mount at ``/``: a catch-all would
answer API requests with a wrong method (405 with an ``Allow`` header) in place of the API.
"""

from __future__ import annotations

import logging
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, JSONResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator
from starlette.staticfiles import StaticFiles

log = logging.getLogger(__name__)

_REPO_ROOT = Path(__file__).resolve().parents[1]
STATIC_DIR = _REPO_ROOT / "static"
THREE_DIR = _REPO_ROOT / "node_modules" / "three"
VIEWER_TAG = "viewer"


class SequenceBounds(BaseModel):
    """An axis-aligned box that holds every frame, in the frames' own coordinates (metres)."""

    model_config = ConfigDict(extra="forbid")

    min: tuple[float, float, float] = Field(description="Smallest x, y, z over all frames, metres.")
    max: tuple[float, float, float] = Field(description="Largest x, y, z over all frames, metres.")

    @model_validator(mode="after")
    def _ordered(self) -> SequenceBounds:
        if any(low > high for low, high in zip(self.min, self.max, strict=True)):
            raise ValueError("bounds.min must not exceed bounds.max on any axis")
        return self


class SequenceFrame(BaseModel):
    """One frame of a volumetric video."""

    model_config = ConfigDict(extra="allow")

    url: str = Field(
        min_length=1,
        description="Where the frame's GLB (Draco allowed) is; relative URLs resolve against the "
        "manifest's own URL.",
    )


class SequenceManifest(BaseModel):
    """A volumetric video as the viewer plays it (``/?sequence=URL`` with URL serving this JSON).

    The viewer fits the camera once to ``bounds`` (so the view does not jump between frames),
    shows frame *i* at time *i / fps*, loops at the end and fetches the next frames ahead of
    playback. Extra keys are allowed and ignored (for example per-frame ``triangles``).
    """

    model_config = ConfigDict(extra="allow")

    version: int = Field(default=1, ge=1, le=1, description="Manifest format version (1).")
    fps: float = Field(gt=0, le=240, description="Playback rate, frames per second.")
    bounds: SequenceBounds = Field(description="A box holding every frame, metres.")
    frames: list[SequenceFrame] = Field(min_length=1, description="The frames in play order.")


_EXAMPLE_MANIFEST = SequenceManifest(
    fps=30,
    bounds=SequenceBounds(min=(-0.5, 0.0, -0.5), max=(0.5, 1.8, 0.5)),
    frames=[SequenceFrame(url=f"frames/{i:05d}.glb") for i in range(3)],
)


def mount_viewer(
    app: FastAPI,
    *,
    static_dir: Path = STATIC_DIR,
    three_dir: Path = THREE_DIR,
) -> None:
    """Serves the viewer page at ``/`` and its files under ``/static`` and ``/vendor/three``.

    When three.js is not installed (``npm ci`` not run) the API still works; the vendor paths
    answer 503 with a problem saying how to install it.
    """
    index = static_dir / "index.html"
    if not index.is_file():
        raise ValueError(f"static_dir {str(static_dir)!r} holds no index.html")

    @app.get("/", include_in_schema=False)
    async def viewer_page() -> FileResponse:
        # Revalidated every time: the page names the module versions it loads.
        return FileResponse(index, headers={"Cache-Control": "no-cache"})

    @app.get(
        "/sequence-manifest.example.json",
        response_model=SequenceManifest,
        tags=[VIEWER_TAG],
        summary="An example volumetric-video manifest (its schema is the viewer's contract)",
    )
    async def sequence_manifest_example() -> SequenceManifest:
        """The viewer plays `/?sequence=URL` where URL serves JSON of this shape."""
        return _EXAMPLE_MANIFEST

    app.mount("/static", StaticFiles(directory=static_dir), name="viewer-static")
    _mount_three(app, three_dir)


def _mount_three(app: FastAPI, three_dir: Path) -> None:
    parts = {"build": three_dir / "build", "examples/jsm": three_dir / "examples" / "jsm"}
    for url_part, directory in parts.items():
        prefix = f"/vendor/three/{url_part}"
        if directory.is_dir():
            app.mount(prefix, StaticFiles(directory=directory), name=f"three-{url_part}")
            continue
        log.warning("three.js is missing at %s: the viewer will not load (run `npm ci`)",
                    directory)

        async def missing(request: object, _directory: Path = directory) -> JSONResponse:
            return JSONResponse(
                {
                    "type": "https://volumesh.dev/problems/viewer-not-installed",
                    "title": "Service Unavailable",
                    "status": 503,
                    "detail": f"three.js is not installed at {_directory}; run `npm ci` in the "
                    "project root (make setup does).",
                },
                status_code=503,
                media_type="application/problem+json",
            )

        app.add_route(prefix + "/{path:path}", missing, include_in_schema=False)
