"""Imports every sub-command module so each registers itself on the Typer app."""

import app.cli.agent
import app.cli.calibrate
import app.cli.enhance
import app.cli.import_mkv
import app.cli.keys
import app.cli.reconstruct
import app.cli.serve
import app.cli.synth
import app.cli.train
import app.cli.worker  # noqa: F401
