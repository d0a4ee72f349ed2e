"""The view's web server: the page's static files, the scene, and its step messages, read-only.

`ViewServer` runs inside the caller's asyncio event loop (aiohttp). Live, `publish` hands each
connected page the newest step message over a WebSocket (`/api/stream`); a replay serves its
recorded steps by index (`/api/step/K`). An operator's orthophoto, made once at start-up, is
served as a PNG (`/api/orthophoto.png`; 404 when there is none). Nothing it serves changes
anything: only GET (and HEAD) routes exist, requests carry no body.

Security: with a token (`view.token_file`), every route but the static files needs it (the
query's `token=` or an `Authorization: Bearer` header), compared in constant time and never
logged (the access log is off, since the query carries it). No CORS header is sent, and a
WebSocket from a page of another origin is refused. At most `max_clients` pages stream at once.
Each page gets only the newest message: a message not yet sent is replaced by the next, never
queued; a page whose socket takes longer than SEND_TIMEOUT_S to accept one, or holds more than
MAX_BUFFERED_BYTES unsent, or that answers no ping within HEARTBEAT_S / 2, is dropped.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import os
import socket
import stat
import time
import zlib
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from aiohttp import WSMsgType, web

from companion.errors import ConfigError

__all__ = ["SEND_TIMEOUT_S", "ServerStats", "ViewServer", "load_token"]

SEND_TIMEOUT_S = 2.0  # a page that takes longer to accept one message is dropped
MAX_BUFFERED_BYTES = 1_000_000  # unsent bytes a page may hold before it is dropped
SOCKET_SEND_BUFFER = 256 * 1024  # the kernel's send buffer for each page
HEARTBEAT_S = 10.0  # a page that answers no ping within half of this is dropped too
MAX_INCOMING_BYTES = 4096  # what a page may send in one WebSocket message (nothing is read)
MAX_TOKEN_BYTES = 4096
TOKEN_KEY = "view.token_file"
STATIC = resources.files("companion.view") / "static"
SECURITY_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",  # the page's address may carry the token
    "Cache-Control": "no-store",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; "
                               "connect-src 'self'; style-src 'self'; frame-ancestors 'none'",
}


def load_token(path: Path) -> str:
    """The access token in path (its first line), or ConfigError naming view.token_file: a
    file that is missing, empty, too long, or readable by group or others is refused."""
    def refuse(problem: str) -> ConfigError:
        return ConfigError(TOKEN_KEY, f"{path}: {problem}")

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    except FileNotFoundError:
        raise refuse("no such file") from None
    except OSError as exc:
        raise refuse(f"cannot open it: {exc.strerror}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise refuse("is not a regular file")
        mode = stat.S_IMODE(info.st_mode)
        if mode & 0o077:
            raise refuse(f"mode {mode:04o} lets group or others read the access token; "
                         "chmod 600 it")
        data = os.read(fd, MAX_TOKEN_BYTES + 1)
    finally:
        os.close(fd)
    if len(data) > MAX_TOKEN_BYTES:
        raise refuse(f"longer than {MAX_TOKEN_BYTES} bytes: not a token file")
    try:
        lines = data.decode("ascii").strip().splitlines()
    except UnicodeDecodeError:
        raise refuse("is not ASCII text") from None
    token = lines[0].strip() if lines else ""
    if len(token) < 16:
        raise refuse("holds no token of at least 16 characters")
    return token


@dataclass
class ServerStats:
    """What the server did: pages streaming now, and counts since it started."""

    clients: int = 0
    connected: int = 0
    refused_token: int = 0
    refused_full: int = 0
    refused_origin: int = 0
    dropped_slow: int = 0  # pages that stopped reading (or answering pings), cut off
    messages_sent: int = 0
    messages_skipped: int = 0  # replaced by a newer one before a page took them
    send_cpu_s: float = 0.0  # this thread's CPU time in sending (waits for a socket included)


@dataclass(eq=False)
class _Client:
    ws: web.WebSocketResponse
    transport: asyncio.Transport | None
    pending: str | None = None
    ready: asyncio.Event = field(default_factory=asyncio.Event)

    def offer(self, text: str) -> bool:
        """Make text the next message; True if it replaced one not yet sent."""
        replaced = self.pending is not None
        self.pending = text
        self.ready.set()
        return replaced


class ViewServer:
    """The page, its scene and its messages, served on bind:port within the running loop."""

    def __init__(self, scene: dict[str, Any], *, bind: str = "127.0.0.1", port: int = 0,
                 token: str | None = None, max_clients: int = 8,
                 steps: Sequence[bytes] | None = None,
                 orthophoto_png: bytes | None = None,
                 log: Callable[[str], None] = lambda _: None,
                 address_keys: tuple[str, str] = ("view.bind", "view.port")) -> None:
        self.scene = scene
        self.bind, self.port = bind, port
        self._token = token
        self.max_clients = max_clients
        self._steps = steps  # a replay's messages, each zlib-compressed JSON
        self._orthophoto = orthophoto_png
        self._log = log
        self._address_keys = address_keys  # what a bad address is reported under
        self.stats = ServerStats()
        self._clients: set[_Client] = set()
        self._senders: set[asyncio.Task[None]] = set()
        self._latest: str | None = None
        self._runner: web.AppRunner | None = None

    @property
    def url(self) -> str:
        """The page's address (without the token)."""
        host = f"[{self.bind}]" if ":" in self.bind else self.bind
        return f"http://{host}:{self.port}/"

    # -- life --------------------------------------------------------------------------------

    async def start(self) -> None:
        """Listen; with port 0 on a free port, then self.port is the one taken. An address
        that cannot be taken raises ConfigError naming view.bind or view.port (address_keys)."""
        app = web.Application(middlewares=[self._headers], client_max_size=1024)
        app.router.add_get("/", self._index)
        app.router.add_get("/api/scene", self._scene)
        app.router.add_get("/api/stream", self._stream)
        app.router.add_get("/api/step/{index}", self._step)
        app.router.add_get("/api/orthophoto.png", self._orthophoto_png)
        app.router.add_static("/static/", Path(str(STATIC)), follow_symlinks=False)
        runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await runner.setup()
        site = web.TCPSite(runner, self.bind, self.port, reuse_address=True)
        try:
            await site.start()
        except OSError as exc:
            await runner.cleanup()
            bind_key, port_key = self._address_keys
            key = bind_key if exc.errno in (99, -2, -3, -5) else port_key
            raise ConfigError(key, f"cannot listen on {self.bind}:{self.port}: "
                                   f"{exc.strerror or exc}") from None
        self._runner = runner
        server = site._server  # the port taken when 0 was asked for
        sockets = getattr(server, "sockets", None) or []
        if sockets:
            self.port = int(sockets[0].getsockname()[1])

    async def close(self, drain_s: float = 0.5) -> None:
        """Give each page up to drain_s to take its last message, then close everything."""
        if self._runner is None:
            return
        if self._clients and any(c.pending is not None for c in self._clients):
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(drain_s):
                    while any(c.pending is not None for c in self._clients):
                        await asyncio.sleep(0.02)
        for client in list(self._clients):
            self._drop(client)
        for task in list(self._senders):
            task.cancel()
        runner, self._runner = self._runner, None
        await runner.cleanup()

    # -- live --------------------------------------------------------------------------------

    @property
    def has_clients(self) -> bool:
        """Whether any page streams now (no page: no message need be made)."""
        return bool(self._clients)

    def publish(self, text: str) -> None:
        """The newest step message (JSON) for every streaming page, replacing any unsent."""
        self._latest = text
        for client in self._clients:
            self.stats.messages_skipped += client.offer(text)

    # -- requests ----------------------------------------------------------------------------

    @web.middleware
    async def _headers(self, request: web.Request,
                       handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
                       ) -> web.StreamResponse:
        response = await handler(request)
        if not response.prepared:
            response.headers.update(SECURITY_HEADERS)
        return response

    def _authorized(self, request: web.Request) -> bool:
        if self._token is None:
            return True
        given = request.query.get("token", "")
        header = request.headers.get("Authorization", "")
        if not given and header.startswith("Bearer "):
            given = header.removeprefix("Bearer ").strip()
        ok = hmac.compare_digest(given.encode("utf-8", "replace"), self._token.encode())
        self.stats.refused_token += not ok
        return ok

    def _refuse(self) -> web.Response:
        return web.Response(status=401, text="this page needs its access token: open it with "
                                             "?token=... as given by the operator\n")

    async def _index(self, request: web.Request) -> web.StreamResponse:
        if not self._authorized(request):
            return self._refuse()
        return web.FileResponse(Path(str(STATIC / "index.html")))

    async def _scene(self, request: web.Request) -> web.Response:
        if not self._authorized(request):
            return self._refuse()
        return web.json_response(self.scene)

    async def _step(self, request: web.Request) -> web.Response:
        if not self._authorized(request):
            return self._refuse()
        if self._steps is None:
            return web.Response(status=404, text="a live view has no recorded steps\n")
        try:
            index = int(request.match_info["index"])
        except ValueError:
            return web.Response(status=400, text="the step index must be a whole number\n")
        if not 0 <= index < len(self._steps):
            return web.Response(status=404, text=f"no step {index}: the run has "
                                                 f"{len(self._steps)}\n")
        return web.Response(body=zlib.decompress(self._steps[index]),
                            content_type="application/json")

    async def _orthophoto_png(self, request: web.Request) -> web.Response:
        if not self._authorized(request):
            return self._refuse()
        if self._orthophoto is None:
            return web.Response(status=404, text="no orthophoto is configured\n")
        return web.Response(body=self._orthophoto, content_type="image/png")

    def _same_origin(self, request: web.Request) -> bool:
        origin = request.headers.get("Origin")
        if origin is None:
            return True  # not a browser page's request (a script's)
        ok = urlsplit(origin).netloc == request.host
        self.stats.refused_origin += not ok
        return ok

    async def _stream(self, request: web.Request) -> web.StreamResponse:
        if not self._authorized(request):
            return self._refuse()
        if not self._same_origin(request):
            return web.Response(status=403, text="a page of another origin may not stream\n")
        if len(self._clients) >= self.max_clients:
            self.stats.refused_full += 1
            return web.Response(status=503, text=f"{self.max_clients} pages are streaming "
                                                 "already (view.max_clients)\n")
        ws = web.WebSocketResponse(max_msg_size=MAX_INCOMING_BYTES, compress=False,
                                   heartbeat=HEARTBEAT_S)
        await ws.prepare(request)
        transport = request.transport
        sock = None if transport is None else transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_SEND_BUFFER)
        client = _Client(ws, transport if isinstance(transport, asyncio.Transport) else None)
        self._clients.add(client)
        self.stats.clients = len(self._clients)
        self.stats.connected += 1
        await ws.send_str(json.dumps(self.scene, separators=(",", ":")))
        if self._latest is not None:
            client.offer(self._latest)
        sender = asyncio.create_task(self._send_loop(client))
        self._senders.add(sender)
        sender.add_done_callback(self._senders.discard)
        try:
            async for msg in ws:  # a page sends nothing that is read; pings are answered
                if msg.type is WSMsgType.ERROR:
                    break
        finally:
            if isinstance(ws.exception(), TimeoutError):  # it answered no ping: not reading
                self._drop(client, slow=True)
            self._forget(client)
            sender.cancel()
        return ws

    async def _send_loop(self, client: _Client) -> None:
        """Send the client its newest message whenever there is one; drop it when slow."""
        while True:
            await client.ready.wait()
            client.ready.clear()
            text, client.pending = client.pending, None
            if text is None:
                continue
            transport = client.transport
            if transport is not None and transport.get_write_buffer_size() > MAX_BUFFERED_BYTES:
                self._drop(client, slow=True)
                return
            started = time.thread_time()
            try:
                async with asyncio.timeout(SEND_TIMEOUT_S):
                    await client.ws.send_str(text)
            except TimeoutError:
                self._drop(client, slow=True)
                return
            except (ConnectionError, RuntimeError):
                self._drop(client)
                return
            finally:
                self.stats.send_cpu_s += time.thread_time() - started
            self.stats.messages_sent += 1

    def _forget(self, client: _Client) -> None:
        self._clients.discard(client)
        self.stats.clients = len(self._clients)

    def _drop(self, client: _Client, slow: bool = False) -> None:
        """Cut a page off at once (its socket aborted: nothing more is buffered for it)."""
        if slow and client in self._clients:
            self.stats.dropped_slow += 1
            self._log("view: a page that stopped reading was dropped")
        self._forget(client)
        client.pending = None
        if client.transport is not None:
            client.transport.abort()
