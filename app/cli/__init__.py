"""The `volumesh` command line.

Each sub-command lives in its own module and imports heavy libraries inside its body, so
`volumesh --help` stays fast. Commands report bad input as one readable line and exit 2.
"""

from __future__ import annotations

import sys

import typer

app = typer.Typer(
    name="volumesh",
    help="Multi-camera RGB-D captures to clean, compressed meshes.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

# Sub-command modules register themselves on `app` when imported.
from app.cli import commands  # noqa: E402, F401


def main() -> None:
    """Entry point: run the CLI, turning input errors into one line on stderr."""
    try:
        app(standalone_mode=True)
    except ValueError as exc:  # raised by pipeline for bad input
        print(f"volumesh: error: {exc}", file=sys.stderr)
        sys.exit(2)
