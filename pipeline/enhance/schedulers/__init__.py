"""Noise schedules and samplers (maths only)."""
