import numpy as np
import scipy.sparse as sp
import torch
from hypothesis import given
from hypothesis import strategies as st

from pipeline.enhance.models.vertex_gain import VertexGainConfig, VertexGainNet
from pipeline.enhance.update.steps import ViewSteps
from pipeline.enhance.update.vertex_gain import GAIN_FEATURES, MEAN_STEP, gain_features

AXES = np.array([[0, 0, -1], [0, 0, 1], [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0]], float)


def _steps(steps_m, weights, normals) -> ViewSteps:
    return ViewSteps(np.asarray(steps_m, float), np.asarray(weights, float), AXES[:len(steps_m)],
                     np.asarray(normals, float), cap_m=1.0, mean_op=_no_neighbours(len(normals)))


def _no_neighbours(vertices: int) -> sp.csr_matrix:
    return sp.identity(vertices, format="csr")


def test_features_of_agreeing_and_disagreeing_views():
    """Two views seeing a vertex whose normal is +z: the front view (forward -z) steps -s
    along its axis, i.e. +s along the normal; agreement gives no spread."""
    normals = [[0, 0, 1], [0, 0, 1], [0, 0, 1]]
    steps = _steps([[-0.02, -0.02, 0.0], [0.02, -0.02, 0.0]],
                   [[1.0, 1.0, 0.0], [1.0, 1.0, 0.0]], normals)
    f = gain_features(steps, edge_m=0.01)
    assert f.shape == (3, GAIN_FEATURES)
    # vertex 0: the views agree in space (+2 edges along the normal for view 0, view 1 looks
    # from behind along +z, so its +0.02 step is also +2 edges along the normal)
    assert np.allclose(f[0], [2.0, 0.0, 1.0, 1.0])
    # vertex 1: they disagree: mean 0, spread 2 edges
    assert np.allclose(f[1], [0.0, 2.0, 1.0, 1.0])
    # vertex 2: unseen
    assert np.allclose(f[2], 0.0)


def _random_views(seed: int, views: int, vertices: int):
    """(steps_m, weights, normals): random steps of about 1 cm, about 70 % of pairs seen."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(vertices, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    steps_m = rng.normal(size=(views, vertices)) * 0.01
    weights = rng.uniform(size=(views, vertices)) * (rng.uniform(size=(views, vertices)) > 0.3)
    return steps_m, weights, normals


@given(st.floats(0.01, 100.0), st.integers(0, 2**31 - 1))
def test_features_do_not_depend_on_the_mesh_scale(scale, seed):
    steps_m, weights, normals = _random_views(seed, 6, 20)
    small = gain_features(_steps(steps_m, weights, normals), 0.005)
    large = gain_features(_steps(steps_m * scale, weights, normals), 0.005 * scale)
    assert np.allclose(small, large, rtol=1e-4, atol=1e-5)
    assert np.all(small[:, 1] >= 0) and np.all(small[:, 3] <= 1)


def test_gains_lie_between_zero_and_the_cap():
    model = VertexGainNet(VertexGainConfig(hidden=8, max_gain=2.0))
    features = torch.randn(100, GAIN_FEATURES) * 50
    gain = model(features)
    assert gain.shape == (100,)
    assert torch.all(gain > 0) and torch.all(gain < 2.0)
    assert MEAN_STEP == 0


@given(st.integers(0, 2**31 - 1), st.integers(2, 4))
def test_features_read_alike_with_every_view_repeated(seed, copies):
    """Twice the views, each seen as before, give the same features: they are per view."""
    steps_m, weights, normals = _random_views(seed, 3, 10)
    once = gain_features(_steps(steps_m, weights, normals), 0.005)
    many = ViewSteps(np.tile(steps_m, (copies, 1)), np.tile(weights, (copies, 1)),
                     np.tile(AXES[:3], (copies, 1)), normals, cap_m=1.0,
                     mean_op=_no_neighbours(len(normals)))
    assert np.allclose(gain_features(many, 0.005), once, atol=1e-5)
