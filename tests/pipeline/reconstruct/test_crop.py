from __future__ import annotations

import numpy as np

from pipeline.reconstruct.crop import CropConfig, crop_mask, find_floor, rig_axis, rig_cylinder_mask
from tests.pipeline.sphere_scene import look_at

TARGET = np.array([0.3, 1.0, -0.2])
RING = [look_at(TARGET + [2 * np.sin(a), 0.5, 2 * np.cos(a)], TARGET)
        for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]


def _subject(rng: np.random.Generator, count: int = 60_000) -> tuple[np.ndarray, np.ndarray]:
    """A ball standing on y = 0 (one point per ~4.3 mm), normals pointing out of it."""
    normals = rng.normal(size=(count, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = TARGET - [0.0, 0.7, 0.0] + 0.3 * normals  # bottom on y = 0
    return points, normals.astype(np.float32)


def _floor(rng: np.random.Generator, count: int = 60_000) -> tuple[np.ndarray, np.ndarray]:
    xz = rng.uniform(-3, 3, size=(count, 2)) + TARGET[[0, 2]]
    points = np.column_stack([xz[:, 0], rng.normal(0, 0.002, count), xz[:, 1]])
    return points, np.tile([0.0, 1.0, 0.0], (count, 1)).astype(np.float32)


def test_the_floor_and_the_studio_are_cut_away() -> None:
    rng = np.random.default_rng(0)
    body, body_n = _subject(rng)
    floor, floor_n = _floor(rng)
    points, normals = np.vstack([body, floor]), np.vstack([body_n, floor_n])
    keep, floor_y = crop_mask(points, normals, RING, 0.004, CropConfig())
    assert floor_y is not None and abs(floor_y) < 0.01
    assert not keep[len(body):].any()
    # The subject keeps all but its lowest centimetre or so.
    assert keep[:len(body)].mean() > 0.95
    assert np.all(body[keep[:len(body)]][:, 1] > floor_y + 0.01)


def test_stray_points_are_dropped_and_sparse_clouds_kept() -> None:
    rng = np.random.default_rng(2)
    body, normals = _subject(rng)
    strays = rng.uniform(-1, 1, size=(200, 3)) + TARGET
    points = np.vstack([body, strays])
    both = np.vstack([normals, np.zeros((200, 3), np.float32)])
    keep, _ = crop_mask(points, both, RING, 0.004, CropConfig(remove_floor=False))
    assert keep[:len(body)].mean() > 0.97 and keep[len(body):].mean() < 0.05
    # A sparse capture (large pixel footprint) keeps its points.
    sparse = body[::50]
    keep, _ = crop_mask(sparse, normals[::50], RING, 0.03, CropConfig(remove_floor=False))
    assert keep.mean() > 0.95


def test_no_floor_is_invented() -> None:
    rng = np.random.default_rng(1)
    body, normals = _subject(rng)
    assert find_floor(body, normals, CropConfig()) is None
    # A table top has legs below it: not a floor.
    top = np.column_stack([rng.uniform(-0.5, 0.5, 3000), np.full(3000, 0.8),
                           rng.uniform(-0.5, 0.5, 3000)])
    legs = np.column_stack([rng.uniform(-0.5, 0.5, 3000), rng.uniform(0, 0.79, 3000),
                            rng.uniform(-0.5, 0.5, 3000)])
    up = np.tile([0.0, 1.0, 0.0], (3000, 1)).astype(np.float32)
    side = np.tile([1.0, 0.0, 0.0], (3000, 1)).astype(np.float32)
    assert find_floor(np.vstack([top, legs]), np.vstack([up, side]), CropConfig()) is None


def test_points_outside_the_ring_are_dropped() -> None:
    found = rig_axis(RING)
    assert found is not None
    np.testing.assert_allclose(found[0], TARGET[[0, 2]], atol=1e-9)
    assert abs(found[1] - 2.0) < 1e-9
    points = TARGET + np.array([[0.0, 0, 0], [1.0, 0, 1], [2.5, 0, 0], [0, 8, -3.0]])
    assert rig_cylinder_mask(points, RING, 0.95).tolist() == [True, True, False, False]
    keep, _ = crop_mask(points, np.zeros((4, 3), np.float32), RING, 0.004,
                        CropConfig(enabled=False))
    assert keep.all()


def test_cameras_on_one_side_crop_nothing() -> None:
    arc = [look_at(TARGET + [2 * np.sin(a), 0.5, 2 * np.cos(a)], TARGET)
           for a in (-0.6, 0.0, 0.6)]
    assert rig_axis(arc) is None
    assert rig_axis(RING[:2]) is None
    points = TARGET + np.array([[0.0, 0, 0], [9.0, 0, 0]])
    assert rig_cylinder_mask(points, arc, 0.95).all()
