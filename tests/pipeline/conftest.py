"""Fixtures of the pipeline's tests: a unit sphere, clean and noisy."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.geometry.mesh import TriangleMesh
from tests.pipeline.meshes import sphere


@pytest.fixture
def unit_sphere() -> TriangleMesh:
    return sphere()


@pytest.fixture
def noisy_sphere(unit_sphere: TriangleMesh) -> tuple[TriangleMesh, TriangleMesh]:
    """(clean, noisy): vertices moved along normals by uniform noise in ±1 cm, seeded."""
    from pipeline.enhance.training.data import noisy_along_normals

    return unit_sphere, noisy_along_normals(unit_sphere, 0.01, np.random.default_rng(0))
