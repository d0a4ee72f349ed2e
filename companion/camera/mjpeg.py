"""Multipart MJPEG over HTTP with per-frame capture times: the stdlib reader.

A stream is `multipart/x-mixed-replace`, one JPEG per part; each part carries its capture time
in the header `X-Capture-Time-Us`: integer microseconds on the autopilot's boot time base. The
SITL's MjpegServer serves such a stream; `MjpegReader` reads it (the SITL re-exports it).
"""

from __future__ import annotations

import contextlib
import http.client
import math
import socket
import threading
from collections.abc import Iterator
from types import TracebackType
from urllib.parse import urlsplit

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError, InputError

__all__ = ["CAPTURE_TIME_HEADER", "MjpegReader"]

CAPTURE_TIME_HEADER = "X-Capture-Time-Us"


class MjpegReader:
    """A multipart MJPEG stream over HTTP, yielding (image, capture_time_s) per part.

    Reads `/stream.mjpg` of an MjpegServer (or any multipart MJPEG stream whose parts carry
    X-Capture-Time-Us) with the stdlib. Images come back as the JPEG holds them: (H, W) uint8
    for the SITL's grayscale frames. Parts whose JPEG does not decode are skipped and counted
    in `corrupt_frames`. A malformed stream raises InputError; a refused or timed-out
    connection raises the OSError (ConnectionError, TimeoutError) from the socket.
    Iteration ends when the server closes the stream.
    """

    def __init__(self, url: str, timeout_s: float = 5.0) -> None:
        parts = urlsplit(url)
        if parts.scheme != "http" or not parts.hostname:
            raise ConfigError("camera.url", f"must be an http:// URL, got {url!r}")
        if not isinstance(timeout_s, int | float) or not 0.0 < timeout_s < math.inf:
            raise ConfigError("camera.timeout_s", f"must be a number > 0, got {timeout_s!r}")
        self.url = url
        self.timeout_s = float(timeout_s)
        self.corrupt_frames = 0
        self._host = parts.hostname
        self._port = parts.port or 80
        self._path = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._closes = 0  # close() calls: a generator created before one does not connect

    def __iter__(self) -> Iterator[tuple[NDArray[np.uint8], float]]:
        return self.frames()

    def frames(self) -> Iterator[tuple[NDArray[np.uint8], float]]:
        """Yield (image, capture_time_s) per part in stream order; connects at the first next()."""
        with self._lock:
            return self._frames(self._closes)

    def _frames(self, closes: int) -> Iterator[tuple[NDArray[np.uint8], float]]:
        conn = http.client.HTTPConnection(self._host, self._port, timeout=self.timeout_s)
        response: http.client.HTTPResponse | None = None
        try:
            conn.connect()
            with self._lock:
                if self._closes != closes:
                    return  # close() came before the socket existed
                previous, self._sock = self._sock, conn.sock
            _shutdown(previous)  # one stream at a time per reader
            conn.request("GET", self._path)
            response = conn.getresponse()
            if response.status != 200:
                raise InputError(f"{self.url}: HTTP {response.status} {response.reason}")
            boundary = _boundary(response.getheader("Content-Type", ""))
            if boundary is None:
                raise InputError(f"{self.url}: not a multipart stream (Content-Type "
                                 f"{response.getheader('Content-Type')!r})")
            while True:
                part = _read_part(response, boundary)
                if part is None:
                    return
                headers, body = part
                image = _decode(body)
                if image is None:
                    self.corrupt_frames += 1
                    continue
                yield image, _capture_time_s(headers)
        finally:
            if response is not None:
                response.close()
            conn.close()

    def close(self) -> None:
        """End the stream: a frames() generator, even one blocked (or still connecting) in
        another thread, stops at its next read."""
        with self._lock:
            self._closes += 1
            sock, self._sock = self._sock, None
        _shutdown(sock)

    def __enter__(self) -> MjpegReader:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _shutdown(sock: socket.socket | None) -> None:
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)


def _boundary(content_type: str) -> str | None:
    """The boundary of a multipart/x-mixed-replace Content-Type, or None."""
    kind, _, params = content_type.partition(";")
    if kind.strip().lower() != "multipart/x-mixed-replace":
        return None
    for param in params.split(";"):
        name, _, value = param.strip().partition("=")
        if name.strip().lower() == "boundary" and value.strip():
            return value.strip().strip('"').removeprefix("--")
    return None


_MAX_HEADER_LINE = 4096
_MAX_PART_BYTES = 64 * 1024 * 1024


def _read_part(response: http.client.HTTPResponse,
               boundary: str) -> tuple[dict[str, str], bytes] | None:
    """The next part's (lower-case headers, body), or None at the end of the stream."""
    delimiter = f"--{boundary}".encode("ascii")
    while True:  # skip the CRLF after the previous body and any preamble
        line = response.readline(_MAX_HEADER_LINE)
        if not line:
            return None
        stripped = line.strip()
        if stripped == delimiter + b"--":
            return None
        if stripped == delimiter:
            break
    headers: dict[str, str] = {}
    while True:
        line = response.readline(_MAX_HEADER_LINE)
        if not line:
            return None
        if not line.strip():
            break
        name, sep, value = line.decode("latin-1").partition(":")
        if not sep:
            raise InputError(f"malformed part header line {line!r}")
        headers[name.strip().lower()] = value.strip()
    try:
        length = int(headers["content-length"])
    except (KeyError, ValueError) as exc:
        raise InputError(f"part without a valid Content-Length: {headers}") from exc
    if not 0 <= length <= _MAX_PART_BYTES:
        raise InputError(f"part Content-Length {length} out of range")
    body = response.read(length)
    if len(body) < length:
        return None  # the stream ended mid-part
    return headers, body


def _capture_time_s(headers: dict[str, str]) -> float:
    value = headers.get(CAPTURE_TIME_HEADER.lower())
    if value is None:
        raise InputError(f"part without {CAPTURE_TIME_HEADER}: cannot pair it with a pose")
    try:
        return int(value) / 1e6
    except ValueError as exc:
        raise InputError(f"{CAPTURE_TIME_HEADER} is not an integer: {value!r}") from exc


def _decode(body: bytes) -> NDArray[np.uint8] | None:
    """The image of a whole JPEG; None for a broken one (no end-of-image marker: cut short or
    garbled, which OpenCV would still half-decode into a picture of noise)."""
    if not body.rstrip(b"\x00\r\n").endswith(b"\xff\xd9"):
        return None
    image = cv2.imdecode(np.frombuffer(body, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    return np.asarray(image, dtype=np.uint8)
