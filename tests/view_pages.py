"""Browsers on the operator's page, in a process of their own: `python -m tests.view_pages URL N`.

Opens N pages of URL in one headless Chromium, then a WebSocket client that never reads (a
frozen phone), and waits until every page says its data is stale (the mission is over). It
prints one JSON line: each page's last step and whether it showed the stale banner. It runs on
one core at the lowest CPU priority, as browsers on other devices, and outside the service's
process, so it never holds the service's interpreter lock.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import sys
from urllib.parse import urlsplit

from tests.browser import chromium


def stalled_client(url: str) -> socket.socket:
    """A WebSocket client that opens the stream and then never reads."""
    parts = urlsplit(url)
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((parts.hostname or "127.0.0.1", parts.port or 80))
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall((f"GET /api/stream HTTP/1.1\r\nHost: {parts.netloc}\r\nUpgrade: websocket\r\n"
                  f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                  "Sec-WebSocket-Version: 13\r\n\r\n").encode())
    assert sock.recv(12) == b"HTTP/1.1 101"
    return sock


def main(url: str, count: int) -> dict[str, list[int] | list[bool]]:
    """Watch url with count pages until the stream stops; what they showed."""
    os.nice(19)
    os.sched_setaffinity(0, {max(os.sched_getaffinity(0))})
    with chromium(800, 600) as context:
        pages = [context.new_page() for _ in range(count)]
        for page in pages:
            page.goto(url)
        for page in pages:
            page.wait_for_selector("body[data-seq]", timeout=120_000)
        stalled = stalled_client(url)
        try:
            for page in pages:  # until the mission is over and the stream stops
                page.wait_for_selector("#stale", state="visible", timeout=600_000)
        finally:
            stalled.close()
        return {"last_seq": [int(p.get_attribute("body", "data-seq") or 0) for p in pages],
                "stale_at_end": [p.locator("#stale").is_visible() for p in pages]}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], int(sys.argv[2]))), flush=True)
