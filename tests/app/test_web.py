"""app.web: the viewer's files and vendored three.js served by the gateway, and the sequence
manifest schema."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from pydantic import ValidationError

from app.web import THREE_DIR, SequenceManifest, mount_viewer


@pytest.fixture(scope="module")
def client() -> TestClient:
    if not (THREE_DIR / "build" / "three.webgpu.js").is_file():
        pytest.fail(f"three.js is missing at {THREE_DIR}: run `npm ci` (make setup does)",
                    pytrace=False)
    app = FastAPI()
    mount_viewer(app)
    return TestClient(app)


def test_index_at_root_names_local_three(client: TestClient) -> None:
    response = client.get("/", params={"asset": "0" * 32})
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/html")
    assert '"three": "/vendor/three/build/three.webgpu.js"' in response.text
    assert "https://" not in response.text.split("<body")[0]  # nothing from a CDN


@pytest.mark.parametrize(("path", "media"), [
    ("/static/app/main.js", "text/javascript"),
    ("/static/style.css", "text/css"),
    ("/vendor/three/build/three.webgpu.js", "text/javascript"),
    ("/vendor/three/build/three.tsl.js", "text/javascript"),
    ("/vendor/three/examples/jsm/loaders/GLTFLoader.js", "text/javascript"),
    ("/vendor/three/examples/jsm/libs/draco/draco_wasm_wrapper.js", "text/javascript"),
    ("/vendor/three/examples/jsm/libs/draco/draco_decoder.wasm", "application/wasm"),
])
def test_files_served_with_their_media_type(client: TestClient, path: str, media: str) -> None:
    response = client.get(path)
    assert response.status_code == 200, path
    assert response.headers["content-type"].startswith(media)
    assert len(response.content) > 100


def test_every_module_the_page_imports_is_served(client: TestClient) -> None:
    root = Path(__file__).resolve().parents[2] / "static" / "app"
    for module in root.glob("*.js"):
        assert client.get(f"/static/app/{module.name}").status_code == 200


@pytest.mark.parametrize("path", ["/vendor/three/package.json", "/vendor/three/src/Three.js",
                                  "/static/../app/web.py", "/vendor/three/build/nope.js"])
def test_nothing_else_is_served(client: TestClient, path: str) -> None:
    assert client.get(path).status_code == 404


def test_missing_three_answers_503_problem(tmp_path: Path) -> None:
    app = FastAPI()
    mount_viewer(app, three_dir=tmp_path / "three")
    response = TestClient(app).get("/vendor/three/build/three.webgpu.js")
    assert response.status_code == 503
    assert response.headers["content-type"].startswith("application/problem+json")
    assert "npm ci" in response.json()["detail"]


def test_static_dir_without_index_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="index.html"):
        mount_viewer(FastAPI(), static_dir=tmp_path)


def test_sequence_manifest_example_and_schema(client: TestClient) -> None:
    example = client.get("/sequence-manifest.example.json")
    assert example.status_code == 200
    manifest = SequenceManifest.model_validate(example.json())
    assert manifest.fps > 0 and manifest.frames
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    assert {"fps", "bounds", "frames"} <= set(schemas["SequenceManifest"]["properties"])


@pytest.mark.parametrize(("change", "field"), [
    ({"fps": 0}, "fps"),
    ({"fps": 1000}, "fps"),
    ({"frames": []}, "frames"),
    ({"frames": [{"url": ""}]}, "frames"),
    ({"bounds": {"min": [0, 0, 0], "max": [1, -1, 1]}}, "bounds"),
    ({"bounds": {"min": [0, 0], "max": [1, 1, 1]}}, "bounds"),
    ({"version": 2}, "version"),
])
def test_bad_sequence_manifests_name_the_field(change: dict[str, object], field: str) -> None:
    doc: dict[str, object] = {"fps": 30, "bounds": {"min": [0, 0, 0], "max": [1, 2, 1]},
                              "frames": [{"url": "frames/0.glb"}], **change}
    with pytest.raises(ValidationError) as raised:
        SequenceManifest.model_validate(doc)
    assert raised.value.errors()[0]["loc"][0] == field


def test_viewer_beside_the_api_leaves_its_errors_alone(tmp_path: Path) -> None:
    from app.main import create_app
    from workers.settings import Settings

    app = create_app(Settings(data_dir=tmp_path))  # type: ignore[call-arg]
    client = TestClient(app)
    assert client.get("/").headers["content-type"].startswith("text/html")
    wrong_method = client.put("/api/v1/jobs")
    assert wrong_method.status_code == 405
    assert wrong_method.headers["content-type"].startswith("application/problem+json")
    assert client.get("/api/v1/nothing").status_code == 404
    assert client.get("/openapi.json").status_code == 200
