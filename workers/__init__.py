"""Celery workers and the service infrastructure they share with the gateway.

The gateway (``app``) sits above this package and may import it; this package never imports
``app``. That is why settings, the job store and storage live here: both sides need them.
"""
