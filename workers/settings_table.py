"""README's configuration table, rendered from :class:`workers.settings.Settings` so the two
cannot drift apart (a test compares them).

``python -m workers.settings_table`` prints the table; with ``--readme README.md`` it writes
it into that file between the marker lines instead.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

from workers.settings import Settings

BEGIN = "<!-- settings:begin -->"
END = "<!-- settings:end -->"
_UNITS = (("GiB", 1024 ** 3), ("MiB", 1024 ** 2), ("KiB", 1024))


def env_name(field: str) -> str:
    """The environment variable that sets ``field``."""
    return f"{Settings.model_config.get('env_prefix', '')}{field}".upper()


def _default(field: str, value: Any) -> str:
    if value is None or value == []:
        return "unset"
    if isinstance(value, bool):
        return "`true`" if value else "`false`"
    if isinstance(value, list):
        return f"`{','.join(str(v) for v in value)}`"
    text = f"`{value}`"
    if field.endswith("_bytes") and isinstance(value, int):
        for unit, size in _UNITS:
            if value >= size and value % size == 0:
                return f"{text} ({value // size} {unit})"
    return text


def _meaning(description: str | None) -> str:
    """One table cell: a field's docstring on one line, a field named by its variable."""
    text = " ".join((description or "").split())

    def code(match: re.Match[str]) -> str:
        word = match.group(1)
        return f"`{env_name(word)}`" if word in Settings.model_fields else f"`{word}`"

    return re.sub(r"``(.+?)``", code, text).replace("|", "\\|")


def settings_table() -> str:
    """The Markdown table ``variable | default | meaning``, one row per setting."""
    rows = ["| variable | default | meaning |", "|---|---|---|"]
    for field, info in Settings.model_fields.items():
        default = info.get_default(call_default_factory=True)
        rows.append(f"| `{env_name(field)}` | {_default(field, default)} | "
                    f"{_meaning(info.description)} |")
    return "\n".join(rows)


def marked_table(text: str) -> str | None:
    """What stands between the marker lines of ``text`` (None: no markers)."""
    begin, end = text.find(BEGIN), text.find(END)
    if begin < 0 or end < begin:
        return None
    return text[begin + len(BEGIN):end].strip("\n")


def with_table(text: str, table: str) -> str:
    """``text`` with ``table`` between its marker lines; ValueError when they are missing."""
    begin, end = text.find(BEGIN), text.find(END)
    if begin < 0 or end < begin:
        raise ValueError(f"no {BEGIN} ... {END} lines to put the table between")
    return f"{text[:begin + len(BEGIN)]}\n{table}\n{text[end:]}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m workers.settings_table")
    parser.add_argument("--readme", type=Path, default=None,
                        help="write the table into this file between its marker lines")
    args = parser.parse_args(argv)
    if args.readme is None:
        print(settings_table())
        return
    args.readme.write_text(with_table(args.readme.read_text(), settings_table()))


if __name__ == "__main__":
    main()
