"""The view's server on loopback: token, origin, client bound, newest-only delivery, slow pages."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import socket
import zlib
from collections.abc import Awaitable, Callable
from pathlib import Path

import aiohttp
import pytest

import companion.view.server as server_module
from companion.errors import ConfigError
from companion.view.server import ViewServer, load_token

TOKEN = "s3cret-token-for-the-tests-0123456789"
SCENE = {"type": "scene", "mode": "live", "rate_hz": 2.0}


def run(coro: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(coro(), 60.0))


async def started(**kwargs: object) -> ViewServer:
    server = ViewServer(SCENE, bind="127.0.0.1", port=0, **kwargs)  # type: ignore[arg-type]
    await server.start()
    return server


def test_the_token_is_required_and_compared_whole() -> None:
    async def body() -> None:
        server = await started(token=TOKEN)
        try:
            async with aiohttp.ClientSession() as s:
                base = server.url
                for path in ("", "api/scene", "api/stream", "api/step/0"):
                    async with s.get(base + path) as r:
                        assert r.status == 401, path
                    async with s.get(base + path, params={"token": TOKEN[:-1]}) as r:
                        assert r.status == 401, path
                    async with s.get(base + path, params={"token": TOKEN + "x"}) as r:
                        assert r.status == 401, path
                async with s.get(base + "api/scene", params={"token": TOKEN}) as r:
                    assert r.status == 200
                    assert await r.json() == SCENE
                    assert "Access-Control-Allow-Origin" not in r.headers
                    assert r.headers["Referrer-Policy"] == "no-referrer"
                async with s.get(base + "api/scene",
                                 headers={"Authorization": f"Bearer {TOKEN}"}) as r:
                    assert r.status == 200
                async with s.get(base, params={"token": TOKEN}) as r:
                    assert r.status == 200
                    assert "data-track-id" not in await r.text()  # rows are made by the script
                async with s.get(base + "static/view.js") as r:  # no data in the static files
                    assert r.status == 200
                async with s.get(base + "static/../server.py") as r:
                    assert r.status in (403, 404)
            assert server.stats.refused_token >= 12
        finally:
            await server.close()

    run(body)


def test_nothing_can_be_changed() -> None:
    async def body() -> None:
        server = await started()
        try:
            async with aiohttp.ClientSession() as s:
                for method in ("POST", "PUT", "DELETE", "PATCH"):
                    async with s.request(method, server.url + "api/scene", data=b"x") as r:
                        assert r.status == 405, method
        finally:
            await server.close()

    run(body)


def test_a_page_of_another_origin_may_not_stream_and_pages_are_bounded() -> None:
    async def body() -> None:
        server = await started(max_clients=2)
        try:
            async with aiohttp.ClientSession() as s:
                url = server.url + "api/stream"
                with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
                    await s.ws_connect(url, origin="http://evil.example")
                assert refused.value.status == 403
                a = await s.ws_connect(url, origin=server.url.rstrip("/"))
                b = await s.ws_connect(url)
                with pytest.raises(aiohttp.WSServerHandshakeError) as full:
                    await s.ws_connect(url)
                assert full.value.status == 503
                assert server.stats.refused_full == 1
                assert json.loads((await a.receive()).data) == SCENE
                await a.close()
                await b.close()
        finally:
            await server.close()

    run(body)


def test_a_page_gets_the_newest_message_not_a_backlog() -> None:
    async def body() -> None:
        server = await started()
        try:
            async with aiohttp.ClientSession() as s:
                ws = await s.ws_connect(server.url + "api/stream")
                assert json.loads((await ws.receive()).data)["type"] == "scene"
                for seq in range(1, 200):  # published faster than any page reads
                    server.publish(json.dumps({"type": "step", "seq": seq}))
                last = 0
                while last < 199:
                    last = json.loads((await ws.receive(timeout=10)).data)["seq"]
                assert server.stats.messages_sent < 199
                assert server.stats.messages_skipped > 0
                await ws.close()
        finally:
            await server.close()

    run(body)


def test_a_page_that_stops_reading_is_dropped() -> None:
    async def body() -> None:
        server = await started()
        loop = asyncio.get_running_loop()
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.setblocking(False)
        try:
            await loop.sock_connect(sock, ("127.0.0.1", server.port))
            key = base64.b64encode(os.urandom(16)).decode()
            await loop.sock_sendall(sock, (
                f"GET /api/stream HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n"
                "Upgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
            reply = await loop.sock_recv(sock, 1024)
            assert reply.startswith(b"HTTP/1.1 101"), reply
            assert server.stats.clients == 1
            big = json.dumps({"type": "step", "pad": "x" * 200_000})
            async with asyncio.timeout(30):  # never read again: the page must be cut off
                while server.stats.dropped_slow == 0:
                    server.publish(big)
                    await asyncio.sleep(0.01)
            assert server.stats.clients == 0
        finally:
            sock.close()
            await server.close()

    run(body)


def test_a_page_that_answers_no_ping_is_dropped(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(server_module, "HEARTBEAT_S", 0.5)

    async def body() -> None:
        server = await started()
        try:
            async with aiohttp.ClientSession() as s:
                ws = await s.ws_connect(server.url + "api/stream", autoping=False)
                async with asyncio.timeout(10):  # small messages, read by nobody, no pong
                    while server.stats.clients:
                        server.publish("{}")
                        await asyncio.sleep(0.05)
                assert server.stats.dropped_slow == 1
                await ws.close()
        finally:
            await server.close()

    run(body)


def test_a_replay_serves_its_steps_by_index() -> None:
    async def body() -> None:
        steps = [zlib.compress(json.dumps({"type": "step", "seq": k + 1}).encode())
                 for k in range(3)]
        server = await started(steps=steps)
        try:
            async with aiohttp.ClientSession() as s:
                async with s.get(server.url + "api/step/2") as r:
                    assert (await r.json())["seq"] == 3
                for bad, status in (("3", 404), ("-1", 404), ("x", 400)):
                    async with s.get(server.url + f"api/step/{bad}") as r:
                        assert r.status == status, bad
        finally:
            await server.close()

    run(body)


def test_a_taken_port_is_a_clear_error() -> None:
    async def body() -> None:
        first = await started()
        try:
            second = ViewServer(SCENE, bind="127.0.0.1", port=first.port)
            with pytest.raises(ConfigError, match=r"view\.port.*cannot listen"):
                await second.start()
        finally:
            await first.close()

    run(body)


def test_token_files_are_checked(tmp_path: Path) -> None:
    path = tmp_path / "token"
    with pytest.raises(ConfigError, match=r"view\.token_file.*no such file"):
        load_token(path)
    path.write_text(TOKEN + "\n")
    path.chmod(0o644)
    with pytest.raises(ConfigError, match=r"view\.token_file.*chmod 600"):
        load_token(path)
    path.chmod(0o600)
    assert load_token(path) == TOKEN
    path.write_text("short\n")
    with pytest.raises(ConfigError, match="at least 16"):
        load_token(path)


def test_the_orthophoto_is_served_with_the_token_and_only_when_there_is_one() -> None:
    png = b"\x89PNG\r\n\x1a\n" + bytes(range(256))  # the server serves the bytes it was given

    async def body() -> None:
        with_photo = await started(token=TOKEN, orthophoto_png=png)
        without = await started()
        try:
            async with aiohttp.ClientSession() as s:
                url = with_photo.url + "api/orthophoto.png"
                async with s.get(url) as r:
                    assert r.status == 401
                async with s.get(url, params={"token": TOKEN}) as r:
                    assert r.status == 200
                    assert r.headers["Content-Type"] == "image/png"
                    assert "Access-Control-Allow-Origin" not in r.headers
                    assert await r.read() == png
                async with s.post(url, params={"token": TOKEN}, data=b"x") as r:
                    assert r.status == 405
                async with s.get(without.url + "api/orthophoto.png") as r:
                    assert r.status == 404
        finally:
            await with_photo.close()
            await without.close()

    run(body)
