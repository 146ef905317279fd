"""An episode's camera frames as an MP4 (PyAV): yuv420p, a keyframe every two frames (LeRobot's
setting, so its decoder seeks cheaply), frame i stamped exactly i / fps."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from services.runtime import REALTIME, drop_realtime, process_threads

CODECS = {"h264": "libx264", "av1": "libsvtav1"}  # LeRobot's name -> the encoder
CRF = "30"


class _NoRealtimeThreads:
    """SVT-AV1 run as root starts its threads under SCHED_FIFO at priority 99 and leaves the thread
    that opened it there too: a busy encoder (or the server thread after it) then starves every other
    process on the machine. Each check puts the threads it has not seen yet back to SCHED_OTHER."""

    def __init__(self) -> None:
        self.enabled = hasattr(os, "sched_getscheduler") and os.sched_getscheduler(0) not in REALTIME
        self.seen: set[int] = set()

    def check(self) -> None:
        if not self.enabled:  # a process put under real-time scheduling on purpose keeps it
            return
        threads = process_threads()
        drop_realtime((threads - self.seen) | {threading.get_native_id()})
        self.seen = threads


class VideoWriter:
    """Frames (H, W, 3) uint8 RGB in, one MP4 out (written beside and renamed when done)."""

    def __init__(self, path: Path, *, fps: int, width: int, height: int, codec: str = "h264") -> None:
        if codec not in CODECS:
            raise ValueError(f"video codec {codec!r}: one of {', '.join(CODECS)}")
        if width % 2 or height % 2:
            raise ValueError(f"a {width}x{height} frame: yuv420p video needs an even width and height")
        os.environ.setdefault("SVT_LOG", "1")  # the AV1 encoder's banner, off
        self.path, self.fps = path, fps
        self.temporary = path.with_suffix(".mp4.tmp")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.container = av.open(str(self.temporary), "w", format="mp4")
        options = {"g": "2", "crf": CRF} | ({"preset": "12"} if codec == "av1" else {})
        stream = self.container.add_stream(CODECS[codec], rate=fps, options=options)
        assert isinstance(stream, av.VideoStream)  # a video codec's stream
        self.stream = stream
        self.stream.width, self.stream.height, self.stream.pix_fmt = width, height, "yuv420p"
        self.stream.time_base = Fraction(1, fps)
        self.frames = 0
        self.realtime = _NoRealtimeThreads()

    def add(self, rgb: np.ndarray) -> None:
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb, dtype=np.uint8), format="rgb24")
        frame.pts, frame.time_base = self.frames, Fraction(1, self.fps)
        self.container.mux(self.stream.encode(frame))
        self.realtime.check()
        self.frames += 1

    def close(self) -> None:
        self.container.mux(self.stream.encode(None))
        self.container.close()
        self.realtime.check()
        self.temporary.replace(self.path)

    def abort(self) -> None:
        self.container.close()
        self.realtime.check()
        self.temporary.unlink(missing_ok=True)


def write_video(path: Path, frames: Iterable[np.ndarray], *, fps: int, codec: str = "h264") -> int:
    """Encode `frames` (the first gives the size); the number written."""
    writer: VideoWriter | None = None
    try:
        for rgb in frames:
            if writer is None:
                writer = VideoWriter(path, fps=fps, width=rgb.shape[1], height=rgb.shape[0], codec=codec)
            writer.add(rgb)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    if writer is None:
        return 0
    writer.close()
    return writer.frames
