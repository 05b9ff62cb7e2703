"""The synthetic rig (as `volumesh synth --motion rigid`): the built-in subject turning and
swaying before eight simulated Azure Kinects, rendered frame-set by frame-set as the stream
goes. Its cameras carry their poses, so its stream has a live preview without a rig."""

from __future__ import annotations

from collections.abc import Iterator

from agent.sources import FrameSet, SourceInfo
from pipeline.io.capture_io import stored_view
from pipeline.synth.motion import MotionConfig, synthesize_sequence
from pipeline.synth.scene import SynthConfig, sample_mesh

DEPTH_SCALE_M = 0.001
"""Millimetres, as the device's."""


class SyntheticSource:
    def __init__(self, frame_count: int, fps: float) -> None:
        self.config = SynthConfig(frame_count=frame_count)
        self.motion = MotionConfig(kind="rigid", frame_rate_hz=fps)
        self.mesh = sample_mesh()
        meta, self._views, _ = synthesize_sequence(self.mesh, self.config, self.motion,
                                                   by_frame=True)
        self.frames = meta.frames
        self.info = SourceInfo(cameras=meta.cameras, depth_scale=DEPTH_SCALE_M, fps=fps,
                               live=False)

    def frame_sets(self, first_position: int) -> Iterator[FrameSet]:
        first = min(first_position, self.config.frame_count)
        views = self._views
        if first > 0:  # resumed: render from there on (the views are drawn lazily)
            _, views, _ = synthesize_sequence(self.mesh, self.config, self.motion,
                                              by_frame=True, first_frame=first)
        count = len(self.info.cameras)
        for position in range(first, self.config.frame_count):
            frame = [next(views) for _ in range(count)]
            yield FrameSet(position, self.frames[position].timestamp_us,
                           tuple(stored_view(view, DEPTH_SCALE_M) for view in frame))

    def close(self) -> None:
        """Nothing held open."""
