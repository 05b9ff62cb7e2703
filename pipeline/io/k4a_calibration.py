"""The Azure Kinect's device calibration (``calibration.json``) in the capture format's terms.

A device stores one calibration for its full sensors: the depth camera's 1024x1024 and the
colour camera's 4096x3072 (4:3; early devices 16:9, 4096x2304). Each camera has normalised
Brown-Conrady intrinsics, ``ModelParameters`` =
``[cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1]`` (principal point and focal
lengths divided by the sensor's width and height, origin at the top-left pixel's corner), and
``Rt``: the camera's pose as ``camera_from_reference`` (``Rotation`` 9 values row-major,
``Translation`` 3 values in metres).

Each recording mode sees a binned and cropped part of its sensor. The pixel intrinsics of a
mode follow the Sensor SDK (src/transformation/mode_specific_calibration.c): scale the
normalised values by the binned sensor size, subtract the crop offset, and move the origin to
the top-left pixel's centre (half a pixel). OpenCV's rational model takes the coefficients as
``[k1, k2, p1, p2, k3, k4, k5, k6]`` (the SDK's examples/opencv_compatibility).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.capture import Intrinsics

DEPTH_LOCATION = "CALIBRATION_CameraLocationD0"
COLOR_LOCATION = "CALIBRATION_CameraLocationPV0"
BROWN_CONRADY = "CALIBRATION_LensDistortionModelBrownConrady"
DEPTH_SENSOR_PX = (1024, 1024)
_PARAMETER_COUNT = 14


@dataclass(frozen=True)
class ModeCrop:
    """How a mode's image sits on its sensor, in pixels (width, height) / (x, y)."""

    binned_px: tuple[int, int]
    """The whole sensor at the mode's binning."""
    crop_px: tuple[int, int]
    """Offset of the image's top-left corner in the binned sensor (negative: padded)."""
    image_px: tuple[int, int]


DEPTH_MODES: dict[str, ModeCrop] = {
    "NFOV_2X2BINNED": ModeCrop((512, 512), (96, 90), (320, 288)),
    "NFOV_UNBINNED": ModeCrop((1024, 1024), (192, 180), (640, 576)),
    "WFOV_2X2BINNED": ModeCrop((512, 512), (0, 0), (512, 512)),
    "WFOV_UNBINNED": ModeCrop((1024, 1024), (0, 0), (1024, 1024)),
    "PASSIVE_IR": ModeCrop((1024, 1024), (0, 0), (1024, 1024)),
}
"""Depth modes by their K4A_DEPTH_MODE name."""

COLOR_MODES: dict[tuple[int, int], ModeCrop] = {
    crop.image_px: crop for crop in (
        ModeCrop((1280, 960), (0, 120), (1280, 720)),
        ModeCrop((1920, 1440), (0, 180), (1920, 1080)),
        ModeCrop((2560, 1920), (0, 240), (2560, 1440)),
        ModeCrop((2048, 1536), (0, 0), (2048, 1536)),
        ModeCrop((3840, 2880), (0, 360), (3840, 2160)),
        ModeCrop((4096, 3072), (0, 0), (4096, 3072)),
    )}
"""Colour resolutions (720p to 3072p) by their image size; all are views of the 4:3 sensor."""

# An early device calibrated its colour camera as 16:9 (4096x2304): the 4:3 sensor with 384
# rows cut off at the top and at the bottom.
_LEGACY_COLOR = ModeCrop((4096, 2304), (0, -384), (4096, 3072))


@dataclass(frozen=True)
class SensorCalibration:
    """One camera of calibration.json."""

    sensor_px: tuple[int, int]
    """The full sensor (width, height) its intrinsics are normalised by."""
    parameters: tuple[float, ...]
    """Normalised Brown-Conrady: cx, cy, fx, fy, k1..k6, codx, cody, p2, p1."""
    camera_from_reference: NDArray[np.float64]
    """4x4 rigid transform, metres, from the device's reference frame to this camera."""


@dataclass(frozen=True)
class DeviceCalibration:
    """A device's depth camera and, when it has one in the file, its colour camera."""

    depth: SensorCalibration
    color: SensorCalibration | None


def _camera(entry: dict[str, Any], where: str) -> SensorCalibration:
    """One entry of CalibrationInformation.Cameras; ValueError naming what is wrong."""
    try:
        intrinsics = entry["Intrinsics"]
        model = intrinsics["ModelType"]
        parameters = tuple(float(v) for v in intrinsics["ModelParameters"])
        rotation = np.array(entry["Rt"]["Rotation"], dtype=float)
        translation = np.array(entry["Rt"]["Translation"], dtype=float)
        sensor = (int(entry["SensorWidth"]), int(entry["SensorHeight"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: missing or malformed field ({exc})") from None
    if model != BROWN_CONRADY:
        raise ValueError(f"{where}: lens model {model}, only {BROWN_CONRADY} is supported")
    if len(parameters) < _PARAMETER_COUNT or not all(map(math.isfinite, parameters)):
        raise ValueError(f"{where}: ModelParameters: {_PARAMETER_COUNT} finite numbers needed")
    if rotation.shape != (9,) or translation.shape != (3,):
        raise ValueError(f"{where}: Rt: 9 rotation and 3 translation values needed")
    matrix = np.eye(4)
    matrix[:3, :3] = rotation.reshape(3, 3)
    matrix[:3, 3] = translation
    if (not np.all(np.isfinite(matrix)) or np.linalg.det(matrix[:3, :3]) < 0
            or not np.allclose(matrix[:3, :3].T @ matrix[:3, :3], np.eye(3), atol=1e-3)):
        raise ValueError(f"{where}: Rt.Rotation is not a rotation")
    return SensorCalibration(sensor, parameters[:_PARAMETER_COUNT], matrix)


def parse_calibration(data: bytes, name: str) -> DeviceCalibration:
    """The depth (D0) and colour (PV0) cameras of a calibration.json; ValueError naming
    ``name`` (the recording) where the file is not a device calibration."""
    try:
        document = json.loads(data.decode("utf-8").rstrip("\x00"))
        cameras = document["CalibrationInformation"]["Cameras"]
        by_location = {c["Location"]: c for c in cameras}
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{name}: calibration.json is not a device calibration ({exc})"
                         ) from None
    if DEPTH_LOCATION not in by_location:
        raise ValueError(f"{name}: calibration.json has no depth camera ({DEPTH_LOCATION})")
    depth = _camera(by_location[DEPTH_LOCATION], f"{name}: calibration.json: depth camera")
    if depth.sensor_px != DEPTH_SENSOR_PX:
        raise ValueError(f"{name}: calibration.json: depth sensor {depth.sensor_px}, expected "
                         f"{DEPTH_SENSOR_PX}")
    color = None
    if COLOR_LOCATION in by_location:
        color = _camera(by_location[COLOR_LOCATION], f"{name}: calibration.json: colour camera")
    return DeviceCalibration(depth=depth, color=color)


def _normalised_to_mode(parameters: tuple[float, ...], crop: ModeCrop) -> tuple[float, ...]:
    """(cx, cy, fx, fy) of normalised, corner-origin values as normalised values of the image
    ``crop`` cuts from the binned sensor (the SDK's non-pixelised output)."""
    cx, cy, fx, fy = parameters[:4]
    (bw, bh), (ox, oy), (w, h) = crop.binned_px, crop.crop_px, crop.image_px
    return ((cx * bw - ox) / w, (cy * bh - oy) / h, fx * bw / w, fy * bh / h)


def mode_intrinsics(parameters: tuple[float, ...], crop: ModeCrop) -> Intrinsics:
    """Pixel intrinsics of one mode: scaled by the binned sensor, shifted by the crop, origin
    at the top-left pixel's centre; distortion in OpenCV's rational order."""
    cx, cy, fx, fy = parameters[:4]
    (bw, bh), (ox, oy), (w, h) = crop.binned_px, crop.crop_px, crop.image_px
    k1, k2, k3, k4, k5, k6 = parameters[4:10]
    p2, p1 = parameters[12:14]
    return Intrinsics(width=w, height=h, fx=fx * bw, fy=fy * bh,
                      cx=cx * bw - ox - 0.5, cy=cy * bh - oy - 0.5,
                      distortion=(k1, k2, p1, p2, k3, k4, k5, k6))


def depth_intrinsics(calibration: DeviceCalibration, depth_mode: str) -> Intrinsics:
    """The depth camera's pixel intrinsics in ``depth_mode`` (a K4A_DEPTH_MODE name)."""
    return mode_intrinsics(calibration.depth.parameters, DEPTH_MODES[depth_mode])


def color_intrinsics(calibration: DeviceCalibration, size_px: tuple[int, int],
                     name: str) -> Intrinsics:
    """The colour camera's pixel intrinsics for images of ``size_px`` (width, height);
    ValueError naming ``name`` where the file has no colour camera or the size is no mode."""
    if calibration.color is None:
        raise ValueError(f"{name}: calibration.json has no colour camera ({COLOR_LOCATION}) "
                         "but the recording has colour")
    if size_px not in COLOR_MODES:
        modes = ", ".join(f"{w}x{h}" for w, h in COLOR_MODES)
        raise ValueError(f"{name}: colour images of {size_px[0]}x{size_px[1]} are no colour "
                         f"mode of the device ({modes})")
    parameters = calibration.color.parameters
    width, height = calibration.color.sensor_px
    if width * 9 // 16 == height:  # a 16:9 calibration: first as the 4:3 sensor
        parameters = _normalised_to_mode(parameters, _LEGACY_COLOR) + parameters[4:]
    elif width * 3 // 4 != height:
        raise ValueError(f"{name}: calibration.json: colour sensor {width}x{height} is neither "
                         "4:3 nor 16:9")
    return mode_intrinsics(parameters, COLOR_MODES[size_px])


def color_from_depth(calibration: DeviceCalibration) -> NDArray[np.float64]:
    """4x4 rigid transform, metres, from the depth camera to the colour camera."""
    if calibration.color is None:
        raise ValueError("calibration.json has no colour camera")
    depth_from_reference = calibration.depth.camera_from_reference
    reference_from_depth = np.eye(4)  # the rigid inverse, as the SDK composes extrinsics
    reference_from_depth[:3, :3] = depth_from_reference[:3, :3].T
    reference_from_depth[:3, 3] = -depth_from_reference[:3, :3].T @ depth_from_reference[:3, 3]
    return np.asarray(calibration.color.camera_from_reference @ reference_from_depth)
