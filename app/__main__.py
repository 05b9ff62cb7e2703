"""``python -m app``: the ``volumesh`` command line (for when the console script is absent)."""

from app.cli import main

main()
