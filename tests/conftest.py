"""Suite-wide settings.

Property-based tests explore new random examples on every local run; CI (``CI`` set, as
``.ci/run`` does) replays a fixed sequence so that a merge is judged on the same cases each
time. Failures found locally become ``@example`` cases of their test.
"""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
