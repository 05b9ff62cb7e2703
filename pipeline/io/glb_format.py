"""The GLB container's and glTF's numeric codes, shared by the writer (`gltf_io`) and the
reader (`gltf_read`)."""

from __future__ import annotations

import numpy as np

DRACO_EXTENSION = "KHR_draco_mesh_compression"
GENERATOR = "volumesh"

GLB_MAGIC = 0x46546C67  # "glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
FLOAT, UBYTE, USHORT, UINT = 5126, 5121, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
TRIANGLES = 4
COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
DTYPES = {FLOAT: np.float32, UBYTE: np.uint8, USHORT: np.uint16, UINT: np.uint32,
          5120: np.int8, 5122: np.int16}
