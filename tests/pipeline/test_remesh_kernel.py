"""The kernel's children started ahead of their work (`remesh_kernel.kernel_children`): the
same remesh as children started on demand, and nothing left behind."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.remesh import RemeshConfig, remesh
from pipeline.remesh_kernel import KernelChild, kernel_children
from tests.pipeline.test_remesh import _bumpy_sphere

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
