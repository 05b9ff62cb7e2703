"""`volumesh keys create|list|revoke` through the real command line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from fastapi.testclient import TestClient

from app.main import create_app
from tests.integration.services import ROOT, base_env
from workers.settings import Settings


def _cli(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "app", "keys", *args], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=60)


def test_create_list_revoke(tmp_path: Path) -> None:
    env = base_env(data_dir=str(tmp_path))
    created = _cli(env, "create", "--name", "ci robot")
    assert created.returncode == 0, created.stderr
    key = created.stdout.strip().splitlines()[-1]  # alone on the last line
    assert key.startswith("vmk_") and " " not in key and len(key) > 40
    assert key not in (tmp_path / "volumesh.db").read_bytes().decode("latin-1")  # hashed
    listed = _cli(env, "list")
    assert "ci robot" in listed.stdout and "live" in listed.stdout
    assert key not in listed.stdout

    with TestClient(create_app(Settings(data_dir=tmp_path), viewer=False)) as client:
        headers = {"Authorization": f"Bearer {key}"}
        body = {"capture_id": "0" * 32}
        assert client.post("/api/v1/jobs", json=body, headers=headers).status_code == 404
        revoked = _cli(env, "revoke", "ci robot")
        assert revoked.returncode == 0 and "revoked" in revoked.stdout
        assert client.post("/api/v1/jobs", json=body, headers=headers).status_code == 401
    assert "revoked" in _cli(env, "list").stdout


def test_bad_key_commands_are_one_line_errors(tmp_path: Path) -> None:
    env = base_env(data_dir=str(tmp_path))
    unknown = _cli(env, "revoke", "nobody")
    assert unknown.returncode == 2
    assert unknown.stderr.strip().startswith("volumesh: error: KEY: no live key")
    empty = _cli(env, "create", "--name", "  ")
    assert empty.returncode == 2 and "--name" in empty.stderr


def test_project_and_admin_keys(tmp_path: Path) -> None:
    env = base_env(data_dir=str(tmp_path))
    keys = {}
    for name, extra in (("one", ["--project", "studio"]), ("two", ["--project", "studio"]),
                        ("ops", ["--admin"]), ("solo", [])):
        created = _cli(env, "create", "--name", name, *extra)
        assert created.returncode == 0, created.stderr
        keys[name] = {"Authorization": f"Bearer {created.stdout.strip().splitlines()[-1]}"}
    listed = _cli(env, "list").stdout
    assert listed.count("project:studio") == 2 and "admin" in listed
    rig = {"world_from_depth": {"cam0": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}}
    with TestClient(create_app(Settings(data_dir=tmp_path), viewer=False)) as client:
        made = client.post("/api/v1/rigs", json=rig, headers=keys["one"]).json()["id"]
        seen = {name: client.get(f"/api/v1/rigs/{made}", headers=auth).status_code
                for name, auth in keys.items()}
    assert seen == {"one": 200, "two": 200, "ops": 200, "solo": 404}
