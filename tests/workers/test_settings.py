"""One settings object: every ``VOLUMESH_*`` variable the code names is a field with a
description, and README's configuration table is the one rendered from it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from workers.settings import Settings
from workers.settings_table import (
    BEGIN,
    END,
    env_name,
    marked_table,
    settings_table,
    with_table,
)

ROOT = Path(__file__).resolve().parents[2]
CLIENT_VARIABLES = {"VOLUMESH_API_KEY"}
"""Read by `volumesh agent`, a client of the service: not a setting of the service."""


def test_readmes_table_is_the_one_the_settings_give() -> None:
    table = marked_table((ROOT / "README.md").read_text())
    assert table is not None, f"README.md has no {BEGIN} ... {END} lines"
    assert table == settings_table(), (
        "README.md's configuration table is stale: run "
        "`.venv/bin/python -m workers.settings_table --readme README.md`")


def test_every_variable_the_code_names_is_a_setting() -> None:
    named = set()
    for package in ("app", "workers", "pipeline"):
        for path in (ROOT / package).rglob("*.py"):
            named |= set(re.findall(r"VOLUMESH_[A-Z][A-Z0-9_]*", path.read_text()))
    assert named, "the scan found no variable at all"
    assert named - CLIENT_VARIABLES <= {env_name(field) for field in Settings.model_fields}


def test_every_setting_says_what_it_does() -> None:
    assert [f for f, info in Settings.model_fields.items() if not info.description] == []


def test_the_table_names_the_variables_pydantic_reads(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(env_name("progress_interval_s"), "1.5")
    assert Settings().progress_interval_s == 1.5
    assert "| `VOLUMESH_PROGRESS_INTERVAL_S` | `0.25` |" in settings_table()


def test_the_table_goes_between_the_markers_only() -> None:
    text = f"intro\n{BEGIN}\nold\n{END}\nrest\n"
    updated = with_table(text, "| a |")
    assert updated == f"intro\n{BEGIN}\n| a |\n{END}\nrest\n"
    assert marked_table(updated) == "| a |"
    with pytest.raises(ValueError, match="settings:begin"):
        with_table("no markers", "| a |")
