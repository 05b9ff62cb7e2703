"""Suite-wide settings.

Property-based tests explore new random examples on every local run; CI (``CI`` set, as
``.ci/run`` does) replays a fixed sequence so that a merge is judged on the same cases each
time, with no per-example deadline (a slow CI machine is not a failure). Failures found
locally become ``@example`` cases of their test.
"""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, deadline=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
