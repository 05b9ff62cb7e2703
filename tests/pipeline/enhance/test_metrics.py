import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enhance.metrics import (
    c2m_summary,
    correction_calibration,
    depth_edge_band,
    normal_error_deg,
    signed_c2m,
)
from tests.pipeline.meshes import sphere


@settings(max_examples=10, deadline=None)
@given(st.floats(-0.02, 0.02))
def test_offset_along_normals_gives_signed_distance(offset_m):
    """Points pushed out (in) along face normals by d are +d (-d) away: the C2M sign."""
    truth = sphere(0.5, 16)
    from pipeline.geometry.mesh import face_normals

    tri = truth.vertices_m[truth.faces]
    centroids = tri.mean(axis=1)
    points = centroids + face_normals(truth.vertices_m, truth.faces) * offset_m
    d = signed_c2m(points, truth)
    assert np.allclose(d, offset_m, atol=1e-6)


def test_identical_meshes_score_zero():
    m = sphere(0.5, 16)
    s = c2m_summary(m, m)
    assert s["c2m_rms_mm"] < 1e-3 and s["reverse_rms_mm"] < 1e-3
    assert normal_error_deg(m, m) < 10.0  # vertex vs face normals on a coarse sphere


def test_edge_band_follows_depth_jumps():
    depth = np.full((32, 32), 0.5, np.float32)
    depth[:, 16:] = 0.8
    valid = np.ones_like(depth, bool)
    band = depth_edge_band(depth, valid, jump=0.1, width_px=3)
    assert band[:, 12:19].all()  # the jump sits between columns 15 and 16
    assert not band[:, :12].any() and not band[:, 19:].any()


@pytest.mark.parametrize("scale", [1.01, 0.99])
def test_scaled_sphere_has_signed_mean_of_the_gap(scale):
    truth = sphere(0.5, 32)
    result = truth.with_vertices(truth.vertices_m * scale)
    s = c2m_summary(result, truth)
    # Vertices lie on the ideal sphere, slightly outside the flat faces: the gap plus a bit.
    assert s["c2m_mean_mm"] == pytest.approx((scale - 1) * 500, abs=0.8)


@settings(max_examples=20, deadline=None)
@given(st.floats(0.25, 4.0), st.floats(-0.01, 0.01))
def test_calibration_reads_a_scaled_and_shifted_correction(scale, shift):
    """A prediction that moves k times the true correction has gain 1/k and correlation 1;
    a constant added to it shows as its bias, in thousandths."""
    rng = np.random.default_rng(0)
    base = rng.uniform(0.4, 0.6, (2, 16, 16))
    clean = base + rng.normal(0.0, 0.003, base.shape)
    mask = np.ones(base.shape, dtype=bool)
    mask[:, :2] = False
    scaled = correction_calibration(base + scale * (clean - base), base, clean, mask)
    assert scaled["gain"] == pytest.approx(1.0 / scale, rel=1e-6)
    assert scaled["correlation"] == pytest.approx(1.0, abs=1e-9)
    shifted = correction_calibration(clean + shift, base, clean, mask)
    assert shifted["bias_permille"] == pytest.approx(1e3 * shift, abs=1e-9)
