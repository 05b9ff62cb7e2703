"""The job store's models, defined in :mod:`workers.models` (workers write them too and must
not import ``app``); re-exported for the gateway."""

from workers.models import JOB_STATES, TERMINAL_STATES, ApiKey, Asset, Base, Capture, Job

__all__ = ["JOB_STATES", "TERMINAL_STATES", "ApiKey", "Asset", "Base", "Capture", "Job"]
