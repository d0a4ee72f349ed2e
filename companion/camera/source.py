"""One interface for every frame source, and a thread that keeps only the newest frame.

`open_source(spec)` opens a device index ("0"), "/dev/videoN", a GStreamer pipeline (contains
"!"), an rtsp://, http:// ... URL or a video file through OpenCV, and a multipart MJPEG stream
whose parts carry X-Capture-Time-Us (an http URL ending in /stream.mjpg, as the SITL serves)
through `MjpegSource`. Every source yields `Frame`s: grey images with the capture time on the
autopilot's boot time base when the source knows it. `LatestFrameGrabber` reads a source in a
thread so a slow consumer always gets the newest frame and never the same one twice.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Protocol
from urllib.parse import urlsplit

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.camera.mjpeg import MjpegReader
from companion.errors import ConfigError, InputError
from companion.vision.camera import is_number

__all__ = ["Frame", "FrameSource", "LatestFrameGrabber", "MjpegSource", "OpenCvSource",
           "open_source"]

Clock = Callable[[], float]
SourceKind = Literal["auto", "opencv", "mjpeg"]
MJPEG_PATH = "/stream.mjpg"


@dataclass(frozen=True, slots=True)
class Frame:
    """A grey (H, W) uint8 image, its capture time (boot time base, s) if known, receive time."""

    image: NDArray[np.uint8]
    capture_time_s: float | None  # on the autopilot's boot time base; None when unknown
    receive_time_s: float  # on the reader's (monotonic) clock
    seq: int  # 0, 1, 2 ... in the order the source read them

    def __post_init__(self) -> None:
        if (not isinstance(self.image, np.ndarray) or self.image.dtype != np.uint8
                or self.image.ndim != 2):
            raise InputError(f"frame image must be a grey (H, W) uint8 array, got "
                             f"{getattr(self.image, 'dtype', type(self.image).__name__)} "
                             f"{getattr(self.image, 'shape', '')}")


class FrameSource(Protocol):
    """Frames in order: read() blocks for the next, None at the end; close() ends a blocked read."""

    def read(self) -> Frame | None: ...

    def close(self) -> None: ...


def _grey(image: NDArray[Any]) -> NDArray[np.uint8]:
    """A decoded image (grey, BGR or BGRA) as a grey (H, W) uint8 array."""
    image = np.asarray(image, dtype=np.uint8)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return np.asarray(cv2.cvtColor(image, code), dtype=np.uint8)
    return image.reshape(image.shape[:2]) if image.ndim == 3 else image


class MjpegSource:
    """A multipart MJPEG stream with X-Capture-Time-Us per part; after an error, read()
    reconnects."""

    def __init__(self, url: str, timeout_s: float = 5.0, clock: Clock = time.monotonic) -> None:
        self._reader = MjpegReader(url, timeout_s)
        self._clock = clock
        self._lock = threading.Lock()
        self._frames: Iterator[tuple[NDArray[np.uint8], float]] | None = None
        self._closed = threading.Event()
        self._seq = 0

    @property
    def corrupt_frames(self) -> int:
        """Parts whose JPEG did not decode (skipped)."""
        return self._reader.corrupt_frames

    def read(self) -> Frame | None:
        """The next frame; None when the server ends the stream or after close()."""
        with self._lock:
            if self._closed.is_set():
                return None
            if self._frames is None:
                self._frames = self._reader.frames()
            frames = self._frames
        try:
            item = next(frames, None)
        except Exception:
            self._frames = None  # that generator is finished: the next read reconnects
            if self._closed.is_set():
                return None
            raise
        if item is None:
            return None
        image, capture_time_s = item
        self._seq += 1
        return Frame(_grey(image), capture_time_s, self._clock(), self._seq - 1)

    def close(self) -> None:
        """End the stream; a read() blocked in another thread returns None."""
        with self._lock:
            self._closed.set()
        self._reader.close()


def _opencv_target(spec: str) -> tuple[str | int, int, bool]:
    """(what cv2.VideoCapture opens, API preference, is a file) for a source spec."""
    if spec.isdigit():
        return int(spec), cv2.CAP_ANY, False
    if spec.startswith("/dev/video"):
        return spec, cv2.CAP_V4L2, False
    if "!" in spec:
        return spec, cv2.CAP_GSTREAMER, False
    if "://" in spec:
        return spec, cv2.CAP_FFMPEG, False
    if not Path(spec).expanduser().is_file():
        raise InputError(f"camera source {spec!r}: no such video file")
    return str(Path(spec).expanduser()), cv2.CAP_FFMPEG, True


class OpenCvSource:
    """Frames through cv2.VideoCapture, as grey; capture times only for a file given
    time_offset_s (offset + the frame's position in the file). A failed live read raises
    ConnectionError and the next read() reopens the source."""

    def __init__(self, spec: str, time_offset_s: float | None = None, timeout_s: float = 5.0,
                 clock: Clock = time.monotonic) -> None:
        self.spec = spec
        self._target, self._api, self.is_file = _opencv_target(spec)
        if time_offset_s is not None and not (is_number(time_offset_s)
                                              and math.isfinite(time_offset_s)):
            raise ConfigError("camera.time_offset_s", f"must be a finite number, got "
                                                      f"{time_offset_s!r}")
        if time_offset_s is not None and not self.is_file:
            raise ConfigError("camera.time_offset_s", f"applies to video files only, not {spec!r}")
        if not is_number(timeout_s) or not 0.0 < timeout_s < math.inf:
            raise ConfigError("camera.timeout_s", f"must be a number > 0, got {timeout_s!r}")
        self._time_offset_s = time_offset_s
        self._timeout_ms = round(timeout_s * 1000)
        self._clock = clock
        self._lock = threading.Lock()  # cv2.VideoCapture is not thread-safe: read vs release
        self._closed = False
        self._seq = 0
        self._capture: Any = self._open()

    def _open(self) -> Any:
        params = [] if self._api != cv2.CAP_FFMPEG else [
            cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, self._timeout_ms,
            cv2.CAP_PROP_READ_TIMEOUT_MSEC, self._timeout_ms]
        capture = cv2.VideoCapture(self._target, self._api, params)
        if not capture.isOpened():
            capture.release()
            backend = {cv2.CAP_GSTREAMER: " (GStreamer)", cv2.CAP_V4L2: " (V4L2)"}
            raise InputError(f"camera source {self.spec!r}: OpenCV cannot open it"
                             f"{backend.get(self._api, '')}")
        return capture

    def read(self) -> Frame | None:
        """The next frame; None at the end of a file or after close()."""
        with self._lock:
            if self._closed:
                return None
            if self._capture is None:
                self._capture = self._open()
            ok, image = self._capture.read()
            position_ms = float(self._capture.get(cv2.CAP_PROP_POS_MSEC)) if ok else 0.0
            if not ok and not self.is_file:
                self._capture.release()
                self._capture = None
                raise ConnectionError(f"camera source {self.spec!r}: no frame (source lost)")
        if not ok:
            return None
        capture_time_s = (None if self._time_offset_s is None
                          else self._time_offset_s + position_ms / 1000.0)
        self._seq += 1
        return Frame(_grey(image), capture_time_s, self._clock(), self._seq - 1)

    def close(self) -> None:
        """Release the capture; waits for a read in progress (at most one read timeout)."""
        self._closed = True
        with self._lock:
            if self._capture is not None:
                self._capture.release()
                self._capture = None


def open_source(spec: str, kind: SourceKind = "auto", *, time_offset_s: float | None = None,
                timeout_s: float = 5.0, clock: Clock = time.monotonic) -> FrameSource:
    """Open `spec` as `kind`; "auto" reads http URLs ending in /stream.mjpg as MjpegSource."""
    if not isinstance(spec, str) or not spec.strip():
        raise InputError(f"camera source must be a non-empty string, got {spec!r}")
    if kind not in ("auto", "opencv", "mjpeg"):
        raise ConfigError("camera.kind", f"must be 'auto', 'opencv' or 'mjpeg', got {kind!r}")
    parts = urlsplit(spec)
    if kind == "mjpeg" or (kind == "auto" and parts.scheme == "http"
                           and parts.path.endswith(MJPEG_PATH)):
        if time_offset_s is not None:
            raise ConfigError("camera.time_offset_s", "applies to video files only, not to an "
                                                      f"MJPEG stream ({spec!r})")
        return MjpegSource(spec, timeout_s, clock)
    return OpenCvSource(spec, time_offset_s, timeout_s, clock)


class LatestFrameGrabber:
    """Reads `source` in a thread, keeping only the newest frame (stamped receive_time_s by
    `clock`); get() hands each frame over at most once. It owns the source: stop() closes it.

    A read that raises is counted in `errors` and retried after a backoff (doubling from
    backoff_s up to backoff_max_s); `max_consecutive_errors` failures in a row end the grabber
    with `error` set. A clean end of stream (read() -> None) ends it with `error` None.
    """

    def __init__(self, source: FrameSource, clock: Clock = time.monotonic, *,
                 max_consecutive_errors: int = 10, backoff_s: float = 0.05,
                 backoff_max_s: float = 2.0, name: str = "frame-grabber") -> None:
        if not isinstance(max_consecutive_errors, int) or max_consecutive_errors < 1:
            raise ConfigError("camera.max_consecutive_errors",
                              f"must be an int >= 1, got {max_consecutive_errors!r}")
        if not (is_number(backoff_s) and is_number(backoff_max_s)
                and 0.0 <= backoff_s <= backoff_max_s < math.inf):
            raise ConfigError("camera.backoff_s", f"need 0 <= backoff_s <= backoff_max_s < inf, "
                                                  f"got {backoff_s!r}, {backoff_max_s!r}")
        self._source = source
        self._clock = clock
        self._max_errors = max_consecutive_errors
        self._backoff_s = float(backoff_s)
        self._backoff_max_s = float(backoff_max_s)
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._latest: Frame | None = None
        self._taken = True  # the latest frame was handed over (or there is none)
        self._ended = False
        self.grabbed = 0  # frames read
        self.dropped = 0  # frames replaced by a newer one before get() took them
        self.errors = 0  # reads that raised
        self.error: BaseException | None = None  # what ended the grabber, if errors did
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> LatestFrameGrabber:
        """Start reading; returns self."""
        if self._stop.is_set() or self._thread.is_alive() or self._ended:
            raise InputError("LatestFrameGrabber can be started once, and not after stop()")
        self._thread.start()
        return self

    @property
    def running(self) -> bool:
        """True until the stream ends, errors end it, or stop()."""
        with self._cond:
            return self._thread.is_alive() and not self._ended

    def get(self, timeout_s: float) -> Frame | None:
        """The newest frame not yet handed over, waiting up to timeout_s; None on timeout or
        once the grabber has ended and every frame was taken."""
        with self._cond:
            self._cond.wait_for(lambda: not self._taken or self._ended, timeout=timeout_s)
            if self._taken:
                return None
            self._taken = True
            return self._latest

    def stop(self) -> None:
        """Stop reading, close the source (which ends a blocked read) and join. Idempotent."""
        self._stop.set()
        self._source.close()
        if self._thread.is_alive():
            self._thread.join()
        with self._cond:
            self._ended = True
            self._cond.notify_all()

    def _run(self) -> None:
        failures = 0
        try:
            while not self._stop.is_set():
                try:
                    frame = self._source.read()
                except Exception as exc:
                    if self._stop.is_set():
                        return
                    failures += 1
                    with self._cond:
                        self.errors += 1
                        if failures >= self._max_errors:
                            self.error = exc
                            return
                    self._stop.wait(min(self._backoff_max_s,
                                        self._backoff_s * 2.0 ** (failures - 1)))
                    continue
                if frame is None:
                    return
                failures = 0
                frame = dataclasses.replace(frame, receive_time_s=self._clock())
                with self._cond:
                    self.grabbed += 1
                    if not self._taken:
                        self.dropped += 1
                    self._latest, self._taken = frame, False
                    self._cond.notify_all()
        finally:
            with self._cond:
                self._ended = True
                self._cond.notify_all()

    def __enter__(self) -> LatestFrameGrabber:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
