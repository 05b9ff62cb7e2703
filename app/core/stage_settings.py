"""The names and kinds of every job option section's settings, checked at the gateway so a
misspelt or mistyped setting is a 422 naming it, not a job that fails at its first stage.

The gateway does not import the pipeline; `stage_settings.json` is a copy of
`pipeline.stage_config.settings_kinds()`, kept equal by a test (regenerate it with
`make stage-settings`). Value ranges are still the worker's to check.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

_EXPECTED = {"bool": "true or false", "int": "an integer", "float": "a number",
             "str": "a string", "list": "a list"}


@cache
def stage_settings() -> dict[str, dict[str, str]]:
    """{section: {setting: kind}} (kinds: bool, int, float, str, list, fixed, or
    ``removed: <what replaced it>``)."""
    return json.loads((Path(__file__).with_name("stage_settings.json")).read_text())


def check_settings(section: str, values: dict[str, Any]) -> None:
    """ValueError naming ``section.setting`` for an unknown or removed setting, one that cannot
    be set from options, or a value of the wrong kind."""
    known = stage_settings()[section]
    for key, value in values.items():
        kind = known.get(key)
        if kind is None:
            settable = (k for k, v in known.items() if v in _EXPECTED)
            raise ValueError(f"{section}.{key}: unknown setting (known: {', '.join(settable)})")
        if kind.startswith("removed: "):
            raise ValueError(f"{section}.{key}: removed; {kind.removeprefix('removed: ')}")
        if kind == "fixed":
            raise ValueError(f"{section}.{key}: cannot be set from options")
        if not _is_kind(value, kind):
            raise ValueError(f"{section}.{key}: expected {_EXPECTED[kind]}, got {value!r}")


def _is_kind(value: Any, kind: str) -> bool:
    if kind == "bool":
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False
    if kind == "int":
        return isinstance(value, int)
    if kind == "float":
        return isinstance(value, int | float)
    return isinstance(value, str if kind == "str" else list)
