"""The SITL camera's frames over MJPEG/HTTP on loopback, and the reader that takes them back.

`MjpegServer` serves `/stream.mjpg` (multipart/x-mixed-replace, one JPEG per part) and
`/frame.jpg` (the latest frame). Each JPEG carries its capture time in the header
`X-Capture-Time-Us`: integer microseconds on the autopilot's boot time base (the time base of
its ATTITUDE/LOCAL_POSITION_NED `time_boot_ms`), so a reader pairs each frame with the pose
interpolated at that instant.

Two ways to consume the stream, one code path in the service:
- `MjpegReader(url)` (from `companion.camera.mjpeg`, re-exported here): yields
  `(image, capture_time_s)` with the capture time from the header; the service reads it through
  `companion.camera.source.MjpegSource`.
- `cv2.VideoCapture(url)`: opens the same URL through OpenCV's FFmpeg backend and decodes the
  frames (as BGR), as it would a real IP camera; it cannot see the part headers, so frames read
  that way have no capture time (only a receive time).
"""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from types import TracebackType
from typing import Any
from urllib.parse import urlsplit

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.camera.mjpeg import CAPTURE_TIME_HEADER, MjpegReader
from companion.errors import ConfigError, InputError

__all__ = ["CAPTURE_TIME_HEADER", "MjpegReader", "MjpegServer", "publish_at_rate"]

BOUNDARY = "frame"

# A client whose socket accepts nothing for this long is dropped: long enough for a loaded
# machine, short enough that a dead client does not hold a thread.
CLIENT_SEND_TIMEOUT_S = 5.0
# How often a waiting stream handler re-checks for shutdown.
_WAIT_POLL_S = 0.2


@dataclass(frozen=True, slots=True)
class _Frame:
    seq: int
    jpeg: bytes
    capture_time_us: int


class _FrameSlot:
    """The newest encoded frame, shared by the publisher and every client (newest wins)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._frame: _Frame | None = None
        self._closed = False

    def put(self, jpeg: bytes, capture_time_us: int) -> int:
        with self._cond:
            seq = 1 if self._frame is None else self._frame.seq + 1
            self._frame = _Frame(seq, jpeg, capture_time_us)
            self._cond.notify_all()
            return seq

    def latest(self) -> _Frame | None:
        with self._cond:
            return self._frame

    def wait_newer(self, seq: int, timeout_s: float) -> _Frame | None:
        """The newest frame after `seq`, or None on timeout or when closed."""
        with self._cond:
            self._cond.wait_for(
                lambda: self._closed or (self._frame is not None and self._frame.seq > seq),
                timeout=timeout_s)
            if self._closed or self._frame is None or self._frame.seq <= seq:
                return None
            return self._frame

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        with self._cond:
            return self._closed


class _HttpServer(ThreadingHTTPServer):
    """One thread per client; server_close() joins them (block_on_close)."""

    daemon_threads = False
    block_on_close = True

    def __init__(self, address: tuple[str, int], slot: _FrameSlot) -> None:
        self.slot = slot
        self._clients: set[socket.socket] = set()
        self._clients_lock = threading.Lock()
        super().__init__(address, _Handler)

    def add_client(self, sock: socket.socket) -> None:
        with self._clients_lock:
            self._clients.add(sock)

    def remove_client(self, sock: socket.socket) -> None:
        with self._clients_lock:
            self._clients.discard(sock)

    def disconnect_clients(self) -> None:
        """Shut every client socket down, so a handler blocked in send() returns."""
        with self._clients_lock:
            clients = list(self._clients)
        for sock in clients:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)


class _Handler(BaseHTTPRequestHandler):
    server: _HttpServer
    timeout = CLIENT_SEND_TIMEOUT_S
    protocol_version = "HTTP/1.0"

    def setup(self) -> None:
        super().setup()
        self.server.add_client(self.connection)

    def finish(self) -> None:
        try:
            super().finish()
        except OSError:
            pass  # the client went away or stop() shut its socket
        finally:
            self.server.remove_client(self.connection)

    def log_message(self, format: str, *args: Any) -> None:
        """Silent: the SITL logs what matters itself."""

    def do_GET(self) -> None:
        path = urlsplit(self.path).path
        try:
            if path == "/stream.mjpg":
                self._stream()
            elif path == "/frame.jpg":
                self._single()
            else:
                self.send_error(404, "try /stream.mjpg or /frame.jpg")
        except OSError:
            pass  # broken pipe, reset, timeout, or stop(): end this client only

    def _single(self) -> None:
        frame = self.server.slot.latest()
        if frame is None:
            self.send_error(503, "no frame published yet")
            return
        self.send_response(200)
        self.send_header("Content-Type", "image/jpeg")
        self.send_header("Content-Length", str(len(frame.jpeg)))
        self.send_header(CAPTURE_TIME_HEADER, str(frame.capture_time_us))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(frame.jpeg)

    def _stream(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        slot = self.server.slot
        seq = 0
        while not slot.closed:
            frame = slot.wait_newer(seq, _WAIT_POLL_S)
            if frame is None:
                continue
            seq = frame.seq  # frames published while this client was sending are skipped
            head = (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                    f"Content-Length: {len(frame.jpeg)}\r\n"
                    f"{CAPTURE_TIME_HEADER}: {frame.capture_time_us}\r\n\r\n").encode("ascii")
            self.wfile.write(head + frame.jpeg + b"\r\n")


class MjpegServer:
    """Serves published frames as MJPEG over HTTP on loopback; publish() never blocks on I/O.

    The socket is bound at construction (port 0: a free port), so `url` is known before
    start(). Each client has its own thread and always gets the newest frame: a slow client
    skips frames, it never delays the publisher or the other clients.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, jpeg_quality: int = 90) -> None:
        if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535:
            raise ConfigError("camera.stream_port", f"must be an int in [0, 65535], got {port!r}")
        if (not isinstance(jpeg_quality, int) or isinstance(jpeg_quality, bool)
                or not 1 <= jpeg_quality <= 100):
            raise ConfigError("camera.jpeg_quality", f"must be in [1, 100], got {jpeg_quality!r}")
        self._slot = _FrameSlot()
        self._jpeg_quality = jpeg_quality
        try:
            self._httpd = _HttpServer((host, port), self._slot)
        except OSError as exc:
            raise ConfigError("camera.stream_port", f"cannot listen on {host}:{port}: {exc}") \
                from exc
        self._thread: threading.Thread | None = None
        self._stopped = False

    @property
    def host(self) -> str:
        """The address the server listens on."""
        return str(self._httpd.server_address[0])

    @property
    def port(self) -> int:
        """The TCP port the server listens on."""
        return int(self._httpd.server_address[1])

    @property
    def url(self) -> str:
        """The MJPEG stream's URL (what cv2.VideoCapture and MjpegReader open)."""
        return f"http://{self.host}:{self.port}/stream.mjpg"

    @property
    def frame_url(self) -> str:
        """The URL of the latest frame as one JPEG."""
        return f"http://{self.host}:{self.port}/frame.jpg"

    def start(self) -> MjpegServer:
        """Start serving in a background thread; returns self."""
        if self._stopped:
            raise InputError("MjpegServer cannot be restarted after stop()")
        if self._thread is None:
            self._thread = threading.Thread(target=self._httpd.serve_forever,
                                            kwargs={"poll_interval": _WAIT_POLL_S},
                                            name=f"mjpeg-server:{self.port}", daemon=True)
            self._thread.start()
        return self

    def publish(self, image: NDArray[np.uint8], capture_time_s: float) -> None:
        """Encode `image` (H, W) or (H, W, 3) uint8 as the newest frame, stamped capture_time_s.

        capture_time_s is on the autopilot's boot time base; it is sent as integer
        microseconds.
        """
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or not (
                image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))):
            raise InputError("image must be a uint8 array of shape (H, W) or (H, W, 3), got "
                             f"{getattr(image, 'dtype', type(image).__name__)} "
                             f"{getattr(image, 'shape', '')}")
        ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self._jpeg_quality])
        if not ok:
            raise InputError(f"JPEG encoding failed for an image of shape {image.shape}")
        self.publish_jpeg(encoded.tobytes(), capture_time_s)

    def publish_jpeg(self, jpeg: bytes, capture_time_s: float) -> None:
        """Serve already encoded (or deliberately garbled) JPEG bytes as the newest frame."""
        if (not isinstance(capture_time_s, int | float) or isinstance(capture_time_s, bool)
                or not math.isfinite(capture_time_s) or capture_time_s < 0.0):
            raise InputError(f"capture_time_s must be a finite number >= 0, "
                             f"got {capture_time_s!r}")
        self._slot.put(bytes(jpeg), round(capture_time_s * 1e6))

    def stop(self) -> None:
        """Stop serving: end every client, join all threads, close the socket. Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        self._slot.close()
        if self._thread is not None:
            self._httpd.shutdown()  # returns once serve_forever has left its loop
            self._thread.join()
        self._httpd.disconnect_clients()
        self._httpd.server_close()  # joins the client threads (block_on_close)

    def __enter__(self) -> MjpegServer:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


def publish_at_rate(server: MjpegServer, frames: list[NDArray[np.uint8]], fps: float,
                    stop: threading.Event, published: list[int]) -> None:
    """Publish frames round-robin at fps, stamped with time.monotonic(), until stop is set;
    published[0] counts them (a benchmark's camera, run in a thread)."""
    period_s, next_s, k = 1.0 / fps, time.monotonic(), 0
    while not stop.is_set():
        server.publish(frames[k % len(frames)], time.monotonic())
        published[0] += 1
        k += 1
        next_s += period_s
        stop.wait(max(next_s - time.monotonic(), 0.0))
