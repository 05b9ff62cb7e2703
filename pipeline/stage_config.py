"""What a reconstruction depends on: its config, built and validated from job options (JSON-
like, as the API and the CLI receive them), and the hash that keys its cached stage outputs."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.enhance.config import REMOVED_SETTINGS, EnhanceConfig
from pipeline.reconstruct.align import AlignConfig
from pipeline.reconstruct.colorize import ColorizeConfig
from pipeline.reconstruct.crop import CropConfig
from pipeline.reconstruct.depth_filter import DepthFilterConfig
from pipeline.reconstruct.meshing import MeshingConfig
from pipeline.reconstruct.registration import RegistrationConfig
from pipeline.reconstruct.remesh.isotropic import RemeshConfig
from pipeline.reconstruct.surface_fit import SurfaceFitConfig
from pipeline.reconstruct.voxel_refine import VoxelRefineConfig

_RIGID_TOLERANCE = 1e-3


@dataclass(frozen=True)
class ReconstructConfig:
    """Everything a reconstruction depends on (its hash keys cached stage outputs)."""

    depth_filter: DepthFilterConfig = field(default_factory=DepthFilterConfig)
    """Depth clean-up (stage filter)."""
    align: AlignConfig = field(default_factory=AlignConfig)
    """Per-camera range offsets and pose touch-ups from overlaps (stage align)."""
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    """Back-projection to oriented world points (stage register)."""
    crop: CropConfig = field(default_factory=CropConfig)
    """What of the registered points is not the subject (stage register)."""
    voxel_refine: VoxelRefineConfig = field(default_factory=VoxelRefineConfig)
    """One camera per voxel (stage refine)."""
    meshing: MeshingConfig = field(default_factory=MeshingConfig)
    """Poisson-disk sampling and surface (stage mesh)."""
    remesh: RemeshConfig = field(default_factory=RemeshConfig)
    """Isotropic remeshing and angle criteria (stage remesh)."""
    surface_fit: SurfaceFitConfig = field(default_factory=SurfaceFitConfig)
    """The remeshed vertices moved onto the refined points (stage fit)."""
    colorize: ColorizeConfig = field(default_factory=ColorizeConfig)
    """Vertex colours from the colour images (stage colorize)."""
    frame_index: int | None = None
    """The capture frame to reconstruct; None: the first one."""
    enhance: bool = False
    """Run the enhance stage. Off by default: the shipped model does not improve a
    reconstruction yet (see the README)."""
    enhancement: EnhanceConfig = field(default_factory=EnhanceConfig)
    """How the enhance stage works (method, views, resolution, DDIM steps...)."""
    world_from_depth: tuple[tuple[str, tuple[float, ...]], ...] = ()
    """Camera poses that replace the capture's: (camera id, 16 row-major values) pairs,
    e.g. from a calibration's rig.json."""

    @property
    def target_edge_length_m(self) -> float:
        """Remeshing target edge length, metres."""
        return self.remesh.target_edge_length_m


_SECTIONS = {"depth_filter", "align", "registration", "crop", "voxel_refine",
             "meshing", "remesh", "surface_fit", "enhancement", "colorize"}
CALIBRATION_SECTION = "calibration"
"""The job option section of the calibrate stage (`pipeline.calibration.CalibrationConfig`)."""
SERVICE_OPTIONS = frozenset({"rig_id", "calibration_capture_id", "rig_name", "calibrate_only",
                             CALIBRATION_SECTION})
"""Job options that say where a job's camera poses come from (a saved rig, or a calibration
capture and its settings); the service acts on them, the reconstruction config holds none."""
EXPORT_OPTION_PREFIX = "draco_"
"""Job options named so configure the export (the GLB's Draco compression), not the
reconstruction."""


def reconstruction_options(options: Mapping[str, Any]) -> dict[str, Any]:
    """The job options `config_from_options` reads: all but the service's and the export's."""
    return {key: value for key, value in options.items()
            if not key.startswith(EXPORT_OPTION_PREFIX) and key not in SERVICE_OPTIONS}


def _coerce(value: Any, current: Any, name: str) -> Any:
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise ValueError(f"{name}: expected true or false, got {value!r}")
        return value
    if isinstance(current, int) and not isinstance(current, bool):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{name}: expected an integer, got {value!r}")
        return value
    if isinstance(current, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{name}: expected a number, got {value!r}")
        if not np.isfinite(value):
            raise ValueError(f"{name}: must be finite")
        return float(value)
    if isinstance(current, str):
        if not isinstance(value, str):
            raise ValueError(f"{name}: expected a string, got {value!r}")
        return value
    if isinstance(current, tuple):
        if not isinstance(value, list | tuple):
            raise ValueError(f"{name}: expected a list, got {value!r}")
        return tuple(value)
    raise ValueError(f"{name}: cannot be set from options")


def replace_section(section: Any, values: Any, name: str) -> Any:
    """A frozen config dataclass with ``values`` (JSON-like, by field name) put in; ValueError
    naming ``name.field`` for an unknown field, a value of the wrong type or a bad value."""
    if not isinstance(values, Mapping):
        raise ValueError(f"{name}: expected an object of settings")
    fields = {f.name: f for f in dataclasses.fields(section)}
    removed = _REMOVED.get(name, {})
    changes = {}
    for key, value in values.items():
        if key in removed:
            raise ValueError(f"{name}.{key}: removed; {removed[key]}")
        if key not in fields:
            raise ValueError(f"{name}.{key}: unknown setting (known: {', '.join(fields)})")
        changes[key] = _coerce(value, getattr(section, key), f"{name}.{key}")
    try:
        return dataclasses.replace(section, **changes)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: {exc}") from None


def parse_world_from_depth(doc: Any, where: str = "world_from_depth"
                           ) -> tuple[tuple[str, tuple[float, ...]], ...]:
    """Validated {camera id: 4x4 rigid} (rig.json's "world_from_depth") as config pairs."""
    if not isinstance(doc, Mapping) or not doc:
        raise ValueError(f"{where}: expected a non-empty object of camera id -> 4x4 matrix")
    pairs = []
    for camera_id, value in doc.items():
        try:
            matrix = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}.{camera_id}: not a 4x4 matrix of numbers") from None
        if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
            raise ValueError(f"{where}.{camera_id}: expected a finite 4x4 matrix")
        rotation = matrix[:3, :3]
        if (not np.allclose(matrix[3], [0, 0, 0, 1], atol=_RIGID_TOLERANCE)
                or not np.allclose(rotation @ rotation.T, np.eye(3), atol=_RIGID_TOLERANCE)
                or np.linalg.det(rotation) < 0):
            raise ValueError(f"{where}.{camera_id}: not a rigid transform")
        pairs.append((str(camera_id), tuple(float(x) for x in matrix.ravel())))
    return tuple(sorted(pairs))


def config_from_options(options: Mapping[str, Any]) -> ReconstructConfig:
    """A validated config from job options (JSON-like); ValueError names a bad option.

    Known keys: enhance, frame_index, target_edge_length_m, voxel_size_m, world_from_depth
    ({camera id: 4x4}), and one object per stage section (e.g. {"meshing": {...}}).
    """
    if not isinstance(options, Mapping):
        raise ValueError("options: expected an object")
    config = ReconstructConfig()
    for key, value in options.items():
        if key == "enhance":
            config = dataclasses.replace(config, enhance=_coerce(value, False, key))
        elif key == "frame_index":
            index = None if value is None else _coerce(value, 0, key)
            if index is not None and index < 0:
                raise ValueError("frame_index: must be >= 0")
            config = dataclasses.replace(config, frame_index=index)
        elif key == "target_edge_length_m":
            section = replace_section(config.remesh, {"target_edge_length_m": value}, key)
            config = dataclasses.replace(config, remesh=section)
        elif key == "voxel_size_m":
            section = replace_section(config.voxel_refine, {"voxel_size_m": value}, key)
            config = dataclasses.replace(config, voxel_refine=section)
        elif key == "world_from_depth":
            config = dataclasses.replace(config, world_from_depth=parse_world_from_depth(value))
        elif key in _SECTIONS:
            section = replace_section(getattr(config, key), value, key)
            config = dataclasses.replace(config, **{key: section})
        else:
            raise ValueError(f"{key}: unknown reconstruction option")
    return config


def config_hash(config: ReconstructConfig) -> str:
    """A stable hex digest of every setting of the config."""
    text = json.dumps(dataclasses.asdict(config), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


_REMOVED = {"enhancement": REMOVED_SETTINGS}
"""{section: {setting: what replaced it}} of settings a job may no longer set."""


def settings_kinds() -> dict[str, dict[str, str]]:
    """{section: {setting: kind}} of every job option section (the stage sections and
    ``calibration``), kind one of bool, int, float, str, list, fixed (not settable from
    options) or ``removed: <what replaced it>``. The gateway, which does not import the
    pipeline, checks job options against a copy of this (`app/core/stage_settings.json`; a
    test keeps the two equal)."""
    from pipeline.calibration import CalibrationConfig

    sections = {name: getattr(ReconstructConfig(), name) for name in sorted(_SECTIONS)}
    sections[CALIBRATION_SECTION] = CalibrationConfig()
    return {name: {f.name: _kind(getattr(section, f.name))
                   for f in dataclasses.fields(section)}
            | {key: f"removed: {why}" for key, why in _REMOVED.get(name, {}).items()}
            for name, section in sorted(sections.items())}


def _kind(current: Any) -> str:
    """The JSON kind `_coerce` accepts for a setting whose default is `current`."""
    for kind, types in (("bool", bool), ("int", int), ("float", float), ("str", str),
                        ("list", tuple)):
        if isinstance(current, types):
            return kind
    return "fixed"
