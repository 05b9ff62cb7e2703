"""The remesh kernel, gpytoolbox's ``remesh_botsch``, and the child interpreter it runs in.

The kernel is native code that can crash the whole process on some inputs (cow.obj), so
`remesh` runs it in a child: a crash, an error or a timeout there leaves the caller running.
A child can be started ahead of its work (`KernelChild.start`), so that the interpreter's
start and the kernel's import are done while the caller works on what comes before the
remesh: the enhancement starts its children before it renders (`kernel_children`). Why
children, and in pieces: docs/decisions/remesh-kernel-children.md.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.geometry.order import in_spatial_order
from pipeline.geometry.repair import edge_table, faces_per_edge, triangle_angles_deg
from pipeline.reconstruct.remesh.boundary_split import split_boundary_edges

FloatArray = NDArray[np.float64]
Faces = NDArray[np.int32]


@dataclass(frozen=True)
class KernelResult:
    """The kernel's mesh, with the figures the caller judges it by, measured where it ran (in
    the kernel's children, side by side, rather than after them in the caller)."""

    vertices_m: FloatArray
    """(V, 3) the result's vertices, the held ones first."""
    faces: Faces
    """(F, 3) the result's faces."""
    held: NDArray[np.int64]
    """(H,) ascending, the input's vertices the kernel held (its boundary's): the result's
    first H vertices, in this order. Empty for the pieces `remesh.start_kernel` joins."""
    angles_deg: FloatArray
    """(F, 3) `triangle_angles_deg` of the result."""
    lost_m: float | None
    """How far the kernel's input vertex furthest from every vertex of the result lies from
    them, metres (`furthest_from_m`); None where it was not asked for."""
    source_ids: NDArray[np.int64] | None = None
    """(V, 3) the corners of the input face each result vertex lies on (`located_on`); None
    where it was not asked for."""
    source_weights: FloatArray | None = None
    """(V, 3) each result vertex's barycentric coordinates on that face."""


KernelOutcome = tuple[KernelResult | None, str | None]
"""The kernel's result, or None and why it failed."""


def kernel(vertices_m: FloatArray, faces: Faces, edge_m: float, iterations: int
           ) -> tuple[FloatArray, Faces, NDArray[np.int64]]:
    """gpytoolbox's ``remesh_botsch`` (boundary vertices held, projection on), called past its
    Python wrapper, whose input checks (row-wise sorts of every half-edge) take most of its
    time; the same checks here take a tenth as long. The wrapper's contract is kept: the held
    vertices (the boundary's, ascending; returned third) come first. A test holds the two
    equal."""
    from gpytoolbox_bindings import _remesh_botsch_cpp_impl

    v = np.asarray(vertices_m, np.float64)
    f = np.asarray(faces, np.int32)
    edges, opposite = edge_table(f)
    uses = faces_per_edge(opposite, len(edges))
    if (uses > 2).any():
        raise ValueError("Input mesh is non-manifold.")
    held = np.unique(edges[uses == 1])
    if len(held):
        order = np.concatenate([held, np.delete(np.arange(len(v)), held)])
        new_index = np.empty(len(v), dtype=np.int64)
        new_index[order] = np.arange(len(v))
        v, f = v[order], new_index[f].astype(np.int32)
    out_v, out_f = _remesh_botsch_cpp_impl(
        v, f, iterations, edge_m, np.arange(len(held), dtype=np.int32),
        np.zeros((0, 2), dtype=np.int32), True,
    )
    return (np.asarray(out_v, dtype=np.float64), np.asarray(out_f, dtype=np.int32),
            held.astype(np.int64))


def boundary_split_kernel(vertices_m: FloatArray, faces: Faces, edge_m: float,
                          iterations: int) -> tuple[FloatArray, Faces, NDArray[np.int64]]:
    """`kernel` on the mesh with its long boundary edges split first, which the kernel
    cannot do as it holds the boundary, in a spatial order (`in_spatial_order`): the
    whole mesh in one child; both steps are small beside the kernel."""
    v, f, _ = in_spatial_order(*split_boundary_edges(vertices_m, faces, edge_m))
    return kernel(v, f, edge_m, iterations)


def furthest_from_m(input_vertices_m: FloatArray, result_vertices_m: FloatArray) -> float:
    """How far the vertex of `input_vertices_m` furthest from every vertex of
    `result_vertices_m` lies from them, metres: libigl's AABB point-to-mesh distance with the
    result's vertices as one-point simplices. The kernel's module holds it already, where
    scipy's KD-tree (as fast) would cost each child a slow import of scipy.spatial, on cores
    the enhancement's stages are using."""
    from gpytoolbox_bindings import _point_mesh_squared_distance_cpp_impl

    if len(input_vertices_m) == 0:
        return 0.0
    if len(result_vertices_m) == 0:
        return float("inf")
    points = np.arange(len(result_vertices_m), dtype=np.int32)[:, None]
    squared_m2 = _point_mesh_squared_distance_cpp_impl(
        np.asarray(result_vertices_m, np.float64), points,
        np.asarray(input_vertices_m, np.float64))[0]
    return float(np.sqrt(squared_m2.max()))


def located_on(vertices_m: FloatArray, faces: Faces, points_m: FloatArray,
               held: NDArray[np.int64]) -> tuple[NDArray[np.int64], FloatArray]:
    """Each of (P, 3) `points_m` as a point of the mesh (`vertices_m`, `faces`): (P, 3) the
    corners of the face nearest it and (P, 3) the barycentric coordinates of its closest
    point there (libigl's AABB). The first H points are the mesh's vertices `held`, which
    come back as themselves, exactly."""
    from gpytoolbox_bindings import _point_mesh_squared_distance_cpp_impl

    _, face, closest_m = _point_mesh_squared_distance_cpp_impl(
        np.asarray(vertices_m, np.float64), np.asarray(faces, np.int32),
        np.asarray(points_m, np.float64))
    ids = faces[np.asarray(face).ravel()].astype(np.int64)
    a = vertices_m[ids[:, 0]]
    ab, ac, ap = vertices_m[ids[:, 1]] - a, vertices_m[ids[:, 2]] - a, closest_m - a
    d00, d01, d11 = (ab * ab).sum(1), (ab * ac).sum(1), (ac * ac).sum(1)
    d20, d21 = (ap * ab).sum(1), (ap * ac).sum(1)
    denom = d00 * d11 - d01 * d01
    safe = np.where(denom > 0, denom, 1.0)
    wb = np.where(denom > 0, (d11 * d20 - d01 * d21) / safe, 0.0)
    wc = np.where(denom > 0, (d00 * d21 - d01 * d20) / safe, 0.0)
    weights = np.clip(np.column_stack([1.0 - wb - wc, wb, wc]), 0.0, 1.0)
    weights /= weights.sum(axis=1, keepdims=True)
    ids[: len(held)] = held[:, None]
    weights[: len(held)] = (1.0, 0.0, 0.0)
    return ids, weights


def measured_kernel(vertices_m: FloatArray, faces: Faces, edge_m: float, iterations: int,
                    split: bool, measure_lost: bool, locate: bool = False) -> KernelResult:
    """`boundary_split_kernel` (where `split`) or `kernel`, with the result's angles and, where
    `measure_lost`, how far the input's vertices are from it (`furthest_from_m`), and where
    `locate` (not with `split`), where each of its vertices lies on the input (`located_on`)."""
    run = boundary_split_kernel if split else kernel
    out_v, out_f, held = run(vertices_m, faces, edge_m, iterations)
    lost_m = furthest_from_m(vertices_m, out_v) if measure_lost else None
    ids, weights = located_on(vertices_m, faces, out_v, held) if locate else (None, None)
    return KernelResult(out_v, out_f, held, triangle_angles_deg(out_v, out_f), lost_m, ids,
                        weights)


class KernelChild:
    """A child interpreter (``python -m pipeline.reconstruct.remesh.kernel``) that has imported
    the kernel and waits on its stdin for one request: the paths of a request folder and of the
    result folder it writes (`save_arrays`), on one line. Closing its stdin unasked lets it end with
    nothing done.

    A plain child process rather than multiprocessing: it never re-imports the caller's
    main module, so it works from any script, worker or test runner. The arrays go both ways
    as files: through pipes, a thread of the caller would have to move each 64 KB, waiting its
    turn for the interpreter lock while the caller works, and the children would wait on it.
    """

    def __init__(self) -> None:
        self.folder = Path(tempfile.mkdtemp(prefix="volumesh-remesh-"))
        # The folder holding this `pipeline`, so the child runs this very kernel.
        package_root = str(Path(__file__).resolve().parents[3])
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH"))
                                            if p)
        # Nothing in the child multiplies matrices: without a BLAS thread pool numpy's import
        # takes half the CPU time, taken from the caller's stages while the child starts.
        env |= {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        with open(self.folder / "stderr.txt", "wb") as stderr:
            self.process = subprocess.Popen(
                [sys.executable, "-P", "-m", "pipeline.reconstruct.remesh.kernel"],
                stdin=subprocess.PIPE,
                stdout=subprocess.DEVNULL, stderr=stderr, env=env)

    def submit(self, vertices_m: FloatArray, faces: Faces, edge_m: float, iterations: int,
               timeout_s: float, split: bool, measure_lost: bool = False, locate: bool = False
               ) -> Callable[[], KernelOutcome]:
        """Hands the child its request (`measured_kernel`'s arguments) and returns a call that
        waits for the outcome."""
        request, result = self.folder / "request", self.folder / "result"
        save_arrays(request, vertices_m=np.asarray(vertices_m, np.float64),
                    faces=np.asarray(faces, np.int32), edge_m=np.float64(edge_m),
                    iterations=np.int64(iterations), split=np.bool_(split),
                    measure_lost=np.bool_(measure_lost), locate=np.bool_(locate))
        assert self.process.stdin is not None
        try:
            self.process.stdin.write(f"{request}\t{result}\n".encode())
            self.process.stdin.close()
        except BrokenPipeError:
            pass  # it ended before its request; the outcome says how
        deadline = time.monotonic() + timeout_s
        # A thread in a blocking waitpid wakes the moment the child ends; Popen.wait(timeout)
        # would poll, up to 50 ms late.
        waiter = threading.Thread(target=self.process.wait, daemon=True)
        waiter.start()

        def wait() -> KernelOutcome:
            waiter.join(max(0.0, deadline - time.monotonic()))
            try:
                if waiter.is_alive():
                    self.process.kill()
                    waiter.join()
                    return None, f"remesh kernel timed out after {timeout_s:g} s"
                return _read_outcome(self.process.returncode, result,
                                     self.folder / "stderr.txt")
            finally:
                shutil.rmtree(self.folder, ignore_errors=True)

        return wait

    def close(self) -> None:
        """Ends a child that was given no request."""
        if self.process.stdin is not None and not self.process.stdin.closed:
            self.process.stdin.close()
        try:
            self.process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        shutil.rmtree(self.folder, ignore_errors=True)


@contextmanager
def kernel_children(count: int) -> Iterator[list[KernelChild]]:
    """`count` children started now, for a `remesh` to come (its `children`); those it did
    not use are ended on leaving."""
    children = [KernelChild() for _ in range(count)]
    try:
        yield children
    finally:
        for child in children:
            child.close()


def start_isolated(vertices_m: FloatArray, faces: Faces, edge_m: float, iterations: int,
                   timeout_s: float, split: bool = True, child: KernelChild | None = None,
                   measure_lost: bool = False, locate: bool = False
                   ) -> Callable[[], KernelOutcome]:
    """Starts `measured_kernel` (the boundary split first where `split`) in `child` (a started
    `KernelChild`; None: one started now) and returns a call that waits for it: (result,
    None), or (None, why it failed). The caller may work meanwhile."""
    return (child or KernelChild()).submit(vertices_m, faces, edge_m, iterations, timeout_s,
                                           split, measure_lost, locate)


def run_isolated(vertices_m: FloatArray, faces: Faces, edge_m: float, iterations: int,
                 timeout_s: float) -> KernelOutcome:
    """The kernel in a child interpreter (`start_isolated`), waited for."""
    return start_isolated(vertices_m, faces, edge_m, iterations, timeout_s)()


def save_arrays(folder: Path, **arrays: NDArray[Any] | np.generic) -> None:
    """`arrays` as one .npy file each in `folder`, made here: how requests and results pass
    between the caller and a child. Plain .npy rather than an .npz, which zips them and checks
    a CRC of every byte it reads, on the path of the speculative remesh's finish."""
    folder.mkdir()
    for name, array in arrays.items():
        np.save(folder / f"{name}.npy", array)


def load_arrays(folder: Path) -> dict[str, NDArray[Any]]:
    """The arrays `save_arrays` wrote to `folder`, by name."""
    return {path.stem: np.load(path, allow_pickle=False) for path in folder.glob("*.npy")}


def _read_outcome(returncode: int, result: Path, stderr: Path) -> KernelOutcome:
    if returncode < 0:
        return None, f"remesh kernel crashed (signal {-returncode})"
    if returncode != 0:
        lines = stderr.read_text(errors="replace").strip().splitlines()
        return None, f"remesh kernel failed: {lines[-1] if lines else returncode}"
    try:
        data = load_arrays(result)
        lost_m = float(data["lost_m"])
        located = len(data["source_ids"]) > 0
        return KernelResult(np.asarray(data["vertices_m"], np.float64),
                            np.asarray(data["faces"], np.int32),
                            np.asarray(data["held"], np.int64),
                            np.asarray(data["angles_deg"], np.float64),
                            None if np.isnan(lost_m) else lost_m,
                            np.asarray(data["source_ids"], np.int64) if located else None,
                            np.asarray(data["source_weights"]) if located else None), None
    except (ValueError, OSError, KeyError) as exc:
        return None, f"remesh kernel returned no mesh ({exc})"


def _child_main() -> None:
    """Child process body: the kernel imported first, then one request from stdin (nothing
    on stdin: exit with nothing done); any failure exits non-zero."""
    import gpytoolbox_bindings  # noqa: F401  (imported while the caller still works)

    line = sys.stdin.readline().strip()
    if not line:
        return
    request_path, result_path = line.split("\t")
    data = load_arrays(Path(request_path))
    out = measured_kernel(data["vertices_m"], data["faces"], float(data["edge_m"]),
                          int(data["iterations"]), bool(data["split"]),
                          bool(data["measure_lost"]), bool(data["locate"]))
    unlocated = np.zeros((0, 3))
    save_arrays(Path(result_path), vertices_m=out.vertices_m, faces=out.faces, held=out.held,
                angles_deg=out.angles_deg,
                lost_m=np.float64(np.nan if out.lost_m is None else out.lost_m),
                source_ids=unlocated if out.source_ids is None else out.source_ids,
                source_weights=unlocated if out.source_weights is None else out.source_weights)


if __name__ == "__main__":
    _child_main()
