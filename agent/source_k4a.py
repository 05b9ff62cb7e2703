"""Live Azure Kinect devices through pyk4a (the optional extra ``volumesh[k4a]``).

Every connected device runs NFOV unbinned depth with 720p MJPG colour at 30 fps, images
synchronised within a capture. On a sync cable, the device with only its out-jack wired is
the master and the others subordinates, each 160 us after the one before (the Sensor SDK's
advice, so their depth lasers do not interfere); subordinates start first, because they wait
for the master's trigger. Captures are matched into frame-sets by device timestamp less the
subordinate delay, as recordings are (pipeline.io.k4a_sync).

Written against pyk4a's documented API (PyK4A, Config, PyK4ACapture); not testable without
devices.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from typing import Any

from agent.sources import FrameSet, SourceInfo
from pipeline.capture import CAMERA_ID_PATTERN, CameraInfo
from pipeline.io.capture_io import StoredView
from pipeline.io.k4a_calibration import (
    color_from_depth,
    color_intrinsics,
    depth_intrinsics,
    parse_calibration,
)
from pipeline.io.k4a_mkv import DEPTH_UNIT_M
from pipeline.io.k4a_sync import match_frames

PYK4A_MISSING = "the k4a source needs pyk4a: pip install 'volumesh[k4a]'"
DEPTH_MODE = "NFOV_UNBINNED"
COLOR_SIZE_PX = (1280, 720)
FPS = 30
SUBORDINATE_STEP_US = 160
CAPTURE_TIMEOUT_MS = 2000
"""A device silent this long has stopped (unplugged, or a subordinate without its master)."""
log = logging.getLogger(__name__)


def open_k4a() -> K4aSource:
    """Every connected device, started; ValueError when pyk4a or a device is missing."""
    try:
        import pyk4a
    except ImportError:
        raise ValueError(PYK4A_MISSING) from None
    count = pyk4a.connected_device_count()
    if count < 1:
        raise ValueError("k4a: no Azure Kinect device connected")
    return K4aSource(pyk4a, count)


def _sync_modes(pyk4a: Any, count: int) -> list[str]:
    """Each device's wired sync mode, from its sync jacks."""
    if count == 1:
        return ["STANDALONE"]
    modes = []
    for device_id in range(count):
        probe = pyk4a.PyK4A(device_id=device_id)
        probe.open()
        try:
            jack_in, jack_out = probe.sync_jack_status
        finally:
            probe.close()
        modes.append("SUBORDINATE" if jack_in else "MASTER" if jack_out else "STANDALONE")
    if modes.count("MASTER") != 1:
        log.warning("k4a: %d devices, %d master(s) on a sync cable: frames are matched by "
                    "device timestamps that may not share a clock", count, modes.count("MASTER"))
    return modes


class K4aSource:
    def __init__(self, pyk4a: Any, count: int) -> None:
        self.pyk4a = pyk4a
        modes = _sync_modes(pyk4a, count)
        self.delays_us = [0] * count
        self.devices: list[Any] = [None] * count
        rank = 0
        try:
            for device_id in sorted(range(count), key=lambda i: modes[i] == "MASTER"):
                if modes[device_id] == "SUBORDINATE":
                    rank += 1
                    self.delays_us[device_id] = rank * SUBORDINATE_STEP_US
                self.devices[device_id] = self._start(device_id, modes[device_id])
            cameras = tuple(self._camera(i, d) for i, d in enumerate(self.devices))
        except BaseException:  # stop the devices already started
            self.close()
            raise
        self.info = SourceInfo(cameras=cameras, depth_scale=DEPTH_UNIT_M, fps=FPS, live=True)
        self.incomplete = 0

    def _start(self, device_id: int, mode: str) -> Any:
        k4a = self.pyk4a
        config = k4a.Config(color_resolution=k4a.ColorResolution.RES_720P,
                            color_format=k4a.ImageFormat.COLOR_MJPG,
                            depth_mode=k4a.DepthMode.NFOV_UNBINNED, camera_fps=k4a.FPS.FPS_30,
                            synchronized_images_only=True,
                            wired_sync_mode=getattr(k4a.WiredSyncMode, mode),
                            subordinate_delay_off_master_usec=self.delays_us[device_id])
        device = k4a.PyK4A(config, device_id=device_id)
        device.start()
        return device

    def _camera(self, device_id: int, device: Any) -> CameraInfo:
        serial = str(getattr(device, "serial", "") or "")
        camera_id = serial if re.fullmatch(CAMERA_ID_PATTERN, serial) else f"cam{device_id}"
        calibration = parse_calibration(device.calibration_raw.encode(), camera_id)
        return CameraInfo(id=camera_id,
                          depth_intrinsics=depth_intrinsics(calibration, DEPTH_MODE),
                          color_intrinsics=color_intrinsics(calibration, COLOR_SIZE_PX,
                                                            camera_id),
                          color_from_depth=color_from_depth(calibration))

    def _captures(self, device_id: int) -> Iterator[tuple[int, Any]]:
        """(trigger time in us, capture) of one device, as they come."""
        device = self.devices[device_id]
        while True:
            try:
                capture = device.get_capture(timeout=CAPTURE_TIMEOUT_MS)
            except self.pyk4a.K4ATimeoutException:
                raise ValueError(f"k4a: device {device_id} sent no capture in "
                                 f"{CAPTURE_TIMEOUT_MS} ms") from None
            if capture.depth is not None:
                yield capture.depth_timestamp_usec - self.delays_us[device_id], capture

    def frame_sets(self, first_position: int) -> Iterator[FrameSet]:
        streams = [self._captures(i) for i in range(len(self.devices))]
        matched = match_frames(streams, lambda pair: pair[0], 1_000_000 // FPS // 2)
        for position, frame_set in enumerate(matched, start=first_position):
            if not frame_set.complete:
                self.incomplete += 1
                continue
            views = tuple(self._view(camera, position, pair[1])  # type: ignore[index]
                          for camera, pair in zip(self.info.cameras, frame_set.frames,
                                                  strict=True))
            yield FrameSet(position, max(frame_set.timestamp_us, 0), views)

    @staticmethod
    def _view(camera: CameraInfo, position: int, capture: Any) -> StoredView:
        color = capture.color  # MJPG: the JPEG file's bytes in a 1-D uint8 array
        return StoredView(camera, position, capture.depth,
                          color_jpeg=None if color is None else color.tobytes())

    def close(self) -> None:
        for device in self.devices:
            if device is not None and device.is_running:
                device.stop()
