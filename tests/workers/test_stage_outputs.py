"""Stage outputs are deleted once a job's asset is stored, but never under a live job of the
same capture: the store-level rule, storage's prefix delete, and a real embedded job."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import httpx
import pytest

from tests.integration.services import (
    FAST_JOB,
    MotoS3,
    Process,
    base_env,
    free_port,
    make_capture_zip,
    wait_for,
    wait_job,
)
from workers.artifacts import discard_outputs
from workers.context import WorkerContext
from workers.models import Capture, Job
from workers.settings import Settings
from workers.storage import Storage, make_storage

SHA_A, SHA_B = "a" * 64, "b" * 64


@pytest.fixture(params=["local", "s3"])
def storage(request: pytest.FixtureRequest, tmp_path: Path) -> Storage:
    if request.param == "local":
        return make_storage(Settings(data_dir=tmp_path))
    moto: MotoS3 = request.getfixturevalue("moto")
    return make_storage(Settings.model_validate(
        {"data_dir": tmp_path, **moto.settings("volumesh-test")}))


def test_delete_prefix_takes_the_folder_alone(storage: Storage) -> None:
    storage.put_bytes("artifacts/x/00-filter-k.npz", b"1")
    storage.put_bytes("artifacts/x/01-align-k.npz", b"2")
    storage.put_bytes("artifacts/xy/00-filter-k.npz", b"3")  # same start, other folder
    storage.put_bytes("assets/j/mesh.glb", b"4")
    assert storage.delete_prefix("artifacts/x/") == 2
    assert not storage.exists("artifacts/x/00-filter-k.npz")
    assert storage.exists("artifacts/xy/00-filter-k.npz") and storage.exists("assets/j/mesh.glb")
    assert storage.delete_prefix("artifacts/none/") == 0
    with pytest.raises(ValueError, match="prefix"):
        storage.delete_prefix("artifacts/x")
    with pytest.raises(ValueError, match="storage key"):
        storage.delete_prefix("../")


def _job(ctx: WorkerContext, sha256: str, state: str) -> str:
    with ctx.store.sessions() as session:
        if session.get(Capture, sha256[:32]) is None:
            session.add(Capture(id=sha256[:32], sha256=sha256, size_bytes=1,
                                storage_key=f"captures/{sha256}.zip", state="ready"))
        job = Job(capture_id=sha256[:32], state=state)
        session.add(job)
        session.commit()
        return job.id


def _set_state(ctx: WorkerContext, job_id: str, state: str) -> None:
    with ctx.store.sessions() as session:
        row = session.get(Job, job_id)
        assert row is not None
        row.state = state
        session.commit()


def test_outputs_stay_while_another_job_of_the_capture_is_live(tmp_path: Path) -> None:
    ctx = WorkerContext.create(Settings(data_dir=tmp_path))
    done = _job(ctx, SHA_A, "succeeded")
    other = _job(ctx, SHA_A, "running")
    _job(ctx, SHA_B, "running")  # a live job of another capture does not hold these
    keys = [f"artifacts/{SHA_A}/0{i}-stage-k.npz" for i in range(3)]
    for key in [*keys, f"artifacts/{SHA_B}/00-filter-k.npz"]:
        ctx.storage.put_bytes(key, b"npz")
    cached = ctx.settings.cache_dir / "artifacts" / keys[0].replace("/", "_")
    cached.parent.mkdir(parents=True)
    cached.write_bytes(b"npz")

    assert discard_outputs(ctx, SHA_A, done) == 0
    assert all(ctx.storage.exists(k) for k in keys) and cached.exists()

    _set_state(ctx, other, "failed")
    assert discard_outputs(ctx, SHA_A, done) == 3
    assert not any(ctx.storage.exists(k) for k in keys) and not cached.exists()
    assert ctx.storage.exists(f"artifacts/{SHA_B}/00-filter-k.npz")


@pytest.mark.slow
def test_a_finished_job_leaves_its_asset_and_no_stage_outputs(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    port = free_port()
    serve = Process([sys.executable, "-m", "app", "serve", "--port", str(port),
                     "--data-dir", str(data_dir)], base_env(), tmp_path / "serve.log").start()
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60)
    try:
        wait_for(lambda: client.get("/readyz").status_code == 200, 60,
                 f"serve to be ready\n{serve.tail()}", interval_s=0.2)
        auth = {"Authorization": f"Bearer {(data_dir / 'api-key.txt').read_text().strip()}"}
        client.headers.update(auth)
        capture = make_capture_zip(tmp_path, cameras=4, width=160, height=144)
        upload = client.post("/api/v1/captures", headers=auth, files={
            "file": ("capture.zip", capture.read_bytes(), "application/zip")})
        assert upload.status_code == 201, upload.text
        sha256 = upload.json()["sha256"]
        job = client.post("/api/v1/jobs", headers=auth,
                          json={"capture_id": upload.json()["id"], **FAST_JOB})
        assert job.status_code == 202, job.text
        done = wait_job(client, job.json()["id"], {"succeeded", "failed"}, 180)
        assert done["state"] == "succeeded", (done, serve.tail())
        # The export deletes them just after it marks the job succeeded.
        deleted = wait_for(lambda: re.search(rf"deleted (\d+) stage outputs of capture "
                                             rf"{sha256[:12]}", serve.log.read_text()), 30,
                           f"the stage outputs to be deleted\n{serve.tail()}")
        assert int(deleted.group(1)) >= 5  # one per work stage the job ran
    finally:
        client.close()
        serve.stop(grace_s=15.0)
    storage = data_dir / "storage"
    kept = sorted(str(p.relative_to(storage)) for p in storage.rglob("*") if p.is_file())
    job_id = done["id"]
    assert kept[:3] == [f"assets/{job_id}/mesh.glb", f"assets/{job_id}/mesh.ply",
                        f"assets/{job_id}/report.json"]
    assert len(kept) == 4 and re.fullmatch(rf"captures/{sha256}-[0-9a-f]+\.zip", kept[3])
    assert not list((data_dir / "cache").rglob(f"*{sha256}*"))
