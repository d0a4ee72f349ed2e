"""systemd's notify protocol: READY, WATCHDOG and STATUS datagrams to $NOTIFY_SOCKET.

`Notifier.from_environment()` is silent when the service is not started by systemd (no
NOTIFY_SOCKET). The watchdog interval is half of $WATCHDOG_USEC, as sd_watchdog_enabled(3)
advises, and only when $WATCHDOG_PID is unset or names this process. The protocol is one
datagram of `KEY=VALUE` lines on a Unix socket; a leading `@` in the address is Linux's
abstract namespace.
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Mapping

__all__ = ["Notifier"]


class Notifier:
    """Sends notify datagrams to one socket address (None: does nothing)."""

    def __init__(self, address: str | None, watchdog_usec: int | None = None) -> None:
        self.address = address
        self.watchdog_interval_s = None if not watchdog_usec else watchdog_usec / 2e6
        self._sock: socket.socket | None = None
        if address:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)

    @staticmethod
    def from_environment(environ: Mapping[str, str] = os.environ) -> Notifier:
        """The notifier systemd asked for, or a silent one."""
        usec = environ.get("WATCHDOG_USEC", "")
        pid = environ.get("WATCHDOG_PID", "")
        ours = not pid or pid == str(os.getpid())
        watchdog = int(usec) if usec.isdigit() and ours else None
        return Notifier(environ.get("NOTIFY_SOCKET") or None, watchdog)

    def _send(self, message: str) -> None:
        if self._sock is None or self.address is None:
            return
        target = "\0" + self.address[1:] if self.address.startswith("@") else self.address
        with contextlib.suppress(OSError):  # systemd gone or the socket full: carry on
            self._sock.sendto(message.encode(), target)

    def ready(self, status: str) -> None:
        """READY=1: the service is connected and working."""
        self._send(f"READY=1\nSTATUS={status}")

    def watchdog(self) -> None:
        """WATCHDOG=1: the main loop and the pipeline are alive."""
        self._send("WATCHDOG=1")

    def status(self, text: str) -> None:
        """STATUS=text, shown by `systemctl status`."""
        self._send(f"STATUS={text}")

    def stopping(self) -> None:
        """STOPPING=1: the service is shutting down on purpose."""
        self._send("STOPPING=1")

    def close(self) -> None:
        """Close the socket."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
