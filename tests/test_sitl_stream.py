"""The SITL's MJPEG stream: capture times end to end, OpenCV compatibility, clean shutdown."""

from __future__ import annotations

import socket
import threading
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from companion.errors import ConfigError, InputError
from companion.vision.camera import BodyPose, CameraModel
from sitl.camera import Renderer, Tag
from sitl.stream import CAPTURE_TIME_HEADER, MjpegReader, MjpegServer

ImageU8 = NDArray[np.uint8]


@pytest.fixture(scope="module")
def frames() -> list[ImageU8]:
    """Five rendered frames of a vehicle drifting east over two tags."""
    renderer = Renderer(CameraModel(), 3)
    tags = [Tag(1, 0.0, 0.0, 0.5), Tag(2, 2.0, 1.0, 0.5)]
    return [renderer.render(BodyPose.from_euler(0.1 * i, 0.0, 0.3 * i, -8.0), tags,
                            np.random.default_rng(i)) for i in range(5)]


def _mean_abs_diff(a: NDArray[np.generic] | None, b: ImageU8) -> float:
    assert a is not None
    return float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))))


def test_reader_gets_every_frame_with_its_capture_time_in_order(
        frames: list[ImageU8], no_thread_left: None) -> None:
    times_s = [12.000001, 12.1, 12.2, 12.300042, 1234567.891234]
    with MjpegServer() as server, MjpegReader(server.url) as reader:
        stream = iter(reader)
        received = []
        for image, t_s in zip(frames, times_s, strict=True):
            server.publish(image, t_s)  # lock step: the reader gets this frame next
            received.append(next(stream))
    assert [t for _, t in received] == [round(t * 1e6) / 1e6 for t in times_s]
    for (image, _), sent in zip(received, frames, strict=True):
        assert image.shape == sent.shape and image.dtype == np.uint8
        assert _mean_abs_diff(image, sent) < 4.0  # JPEG, quality 90, smooths the exposure noise
    assert reader.corrupt_frames == 0


def test_a_late_reader_starts_at_the_newest_frame(frames: list[ImageU8],
                                                  no_thread_left: None) -> None:
    with MjpegServer() as server:
        for i, image in enumerate(frames):
            server.publish(image, 5.0 + i)
        with MjpegReader(server.url) as reader:
            image, t_s = next(iter(reader))
    assert t_s == 9.0
    assert _mean_abs_diff(image, frames[-1]) < 4.0


def test_reader_ends_when_the_server_stops(frames: list[ImageU8], no_thread_left: None) -> None:
    server = MjpegServer().start()
    reader = MjpegReader(server.url)
    stream = iter(reader)
    server.publish(frames[0], 1.0)
    assert next(stream)[1] == 1.0
    server.stop()
    assert list(stream) == []
    with pytest.raises(ConnectionError):
        next(iter(MjpegReader(server.url, timeout_s=1.0)))


def test_close_from_another_thread_ends_a_waiting_reader(frames: list[ImageU8],
                                                         no_thread_left: None) -> None:
    with MjpegServer() as server:
        reader = MjpegReader(server.url, timeout_s=30.0)
        stream = iter(reader)
        server.publish(frames[0], 1.0)
        assert next(stream)[1] == 1.0
        closer = threading.Timer(0.05, reader.close)  # before or during the read: same result
        closer.start()
        start = time.perf_counter()
        assert list(stream) == []  # no new frame: it waits until close() cuts the socket
        assert time.perf_counter() - start < 10.0
        closer.join()


def test_opencv_videocapture_opens_the_stream(frames: list[ImageU8],
                                              no_thread_left: None) -> None:
    """cv2.VideoCapture decodes the frames (as BGR); it cannot see the capture-time header."""
    done = threading.Event()
    with MjpegServer() as server:
        def publish() -> None:
            i = 0
            while not done.is_set():
                server.publish(frames[0], 0.01 * i)
                i += 1
                done.wait(0.005)  # pace the publisher like a camera; not a test sleep

        publisher = threading.Thread(target=publish, name="test-publisher")
        publisher.start()
        try:
            capture = cv2.VideoCapture(server.url, cv2.CAP_FFMPEG,
                                       [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, 5000,
                                        cv2.CAP_PROP_READ_TIMEOUT_MSEC, 5000])
            try:
                assert capture.isOpened()
                decoded = []
                for _ in range(3):
                    ok, image = capture.read()
                    assert ok
                    decoded.append(image)
            finally:
                capture.release()
        finally:
            done.set()
            publisher.join()
    for image in decoded:
        assert image.shape == (480, 640, 3)
        assert _mean_abs_diff(image[:, :, 1], frames[0]) < 4.0


def test_single_frame_endpoint_and_errors(frames: list[ImageU8], no_thread_left: None) -> None:
    with MjpegServer() as server:
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(server.frame_url, timeout=5)
        assert info.value.code == 503
        info.value.close()
        server.publish(frames[2], 3.25)
        with urllib.request.urlopen(server.frame_url, timeout=5) as response:
            assert response.headers[CAPTURE_TIME_HEADER] == "3250000"
            assert response.headers["Content-Type"] == "image/jpeg"
            image = cv2.imdecode(np.frombuffer(response.read(), np.uint8), cv2.IMREAD_UNCHANGED)
        assert _mean_abs_diff(image, frames[2]) < 4.0
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(server.url.replace("stream.mjpg", "nothing"), timeout=5)
        assert info.value.code == 404
        info.value.close()


def test_a_stalled_client_blocks_neither_publisher_nor_others_nor_stop(
        no_thread_left: None) -> None:
    rng = np.random.default_rng(0)
    noise = [rng.integers(0, 256, (720, 1280), dtype=np.uint8) for _ in range(3)]  # ~1 MB JPEGs
    server = MjpegServer().start()
    stalled = socket.socket()
    try:
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.connect((server.host, server.port))
        stalled.sendall(b"GET /stream.mjpg HTTP/1.0\r\n\r\n")
        server.publish(noise[0], 0.0)
        assert stalled.recv(12).startswith(b"HTTP/1.0 200")  # it is streaming; now it stalls
        with MjpegReader(server.url) as reader:
            stream = iter(reader)
            assert next(stream)[1] == 0.0
            for i in range(1, 41):  # ~40 MB: far more than the stalled socket's buffers hold
                server.publish(noise[i % 3], float(i))
            received = [0.0]
            while received[-1] != 40.0:  # the other reader still reaches the newest frame
                received.append(next(stream)[1])
        assert received == sorted(set(received))
        start = time.perf_counter()
        server.stop()
        assert time.perf_counter() - start < 3.0  # stop cuts the stalled client off
    finally:
        server.stop()
        stalled.close()


def test_stop_is_idempotent_and_frees_the_port(no_thread_left: None) -> None:
    server = MjpegServer()
    assert server.url.startswith(f"http://127.0.0.1:{server.port}/")
    server.stop()  # never started
    server.stop()
    with pytest.raises(InputError, match="restart"):
        server.start()
    with MjpegServer() as running:
        port = running.port
    with socket.socket() as probe:
        assert probe.connect_ex(("127.0.0.1", port)) != 0


def test_publish_rejects_bad_frames(no_thread_left: None) -> None:
    with MjpegServer() as server:
        with pytest.raises(InputError, match="uint8"):
            server.publish(np.zeros((4, 4), dtype=np.float32), 0.0)
        with pytest.raises(InputError, match="capture_time_s"):
            server.publish(np.zeros((4, 4), dtype=np.uint8), float("nan"))
    with pytest.raises(ConfigError, match="jpeg_quality"):
        MjpegServer(jpeg_quality=0)
    with pytest.raises(ConfigError, match="url"):
        MjpegReader("rtsp://127.0.0.1/x")


def _one_shot_server(payload: bytes) -> tuple[str, threading.Thread, socket.socket]:
    """A loopback server that answers one request with `payload` and closes."""
    listener = socket.create_server(("127.0.0.1", 0))

    def serve() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.recv(4096)
            conn.sendall(payload)

    thread = threading.Thread(target=serve, name="test-one-shot")
    thread.start()
    return f"http://127.0.0.1:{listener.getsockname()[1]}/stream.mjpg", thread, listener


def _part(body: bytes, extra: str) -> bytes:
    return (f"--b\r\nContent-Type: image/jpeg\r\nContent-Length: {len(body)}\r\n{extra}\r\n"
            .encode() + body + b"\r\n")


def test_reader_skips_corrupt_parts_and_rejects_parts_without_time(
        frames: list[ImageU8], no_thread_left: None) -> None:
    good = cv2.imencode(".jpg", frames[0])[1].tobytes()
    head = b"HTTP/1.0 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=b\r\n\r\n"
    url, thread, listener = _one_shot_server(
        head + _part(b"not a jpeg", "X-Capture-Time-Us: 1\r\n")
        + _part(good, "X-Capture-Time-Us: 2\r\n") + b"--b--\r\n")
    try:
        reader = MjpegReader(url)
        got = [t for _, t in reader]
        assert got == [2e-6] and reader.corrupt_frames == 1
    finally:
        thread.join()
        listener.close()
    url, thread, listener = _one_shot_server(head + _part(good, ""))
    try:
        with pytest.raises(InputError, match=CAPTURE_TIME_HEADER):
            next(iter(MjpegReader(url)))
    finally:
        thread.join()
        listener.close()
