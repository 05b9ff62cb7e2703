"""Sampling pipelines that turn degraded depth into enhanced depth."""
