"""Frame sources: MJPEG with capture times, OpenCV files, the newest-frame grabber."""

from __future__ import annotations

import itertools
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from companion.camera.source import (
    Frame,
    FrameSource,
    LatestFrameGrabber,
    MjpegSource,
    OpenCvSource,
    open_source,
)
from companion.errors import ConfigError, InputError
from sitl.stream import MjpegServer

ImageU8 = NDArray[np.uint8]
WAIT_S = 10.0  # generous upper bound for conditions that hold in milliseconds


def _image(i: int) -> ImageU8:
    """A smooth 64 x 48 test image, distinct for each i (JPEG keeps it within a few levels)."""
    x = np.linspace(0.0, 1.0, 64)[None, :] + np.linspace(0.0, 1.0, 48)[:, None]
    return np.asarray(20 + 30 * i + 60 * x, dtype=np.uint8)


def _close(a: ImageU8, b: ImageU8) -> bool:
    return bool(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))) < 4.0)


class _Counting:
    """A FrameSource wrapper that lets a test wait until read() has been called n times."""

    def __init__(self, inner: FrameSource) -> None:
        self.inner = inner
        self.calls = 0
        self._cond = threading.Condition()

    def read(self) -> Frame | None:
        with self._cond:
            self.calls += 1
            self._cond.notify_all()
        return self.inner.read()

    def close(self) -> None:
        self.inner.close()

    def wait_calls(self, n: int) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: self.calls >= n, timeout=WAIT_S)


class _Scripted:
    """A FrameSource playing a script: an exception is raised, a frame returned, None ends."""

    def __init__(self, script: list[Exception | Frame | None]) -> None:
        self.script = list(script)

    def read(self) -> Frame | None:
        item = self.script.pop(0) if self.script else None
        if isinstance(item, Exception):
            raise item
        return item

    def close(self) -> None:
        pass


def test_mjpeg_source_yields_frames_with_their_capture_times(no_thread_left: None) -> None:
    clock = itertools.count(100.0)
    times_s = [3.0, 3.05, 3.100001, 4.5]
    with MjpegServer() as server:
        source = open_source(server.url, clock=lambda: float(next(clock)))
        assert isinstance(source, MjpegSource)
        try:
            frames = []
            for i, t_s in enumerate(times_s):
                server.publish(_image(i), t_s)  # lock step: this is the next frame read
                frame = source.read()
                assert frame is not None
                frames.append(frame)
        finally:
            source.close()
        assert source.read() is None
    assert [f.capture_time_s for f in frames] == times_s
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    assert [f.receive_time_s for f in frames] == [100.0, 101.0, 102.0, 103.0]
    for i, frame in enumerate(frames):
        assert frame.image.shape == (48, 64) and _close(frame.image, _image(i))


def test_grabber_hands_over_the_newest_and_counts_what_it_dropped(no_thread_left: None) -> None:
    n = 6
    with MjpegServer() as server:
        source = _Counting(open_source(server.url))
        with LatestFrameGrabber(source, clock=lambda: 7.0) as grabber:
            for i in range(n):
                source.wait_calls(i + 1)  # the grabber waits for frame i
                server.publish(_image(i), 10.0 + i)
            source.wait_calls(n + 1)  # frame n-1 is stored: the grabber reads on
            frame = grabber.get(WAIT_S)
            assert frame is not None and frame.capture_time_s == 10.0 + n - 1
            assert frame.receive_time_s == 7.0 and frame.seq == n - 1
            assert (grabber.grabbed, grabber.dropped, grabber.errors) == (n, n - 1, 0)
            assert grabber.get(0.0) is None  # nothing newer than what was handed over
            server.publish(_image(0), 20.0)
            frame = grabber.get(WAIT_S)
            assert frame is not None and frame.capture_time_s == 20.0
            assert (grabber.grabbed, grabber.dropped) == (n + 1, n - 1)
        assert not grabber.running and grabber.error is None


def test_grabber_stop_joins_while_the_source_blocks(no_thread_left: None) -> None:
    with MjpegServer() as server:  # publishes nothing: the read blocks
        source = _Counting(open_source(server.url, timeout_s=60.0))
        grabber = LatestFrameGrabber(source).start()
        source.wait_calls(1)
        grabber.stop()  # closing the source ends the read at once, not after 60 s
        grabber.stop()
        assert not grabber.running and grabber.get(0.0) is None
        assert grabber.grabbed == 0 and grabber.error is None


def test_grabber_survives_errors_and_ends_with_the_stream(no_thread_left: None) -> None:
    frame = Frame(_image(0), None, 0.0, 0)
    source = _Scripted([ConnectionError("lost"), InputError("bad part"), frame, None])
    with LatestFrameGrabber(source, clock=lambda: 5.0, backoff_s=0.001) as grabber:
        got = grabber.get(WAIT_S)
        assert got is not None and got.receive_time_s == 5.0 and got.image is frame.image
        assert grabber.get(WAIT_S) is None  # returns as soon as the stream has ended
        assert not grabber.running
        assert (grabber.grabbed, grabber.dropped, grabber.errors) == (1, 0, 2)
        assert grabber.error is None


def test_grabber_gives_up_after_consecutive_errors(no_thread_left: None) -> None:
    source = _Scripted([InputError(f"failure {i}") for i in range(10)])
    with LatestFrameGrabber(source, max_consecutive_errors=3, backoff_s=0.001) as grabber:
        assert grabber.get(WAIT_S) is None
        assert grabber.errors == 3 and not grabber.running
        assert isinstance(grabber.error, InputError) and "failure 2" in str(grabber.error)
    with pytest.raises(ConfigError, match="max_consecutive_errors"):
        LatestFrameGrabber(source, max_consecutive_errors=0)


def test_opencv_source_reads_a_video_file_with_its_frame_times(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (64, 48))
    assert writer.isOpened()
    for i in range(4):
        writer.write(cv2.cvtColor(_image(i), cv2.COLOR_GRAY2BGR))
    writer.release()
    source = open_source(str(path), time_offset_s=50.0, clock=lambda: 1.5)
    assert isinstance(source, OpenCvSource) and source.is_file
    frames = []
    while (frame := source.read()) is not None:
        frames.append(frame)
    source.close()
    assert source.read() is None
    assert [f.capture_time_s for f in frames] == pytest.approx([50.0, 50.1, 50.2, 50.3])
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    assert all(f.receive_time_s == 1.5 for f in frames)
    for i, frame in enumerate(frames):
        assert frame.image.shape == (48, 64) and _close(frame.image, _image(i))
    untimed = open_source(str(path), kind="opencv")
    first = untimed.read()
    untimed.close()
    assert first is not None and first.capture_time_s is None


def test_bad_specs_are_named(tmp_path: Path) -> None:
    missing = str(tmp_path / "nothing.avi")
    with pytest.raises(InputError, match=r"nothing\.avi"):
        open_source(missing)
    with pytest.raises(InputError, match="/dev/video99"):
        open_source("/dev/video99")
    with pytest.raises(InputError, match="non-empty"):
        open_source("  ")
    with pytest.raises(ConfigError, match=r"camera\.kind"):
        open_source(missing, kind="webcam")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"camera\.url"):
        open_source("rtsp://127.0.0.1/x", kind="mjpeg")
    with pytest.raises(ConfigError, match="video files only"):
        open_source("http://127.0.0.1:1/stream.mjpg", time_offset_s=1.0)
    with pytest.raises(InputError, match="grey"):
        Frame(np.zeros((4, 4, 3), np.uint8), None, 0.0, 0)
