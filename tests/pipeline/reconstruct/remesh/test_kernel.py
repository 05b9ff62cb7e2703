"""The kernel's children started ahead of their work (`kernel.kernel_children`): the
same remesh as children started on demand, and nothing left behind."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.geometry.mesh import mean_edge_length_m
from pipeline.geometry.repair import triangle_angles_deg
from pipeline.reconstruct.remesh.isotropic import RemeshConfig, remesh, start_kernel
from pipeline.reconstruct.remesh.kernel import (
    KernelChild,
    _read_outcome,
    furthest_from_m,
    kernel_children,
    load_arrays,
    run_isolated,
    save_arrays,
)
from tests.pipeline.reconstruct.remesh.test_isotropic import _bumpy_sphere
from tests.pipeline.reconstruct.remesh.test_pieces import _noisy_sphere

CONFIG = RemeshConfig(target_edge_length_m=0.03, iterations=2, kernel_processes=2)


@pytest.mark.parametrize("started", [2, 1], ids=["all", "fewer than the pieces"])
def test_children_started_ahead_give_the_same_remesh(started: int) -> None:
    """Two pieces: their children all started ahead, or one, the other started on demand."""
    source = _bumpy_sphere()
    on_demand, _ = remesh(source, CONFIG)
    with kernel_children(started) as children:
        ahead, stats = remesh(source, CONFIG, children)
    assert stats["warning"] is None
    np.testing.assert_array_equal(ahead.faces, on_demand.faces)
    np.testing.assert_array_equal(ahead.vertices_m, on_demand.vertices_m)
    assert all(c.process.returncode == 0 and not c.folder.exists() for c in children)


def test_unused_children_end_cleanly() -> None:
    with kernel_children(3) as children:
        pass
    assert [c.process.returncode for c in children] == [0, 0, 0]
    assert not any(c.folder.exists() for c in children)


def test_a_child_killed_before_its_work_keeps_the_input_and_warns() -> None:
    source = _bumpy_sphere()
    child = KernelChild()
    child.process.kill()
    child.process.wait()
    out, stats = remesh(source, RemeshConfig(target_edge_length_m=0.03, iterations=2,
                                             kernel_processes=1), [child])
    child.close()
    assert "crashed" in stats["warning"] and "kept the unremeshed mesh" in stats["warning"]
    assert out.face_count > 0.9 * source.face_count


def test_a_child_runs_this_kernel_whatever_the_working_folder(tmp_path, monkeypatch) -> None:
    """`python -m` puts the working folder first on the path, and PYTHONPATH comes before the
    installed packages: a folder holding another `pipeline` package (a worktree, a checkout of
    another version) must not be run from either."""
    decoy = tmp_path / "pipeline" / "reconstruct" / "remesh"
    decoy.mkdir(parents=True)
    for folder in (decoy, decoy.parent, decoy.parent.parent):
        (folder / "__init__.py").write_text("")
    (decoy / "kernel.py").write_text("raise SystemExit(3)\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    source = _bumpy_sphere()
    result, why = run_isolated(source.vertices_m, source.faces, 0.03, 1, 60.0)
    assert why is None and result is not None and len(result.faces) > 0


@pytest.mark.parametrize("pieces", [1, 3])
def test_the_figures_measured_in_the_children_are_the_joined_meshes(pieces: int) -> None:
    """The angles come with the faces they belong to; the furthest input vertex is measured
    against each piece's own result, so it is at least the whole's and at most an edge
    more."""
    mesh = _noisy_sphere(2, open_cap=True)
    edge_m = mean_edge_length_m(mesh)
    config = RemeshConfig(target_edge_length_m=edge_m, iterations=1, kernel_processes=pieces)
    result, why = start_kernel(mesh.vertices_m, mesh.faces, config, measure_lost=True)()
    assert why is None and result is not None
    np.testing.assert_array_equal(result.angles_deg,
                                  triangle_angles_deg(result.vertices_m, result.faces))
    whole_m = furthest_from_m(mesh.vertices_m, result.vertices_m)
    assert result.lost_m is not None and whole_m <= result.lost_m <= whole_m + edge_m
    if pieces == 1:
        assert result.lost_m == whole_m
    unmeasured, _ = start_kernel(mesh.vertices_m, mesh.faces, config)()
    assert unmeasured is not None and unmeasured.lost_m is None


def test_arrays_pass_through_a_folder_as_they_were(tmp_path) -> None:
    arrays = {"vertices_m": np.random.default_rng(0).random((5, 3)),
              "faces": np.arange(6, dtype=np.int32).reshape(2, 3),
              "edge_m": np.float64(0.005), "split": np.bool_(True)}
    save_arrays(tmp_path / "request", **arrays)
    loaded = load_arrays(tmp_path / "request")
    assert loaded.keys() == arrays.keys()
    for name, array in arrays.items():
        assert loaded[name].dtype == array.dtype
        np.testing.assert_array_equal(loaded[name], array)


def test_a_result_missing_an_array_is_no_mesh(tmp_path) -> None:
    save_arrays(tmp_path / "result", vertices_m=np.zeros((3, 3)))
    result, why = _read_outcome(0, tmp_path / "result", tmp_path / "stderr.txt")
    assert result is None and why is not None and "returned no mesh" in why
