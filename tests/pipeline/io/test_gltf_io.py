"""GLB export: Draco round trips, the Khronos validator, file structure, LOD and dispatch."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path
from typing import Any

import DracoPy
import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pipeline.geometry.mesh import TriangleMesh, vertex_normals
from pipeline.io.glb_format import DRACO_EXTENSION
from pipeline.io.gltf_io import DracoConfig, encode_glb, simplify, write_glb, write_mesh
from pipeline.io.gltf_read import decode_glb
from pipeline.io.mesh_io import read_mesh

REPO = Path(__file__).resolve().parents[3]
VALIDATOR = REPO / "tests" / "js" / "validate_gltf.mjs"
BUNNY = REPO.parent / "shared" / "data" / "meshes" / "stanford-bunny.obj"


def sphere(subdivisions: int = 3, radius: float = 0.3, noise: float = 0.0, seed: int = 0,
           colored: bool = True) -> TriangleMesh:
    """An icosphere, optionally with radial noise, coloured by position."""
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    rng = np.random.default_rng(seed)
    unit = np.asarray(ico.vertices)
    radii = radius * (1.0 + noise * rng.uniform(-1.0, 1.0, len(unit)))
    vertices = unit * radii[:, None]
    colors = np.clip(np.rint(127.5 + 120.0 * unit), 0, 255).astype(np.uint8) if colored else None
    return TriangleMesh(vertices, np.asarray(ico.faces, dtype=np.int32), colors)


def position_bound(vertices: np.ndarray, bits: int) -> float:
    """Draco's largest position error: half a quantisation step over the bounding cube's side,
    plus float32 rounding, since Draco converts the input, origin and step to float32 and
    dequantises in float32 (a few ulps of the coordinates and of the side)."""
    side = float(np.ptp(vertices, axis=0).max())
    return 0.5 * side / (2**bits - 1) + 2.0**-22 * (float(np.abs(vertices).max()) + side)


def glb_json(data: bytes) -> dict[str, Any]:
    length, kind = struct.unpack_from("<II", data, 12)
    assert kind == 0x4E4F534A
    return json.loads(data[20:20 + length])


def validate(tmp_path: Path, data: bytes) -> dict[str, Any]:
    """The Khronos glTF-Validator's report on `data` (via tests/js/validate_gltf.mjs)."""
    if not (REPO / "node_modules" / "gltf-validator").is_dir():
        pytest.skip("node_modules/gltf-validator missing: run `npm ci` (the Makefile does)")
    node = shutil.which("node")
    assert node is not None, "node_modules is installed but node is not on PATH"
    path = tmp_path / "mesh.glb"
    path.write_bytes(data)
    done = subprocess.run([node, str(VALIDATOR), str(path)], cwd=REPO, capture_output=True,
                          text=True, timeout=60, check=False)
    assert done.returncode in (0, 1), done.stderr
    return json.loads(done.stdout)


def assert_same_geometry(original: TriangleMesh, decoded: TriangleMesh, bits: int) -> np.ndarray:
    """Checks positions within Draco's bound both ways; returns decoded -> original index."""
    bound = position_bound(original.vertices_m, bits)
    distance, index = cKDTree(original.vertices_m).query(decoded.vertices_m)
    assert distance.max() <= bound * np.sqrt(3)
    assert np.abs(decoded.vertices_m - original.vertices_m[index]).max() <= bound
    used = np.unique(original.faces)
    back, _ = cKDTree(decoded.vertices_m).query(original.vertices_m[used])
    assert back.max() <= bound * np.sqrt(3)
    return index


def canonical_faces(faces: np.ndarray) -> set[tuple[int, ...]]:
    """Faces as a set, each rotated to start at its smallest index (orientation kept)."""
    rolled = [np.roll(f, -int(np.argmin(f))) for f in faces]
    return {tuple(int(i) for i in f) for f in rolled}


# --- round trips -----------------------------------------------------------------------------


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    scale=st.floats(1e-3, 1e2),
    offset=st.tuples(*[st.floats(-50.0, 50.0)] * 3),
    rotation_seed=st.integers(0, 2**31),
    noise=st.floats(0.0, 0.2),
    bits=st.integers(8, 18),
)
def test_draco_round_trip_keeps_sphere_within_quantisation(
    scale: float, offset: tuple[float, float, float], rotation_seed: int, noise: float, bits: int
) -> None:
    base = sphere(subdivisions=2, radius=1.0, noise=noise, seed=rotation_seed)
    rotation = Rotation.random(random_state=rotation_seed).as_matrix()
    mesh = TriangleMesh(base.vertices_m @ rotation.T * scale + np.array(offset), base.faces,
                        base.vertex_colors)
    decoded = decode_glb(encode_glb(mesh, draco=DracoConfig(position_quantization_bits=bits)))
    index = assert_same_geometry(mesh, decoded, bits)
    assert canonical_faces(index[decoded.faces]) == canonical_faces(mesh.faces)
    assert decoded.vertex_colors is not None and mesh.vertex_colors is not None
    np.testing.assert_array_equal(decoded.vertex_colors, mesh.vertex_colors[index])
    expected = vertex_normals(mesh.vertices_m, mesh.faces)[index]
    assert decoded.vertex_normals is not None
    cosine = np.sum(decoded.vertex_normals * expected, axis=1)
    assert cosine.min() >= np.cos(np.radians(0.5))  # 10-bit octahedral normals


@settings(max_examples=30, deadline=None)
@given(data=st.data(), vertex_count=st.integers(3, 60), face_count=st.integers(1, 80))
def test_draco_round_trip_of_arbitrary_triangle_soups(
    data: st.DataObject, vertex_count: int, face_count: int
) -> None:
    vertices = np.array(data.draw(st.lists(
        st.tuples(*[st.floats(-10.0, 10.0, allow_subnormal=False)] * 3),
        min_size=vertex_count, max_size=vertex_count)))
    faces = np.array(data.draw(st.lists(
        st.lists(st.integers(0, vertex_count - 1), min_size=3, max_size=3, unique=True),
        min_size=face_count, max_size=face_count)), dtype=np.int32)
    mesh = TriangleMesh(vertices, faces)
    try:
        glb = encode_glb(mesh, draco=DracoConfig(position_quantization_bits=12))
    except ValueError as exc:
        # Only allowed when every triangle collapses at 12-bit positions.
        assert "degenerate" in str(exc)
        snap = 2.0 * position_bound(vertices, 12) + 1e-12
        corners = vertices[faces]
        shortest = np.min([np.linalg.norm(corners[:, a] - corners[:, b], axis=1)
                           for a, b in ((0, 1), (1, 2), (2, 0))], axis=0)
        assert np.all(shortest <= snap)
        return
    decoded = decode_glb(glb)
    assert decoded.vertex_colors is None
    assert np.all(decoded.faces < decoded.vertex_count)
    if np.ptp(vertices, axis=0).max() > 0:
        # Triangles whose corners meet at 12-bit positions are dropped, and with them corners
        # no other triangle uses. Corners further apart than a step in some coordinate cannot
        # meet: those triangles' corners must come back.
        step = 2.0 * position_bound(vertices, 12)
        corners = vertices[faces]
        apart = np.min([np.abs(corners[:, a] - corners[:, b]).max(axis=1)
                        for a, b in ((0, 1), (1, 2), (2, 0))], axis=0)
        if (apart > step).any():
            assert_same_geometry(TriangleMesh(vertices, faces[apart > step]), decoded, 12)


def test_plain_glb_round_trip_is_exact_in_float32() -> None:
    mesh = sphere(subdivisions=3, noise=0.05)
    decoded = decode_glb(encode_glb(mesh, draco=None))
    np.testing.assert_array_equal(decoded.vertices_m, mesh.vertices_m.astype(np.float32))
    np.testing.assert_array_equal(decoded.faces, mesh.faces)
    np.testing.assert_array_equal(decoded.vertex_colors, mesh.vertex_colors)
    np.testing.assert_array_equal(decoded.vertex_normals,
                                  vertex_normals(mesh.vertices_m, mesh.faces))


def test_given_normals_are_written_not_recomputed() -> None:
    base = sphere(subdivisions=2)
    flipped = -vertex_normals(base.vertices_m, base.faces)
    mesh = TriangleMesh(base.vertices_m, base.faces, base.vertex_colors, flipped)
    np.testing.assert_array_equal(decode_glb(encode_glb(mesh, draco=None)).vertex_normals, flipped)


def test_mesh_without_colours_has_no_color_attribute() -> None:
    mesh = sphere(subdivisions=2, colored=False)
    for draco in (DracoConfig(), None):
        data = encode_glb(mesh, draco=draco)
        (primitive,) = glb_json(data)["meshes"][0]["primitives"]
        assert "COLOR_0" not in primitive["attributes"]
        assert decode_glb(data).vertex_colors is None


def test_fewer_colour_bits_merge_levels_and_shrink_the_file() -> None:
    mesh = sphere(subdivisions=4, noise=0.02)
    full = encode_glb(mesh)
    coarse = encode_glb(mesh, draco=DracoConfig(color_quantization_bits=4))
    decoded = decode_glb(coarse)
    index = assert_same_geometry(mesh, decoded, 14)
    assert mesh.vertex_colors is not None and decoded.vertex_colors is not None
    error = np.abs(decoded.vertex_colors.astype(int) - mesh.vertex_colors[index].astype(int))
    assert error.max() <= np.ceil(255 / 15 / 2)
    assert len(np.unique(decoded.vertex_colors)) <= 16
    assert len(coarse) < len(full)


# --- the file itself -------------------------------------------------------------------------


def test_draco_glb_structure() -> None:
    mesh = sphere(subdivisions=3)
    data = encode_glb(mesh, extras={"source": "test"})
    doc = glb_json(data)
    assert DRACO_EXTENSION in doc["extensionsUsed"]
    assert DRACO_EXTENSION in doc["extensionsRequired"]
    assert doc["asset"] == {"version": "2.0", "generator": "volumesh", "extras": {"source": "test"}}
    (primitive,) = doc["meshes"][0]["primitives"]
    assert set(primitive["attributes"]) == {"POSITION", "NORMAL", "COLOR_0"}
    accessor_ids = [*primitive["attributes"].values(), primitive["indices"]]
    for accessor_id in accessor_ids:
        assert "bufferView" not in doc["accessors"][accessor_id]
        assert "byteOffset" not in doc["accessors"][accessor_id]
    # The ids name the attributes as Draco itself numbered them.
    extension = primitive["extensions"][DRACO_EXTENSION]
    view = doc["bufferViews"][extension["bufferView"]]
    binary_start = 20 + struct.unpack_from("<I", data, 12)[0] + 8
    draco_bytes = data[binary_start + view.get("byteOffset", 0):][: view["byteLength"]]
    decoded = DracoPy.decode(draco_bytes)
    by_type = {a["attribute_type"]: a["unique_id"] for a in decoded.attributes}
    assert extension["attributes"] == {"POSITION": by_type[0], "NORMAL": by_type[1],
                                       "COLOR_0": by_type[2]}
    position = doc["accessors"][primitive["attributes"]["POSITION"]]
    assert position["count"] == len(decoded.points)
    np.testing.assert_allclose(position["min"], np.asarray(decoded.points).min(axis=0))
    np.testing.assert_allclose(position["max"], np.asarray(decoded.points).max(axis=0))
    color = doc["accessors"][primitive["attributes"]["COLOR_0"]]
    assert (color["componentType"], color["type"], color["normalized"]) == (5121, "VEC3", True)
    material = doc["materials"][primitive["material"]]["pbrMetallicRoughness"]
    assert material["metallicFactor"] == 0.0
    assert 0.5 <= material["roughnessFactor"] <= 1.0


def test_draco_and_plain_glb_pass_the_khronos_validator(tmp_path: Path) -> None:
    mesh = sphere(subdivisions=3, noise=0.05)
    for draco in (DracoConfig(), DracoConfig(position_quantization_bits=11), None):
        report = validate(tmp_path, encode_glb(mesh, draco=draco))
        assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
        assert report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
        assert report["info"]["generator"] == "volumesh"


def test_validator_catches_a_broken_file(tmp_path: Path) -> None:
    # Guards the test above: a Draco accessor with a byteOffset must be reported.
    data = encode_glb(sphere(subdivisions=1))
    doc = glb_json(data)
    doc["accessors"][0]["byteOffset"] = 0
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    old_length = struct.unpack_from("<I", data, 12)[0]
    rest = data[20 + old_length:]
    broken = struct.pack("<III", 0x46546C67, 2, 20 + len(text) + len(rest))
    broken += struct.pack("<II", len(text), 0x4E4F534A) + text + rest
    assert validate(tmp_path, broken)["issues"]["numErrors"] > 0


def test_test_model_passes_validator_and_round_trips(tmp_path: Path) -> None:
    mesh = read_mesh(BUNNY) if BUNNY.is_file() else sphere(subdivisions=5, noise=0.03)
    colors = np.clip(np.rint(255 * (mesh.vertices_m - mesh.vertices_m.min(axis=0))
                             / np.ptp(mesh.vertices_m, axis=0).max()), 0, 255).astype(np.uint8)
    mesh = TriangleMesh(mesh.vertices_m, mesh.faces, colors)
    data = encode_glb(mesh)
    report = validate(tmp_path, data)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
    decoded = decode_glb(data)
    index = assert_same_geometry(mesh, decoded, 14)
    np.testing.assert_array_equal(decoded.vertex_colors, colors[index])
    assert decoded.face_count == mesh.face_count


def test_draco_is_much_smaller_than_plain_glb() -> None:
    mesh = sphere(subdivisions=5, noise=0.02)
    draco, plain = encode_glb(mesh), encode_glb(mesh, draco=None)
    assert len(draco) * 5 < len(plain)


# --- bad input -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("mesh", "field"),
    [
        (TriangleMesh(np.zeros((3, 3)), np.zeros((0, 3), dtype=np.int32)), "faces"),
        (TriangleMesh(np.zeros((0, 3)), np.zeros((1, 3), dtype=np.int32)), "vertices_m"),
        (TriangleMesh(np.eye(3), np.array([[0, 1, 3]], dtype=np.int32)), "faces"),
        (TriangleMesh(np.eye(3), np.array([[0, -1, 2]], dtype=np.int32)), "faces"),
        (TriangleMesh(np.array([[0, 0, np.nan], [1, 0, 0], [0, 1, 0]]),
                      np.array([[0, 1, 2]], dtype=np.int32)), "vertices_m"),
        (TriangleMesh(np.eye(3), np.array([[0, 1, 2]], dtype=np.int32),
                      np.zeros((2, 3), dtype=np.uint8)), "vertex_colors"),
        (TriangleMesh(np.eye(3), np.array([[0, 1, 2]], dtype=np.int32),
                      np.zeros((3, 3), dtype=np.float32)), "vertex_colors"),  # type: ignore[arg-type]
    ],
)
def test_bad_meshes_are_refused_naming_the_field(mesh: TriangleMesh, field: str) -> None:
    for draco in (DracoConfig(), None):
        with pytest.raises(ValueError, match=field):
            encode_glb(mesh, draco=draco)


@pytest.mark.parametrize(
    "kwargs",
    [{"position_quantization_bits": 0}, {"position_quantization_bits": 31},
     {"normal_quantization_bits": 0}, {"color_quantization_bits": 9},
     {"compression_level": 11}, {"compression_level": 2.5}],
)
def test_bad_draco_config_is_refused(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        DracoConfig(**kwargs)


def test_bad_extras_are_refused() -> None:
    with pytest.raises(ValueError, match="extras"):
        encode_glb(sphere(subdivisions=1), extras={"x": object()})


# --- files and LOD ---------------------------------------------------------------------------


def test_write_mesh_dispatches_on_suffix(tmp_path: Path) -> None:
    mesh = sphere(subdivisions=2)
    write_mesh(tmp_path / "a.glb", mesh)
    assert (tmp_path / "a.glb").read_bytes() == encode_glb(mesh)
    write_glb(tmp_path / "sub" / "b.GLB", mesh, draco=None)
    assert (tmp_path / "sub" / "b.GLB").read_bytes() == encode_glb(mesh, draco=None)
    write_mesh(tmp_path / "c.ply", mesh)
    back = read_mesh(tmp_path / "c.ply")
    assert back.face_count == mesh.face_count
    np.testing.assert_allclose(back.vertices_m, mesh.vertices_m, atol=1e-6)
    with pytest.raises(ValueError, match=r"d\.obj"):
        write_mesh(tmp_path / "d.obj", mesh)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a.glb", "b.GLB", "c.ply", "sub"]


def test_simplify_reaches_target_and_keeps_shape_and_colours() -> None:
    mesh = sphere(subdivisions=5, radius=0.3)
    reduced = simplify(mesh, 2000)
    assert 1800 <= reduced.face_count <= 2000
    radii = np.linalg.norm(reduced.vertices_m, axis=1)
    assert np.abs(radii - 0.3).max() < 0.01
    assert reduced.vertex_colors is not None
    expected = np.clip(np.rint(127.5 + 120.0 * reduced.vertices_m / radii[:, None]), 0, 255)
    assert np.abs(reduced.vertex_colors - expected).max() <= 8
    assert simplify(mesh, mesh.face_count) is mesh
    for bad in (0, -5):
        with pytest.raises(ValueError, match="target_faces"):
            simplify(mesh, bad)
