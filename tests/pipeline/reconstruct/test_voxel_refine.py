from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.reconstruct.voxel_refine import VoxelRefineConfig, choose_cameras, refine_mask

SIZE = 0.01


def _cloud(seed: int, count: int, cameras: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.025, 0.025, size=(count, 3))
    index = rng.integers(0, cameras, size=count)
    centres = rng.normal(size=(cameras, 3)) * 2.0
    return points, index, centres


def _reference(points: np.ndarray, index: np.ndarray, centres: np.ndarray,
               layer_axis: int) -> dict[tuple[int, ...], int]:
    """Loop-by-loop statement of docs/architecture.md, step 7 (one majority pass)."""
    voxels: dict[tuple[int, ...], set[int]] = {}
    for p, c in zip(points, index, strict=True):
        voxels.setdefault(tuple(np.floor(p / SIZE).astype(int)), set()).add(int(c))
    nearest = {}
    for v, cams in voxels.items():
        centre = (np.array(v) + 0.5) * SIZE
        nearest[v] = min(cams, key=lambda c: (np.sum((centre - centres[c]) ** 2), c))
    axes = [a for a in range(3) if a != layer_axis]
    result = {}
    for v, cams in voxels.items():
        votes: Counter[int] = Counter()
        for du in (-1, 0, 1):
            for dv in (-1, 0, 1):
                if du == dv == 0:
                    continue
                n = list(v)
                n[axes[0]] += du
                n[axes[1]] += dv
                if tuple(n) in nearest and nearest[tuple(n)] in cams:
                    votes[nearest[tuple(n)]] += 1
        best = max(votes.values(), default=0)
        own = votes.get(nearest[v], 0)
        if best == 0 or own >= best:
            result[v] = nearest[v]
        else:
            result[v] = min(c for c, n in votes.items() if n == best)
    return result


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), count=st.integers(1, 400), cameras=st.integers(1, 5),
       layer_axis=st.sampled_from([0, 1, 2]))
def test_choice_matches_the_loop_statement_and_keeps_one_camera_per_voxel(
        seed: int, count: int, cameras: int, layer_axis: int) -> None:
    points, index, centres = _cloud(seed, count, cameras)
    config = VoxelRefineConfig(voxel_size_m=SIZE, layer_axis=layer_axis)
    choice = choose_cameras(points, index, centres, config)
    expected = _reference(points, index, centres, layer_axis)
    got = {tuple(c): int(cam) for c, cam in zip(choice.coords, choice.camera, strict=True)}
    assert got == expected
    keep = refine_mask(points, index, centres, config)
    # Exactly one camera per voxel among the kept points, and every voxel keeps some.
    kept_per_voxel: dict[tuple[int, ...], set[int]] = {}
    for p, c in zip(points[keep], index[keep], strict=True):
        kept_per_voxel.setdefault(tuple(np.floor(p / SIZE).astype(int)), set()).add(int(c))
    assert set(kept_per_voxel) == set(expected)
    assert all(len(cams) == 1 for cams in kept_per_voxel.values())


def test_majority_makes_a_camera_continuous_across_a_layer() -> None:
    # A 7x7 sheet of voxels in one z layer; camera 0 is nearest everywhere except one
    # voxel in the middle, where camera 1 is nearer but camera 0 has points too.
    grid = np.stack(np.meshgrid(np.arange(7), np.arange(7), indexing="ij"), -1).reshape(-1, 2)
    centres = (grid + 0.5) * SIZE
    points = np.column_stack([centres, np.full(len(centres), 0.5 * SIZE)])
    index = np.zeros(len(points), dtype=np.int64)
    middle = np.array([[3.5 * SIZE, 3.5 * SIZE, 0.5 * SIZE]])
    points = np.vstack([points, middle])
    index = np.append(index, 1)
    cams = np.array([[0.035, 0.035, 5.0], [0.035, 0.035, 0.5 * SIZE + 1e-3]])
    config = VoxelRefineConfig(voxel_size_m=SIZE)
    nearest_only = choose_cameras(points, index, cams,
                                  VoxelRefineConfig(voxel_size_m=SIZE, majority_passes=0))
    assert sorted(Counter(nearest_only.camera.tolist()).items()) == [(0, 48), (1, 1)]
    smoothed = choose_cameras(points, index, cams, config)
    assert np.all(smoothed.camera == 0)
    keep = refine_mask(points, index, cams, config)
    assert np.all(index[keep] == 0)


def test_empty_and_bad_inputs() -> None:
    config = VoxelRefineConfig()
    assert refine_mask(np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((2, 3)),
                       config).shape == (0,)
    with pytest.raises(ValueError, match="camera_index"):
        refine_mask(np.zeros((3, 3)), np.array([0, 1, 5]), np.zeros((2, 3)), config)
    with pytest.raises(ValueError, match="points_world"):
        refine_mask(np.zeros((3, 2)), np.zeros(3, np.int64), np.zeros((2, 3)), config)
    with pytest.raises(ValueError):
        VoxelRefineConfig(layer_axis=3)
