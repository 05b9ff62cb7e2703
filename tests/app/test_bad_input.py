"""Bad input of many kinds: each answer is a 4xx problem+json with a readable detail, never 5xx.

Capture-format errors are found by a real worker process reading the upload (validate queue).
"""

from __future__ import annotations

import io
import json
import stat
import zipfile
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import pytest

from tests.app.conftest import Service, admin_auth
from tests.hostile_captures import pack
from tests.integration.services import ANONYMOUS

PROBLEM = "application/problem+json"
UNKNOWN_ID = "0123456789abcdef0123456789abcdef"


def read_entries(service: Service) -> dict[str, bytes]:
    with zipfile.ZipFile(service.capture_zip) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def with_doc(service: Service, change: Callable[[dict[str, Any]], None]) -> bytes:
    entries = read_entries(service)
    doc = json.loads(entries["capture.json"])
    change(doc)
    entries["capture.json"] = json.dumps(doc).encode()
    return pack(entries)


def first_depth(entries: dict[str, bytes]) -> str:
    return sorted(n for n in entries if "/depth/" in n)[0]


def depth_8bit(service: Service) -> bytes:
    entries = read_entries(service)
    name = first_depth(entries)
    depth = np.asarray(cv2.imdecode(np.frombuffer(entries[name], np.uint8),
                                    cv2.IMREAD_UNCHANGED))
    entries[name] = cv2.imencode(".png", (depth // 256).astype(np.uint8))[1].tobytes()
    return pack(entries)


def depth_corrupt_pixels(service: Service) -> bytes:
    entries = read_entries(service)
    name = first_depth(entries)
    entries[name] = entries[name][:33] + b"\x00garbage" * 50  # valid header, broken data
    return pack(entries)


def depth_missing(service: Service) -> bytes:
    entries = read_entries(service)
    del entries[first_depth(entries)]
    return pack(entries)


def symlink_zip(service: Service) -> bytes:
    entries = read_entries(service)
    buffer = io.BytesIO(pack(entries))
    with zipfile.ZipFile(buffer, "a") as archive:
        info = zipfile.ZipInfo("link")
        info.external_attr = (stat.S_IFLNK | 0o777) << 16
        archive.writestr(info, "/etc/passwd")
    return buffer.getvalue()


def encrypted_zip(service: Service) -> bytes:
    buffer = io.BytesIO(pack(read_entries(service)))
    with zipfile.ZipFile(buffer, "a") as archive:
        info = zipfile.ZipInfo("secret.bin")
        archive.writestr(info, b"x" * 10)
    data = bytearray(buffer.getvalue())
    # Set the "encrypted" flag of the last central-directory record (signature PK\1\2).
    at = data.rfind(b"PK\x01\x02")
    data[at + 8] |= 0x01
    return bytes(data)


def bomb_zip() -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("capture.json", "{}")
        archive.writestr("cam0/depth/000000.png", bytes(5 * 1024 * 1024))
    return buffer.getvalue()


def many_files_zip() -> bytes:
    return pack({"capture.json": b"{}", **{f"junk/{i}.txt": b"x" for i in range(300)}})


def too_large_unpacked() -> bytes:
    rng = np.random.default_rng(0)
    return pack({"capture.json": b"{}", "big.bin": rng.bytes(7 * 1024 * 1024)})


def multipart(body: bytes, field: str = "file", close: bool = True) -> tuple[bytes, str]:
    boundary = "volumeshboundary"
    parts = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"{field}\"; "
             f"filename=\"c.zip\"\r\nContent-Type: application/zip\r\n\r\n").encode()
    parts += body + b"\r\n"
    if close:
        parts += f"--{boundary}--\r\n".encode()
    return parts, f"multipart/form-data; boundary={boundary}"


def chunks(total: int) -> Any:
    block = b"\x00" * (1024 * 1024)
    for _ in range(total // len(block)):
        yield block


ZIP = {"Content-Type": "application/zip"}

# name -> (expected status, builds (method, url, request kwargs) from the service)
Case = Callable[[Service], tuple[str, str, dict[str, Any]]]


def upload(body: Callable[[Service], bytes], headers: dict[str, str] | None = None) -> Case:
    def build(s: Service) -> tuple[str, str, dict[str, Any]]:
        chosen = ZIP if headers is None else headers
        return "POST", "/api/v1/captures", {"content": body(s),
                                             "headers": {**s.auth, **chosen}}
    return build


def form(body: Callable[[Service], bytes], field: str = "file", close: bool = True) -> Case:
    def build(s: Service) -> tuple[str, str, dict[str, Any]]:
        content, ctype = multipart(body(s), field, close)
        return "POST", "/api/v1/captures", {"content": content,
                                             "headers": {**s.auth, "Content-Type": ctype}}
    return build


def job(body: Any, raw: bool = False) -> Case:
    def build(s: Service) -> tuple[str, str, dict[str, Any]]:
        if raw:
            return "POST", "/api/v1/jobs", {"content": body, "headers": {
                **s.auth, "Content-Type": "application/json"}}
        return "POST", "/api/v1/jobs", {"json": body, "headers": s.auth}
    return build


def plain(method: str, url: str, **kwargs: Any) -> Case:
    return lambda s: (method, url, kwargs)


def valid(s: Service) -> bytes:
    return s.capture_zip.read_bytes()


def set_field(path: list[Any], value: Any) -> Callable[[dict[str, Any]], None]:
    def change(doc: dict[str, Any]) -> None:
        target = doc
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
    return change


CASES: dict[str, tuple[int, Case]] = {
    "wrong content type": (415, upload(valid, {"Content-Type": "text/plain"})),
    "no content type": (415, upload(valid, {})),
    "empty body": (400, upload(lambda s: b"")),
    "not a zip": (400, upload(lambda s: b"this is not a zip archive" * 10)),
    "truncated zip": (400, upload(lambda s: valid(s)[: len(valid(s)) // 2])),
    "zip bomb": (413, upload(lambda s: bomb_zip())),
    "unpacked size over limit": (413, upload(lambda s: too_large_unpacked())),
    "too many files": (413, upload(lambda s: many_files_zip())),
    "path traversal": (422, upload(lambda s: pack({**read_entries(s), "../evil.txt": b"x"}))),
    "absolute path": (422, upload(lambda s: pack({**read_entries(s), "/etc/evil": b"x"}))),
    "symbolic link": (422, upload(symlink_zip)),
    "encrypted entry": (422, upload(encrypted_zip)),
    "no capture.json": (422, upload(lambda s: pack({"readme.txt": b"hello"}))),
    "capture.json not JSON": (422, upload(lambda s: pack({**read_entries(s),
                                                          "capture.json": b"{not json"}))),
    "wrong format id": (422, upload(lambda s: with_doc(s, set_field(["format"], "other/9")))),
    "8-bit depth": (422, upload(depth_8bit)),
    "corrupt depth pixels": (422, upload(depth_corrupt_pixels)),
    "missing depth image": (422, upload(depth_missing)),
    "size contradicts intrinsics": (422, upload(lambda s: with_doc(s, set_field(
        ["cameras", 0, "depth_intrinsics", "width"], 96)))),
    "NaN intrinsics": (422, upload(lambda s: with_doc(s, set_field(
        ["cameras", 0, "depth_intrinsics", "fx"], float("nan"))))),
    "negative depth scale": (422, upload(lambda s: with_doc(s, set_field(["depth_scale"], -1)))),
    "non-rigid pose": (422, upload(lambda s: with_doc(s, set_field(
        ["cameras", 0, "world_from_depth"], [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                              [0, 0, 0, 1]])))),
    "declared body over limit": (413, upload(lambda s: b"x", {
        "Content-Type": "application/zip", "Content-Length": str(64 * 1024 * 1024)})),
    "streamed body over limit": (413, lambda s: ("POST", "/api/v1/captures", {
        "content": chunks(10 * 1024 * 1024), "headers": {**s.auth, **ZIP}})),
    "multipart without file field": (400, form(valid, field="other")),
    "multipart without closing boundary": (400, form(valid, close=False)),
    "multipart without boundary": (400, upload(valid, {"Content-Type": "multipart/form-data"})),
    "missing API key": (401, lambda s: ("POST", "/api/v1/captures", {
        "content": valid(s), "headers": {**ZIP, **ANONYMOUS}})),
    "read without API key": (401, lambda s: ("GET", "/api/v1/jobs", {"headers": ANONYMOUS})),
    "wrong API key": (401, lambda s: ("POST", "/api/v1/captures", {
        "content": valid(s), "headers": {**ZIP, "Authorization": "Bearer vmk_wrong"}})),
    "basic auth instead of bearer": (401, lambda s: ("POST", "/api/v1/jobs", {
        "json": {"capture_id": UNKNOWN_ID}, "headers": {"Authorization": "Basic dXNlcjpwdw=="}})),
    "unknown capture id": (404, job({"capture_id": UNKNOWN_ID})),
    "malformed capture id": (422, job({"capture_id": "../../etc"})),
    "unknown job option": (422, job({"capture_id": UNKNOWN_ID, "colour": "blue"})),
    "option out of range": (422, job({"capture_id": UNKNOWN_ID, "draco_position_bits": 99})),
    "option of wrong type": (422, job({"capture_id": UNKNOWN_ID, "enhance": "yes please"})),
    "unknown stage setting": (422, job({"capture_id": UNKNOWN_ID, "enhancement": {"bogus": 1}})),
    "stage setting of wrong kind": (422, job({"capture_id": UNKNOWN_ID,
                                              "meshing": {"poisson_depth": 7.5}})),
    "stage setting not settable": (422, job({"capture_id": UNKNOWN_ID,
                                             "enhancement": {"weights": "x"}})),
    "job body not JSON": (422, job(b"{capture_id: ", raw=True)),
    "job body too large": (413, job(b"{\"capture_id\": \"" + b"a" * 40000 + b"\"}", raw=True)),
    "job body a list": (422, job([1, 2, 3])),
    "unknown job id": (404, plain("GET", f"/api/v1/jobs/{UNKNOWN_ID}")),
    "malformed job id": (422, plain("GET", "/api/v1/jobs/not-a-job")),
    "cancel unknown job": (404, lambda s: ("DELETE", f"/api/v1/jobs/{UNKNOWN_ID}",
                                           {"headers": s.auth})),
    "page size zero": (422, plain("GET", "/api/v1/jobs?limit=0")),
    "unknown job state filter": (422, plain("GET", "/api/v1/jobs?state=sleeping")),
    "unknown capture": (404, plain("GET", f"/api/v1/captures/{UNKNOWN_ID}")),
    "unknown asset": (404, plain("GET", f"/api/v1/assets/{UNKNOWN_ID}/mesh.glb")),
    "unknown asset file": (422, plain("GET", f"/api/v1/assets/{UNKNOWN_ID}/secrets.txt")),
    "unknown path": (404, plain("GET", "/api/v2/everything")),
    "method not allowed": (405, plain("PUT", "/api/v1/jobs")),
}


def test_there_are_at_least_25_kinds() -> None:
    assert len(CASES) >= 25


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input_is_a_4xx_problem(service: Service, name: str) -> None:
    expected, build = CASES[name]
    method, url, kwargs = build(service)
    response = service.client.request(method, url, **kwargs)
    assert response.status_code == expected, (name, response.status_code, response.text)
    assert response.headers["content-type"].startswith(PROBLEM), response.headers
    body = response.json()
    assert body["status"] == expected
    assert isinstance(body["detail"], str) and len(body["detail"]) > 10
    assert body["title"] and body["type"].startswith("https://")
    if expected == 401:
        assert response.headers.get("www-authenticate", "").startswith("Bearer")


def test_rejected_capture_is_not_kept(service: Service) -> None:
    response = service.client.post("/api/v1/captures", content=depth_8bit(service),
                                   headers={**service.auth, **ZIP})
    assert response.status_code == 422
    assert "16-bit" in response.json()["detail"]
    stored = list((service.data_dir / "storage" / "captures").glob("*.zip"))
    # Every zip kept is a capture someone has (an admin key lists all owners').
    listed = service.client.get("/api/v1/captures?limit=100",
                                headers=admin_auth(service)).json()["items"]
    assert {c["sha256"] for c in listed} == {p.stem.split("-")[0] for p in stored}
    assert not list((service.data_dir / "tmp").glob("upload-*"))


def test_revoked_key_is_refused(service: Service) -> None:
    from app.core.security import create_key, revoke_key

    gateway = service.client.app.state.gateway  # type: ignore[attr-defined]
    with gateway.sessions() as session:
        row, key = create_key(session, "short-lived")
    headers = {"Authorization": f"Bearer {key}", "Content-Type": "application/json"}
    body = {"capture_id": UNKNOWN_ID}
    assert service.client.post("/api/v1/jobs", json=body, headers=headers).status_code == 404
    with gateway.sessions() as session:
        assert [r.id for r in revoke_key(session, row.id)] == [row.id]
    response = service.client.post("/api/v1/jobs", json=body, headers=headers)
    assert response.status_code == 401
    assert "revoked" in response.json()["detail"]


@pytest.mark.parametrize("section, settings, named", [
    ("enhancement", {"bogus": 1}, "enhancement.bogus: unknown setting (known: "),
    ("enhancement", {"learned_gain": False},
     "enhancement.learned_gain: removed; the per-vertex gain network"),
    ("meshing", {"poisson_depth": 7.5}, "meshing.poisson_depth: expected an integer"),
    ("calibration", {"icp": 1}, "calibration.icp: expected true or false"),
])
def test_a_bad_stage_setting_names_itself_and_creates_no_job(
        service: Service, section: str, settings: dict, named: str) -> None:
    before = service.client.get("/api/v1/jobs", headers=service.auth).json()["items"]
    body: dict[str, Any] = {"capture_id": UNKNOWN_ID, section: settings}
    if section == "calibration":
        body = {"calibration_capture_id": UNKNOWN_ID, section: settings}
    response = service.client.post("/api/v1/jobs", json=body, headers=service.auth)
    assert response.status_code == 422 and named in response.json()["detail"]
    assert service.client.get("/api/v1/jobs", headers=service.auth).json()["items"] == before
