"""The autopilot's UDP link on loopback, with injectable faults (loss, latency, cuts).

Times are simulation seconds: a fault that lasts 5 s lasts 5 simulated seconds, whatever the
speed-up.
"""

from __future__ import annotations

import heapq
import select
import socket
from dataclasses import dataclass

import numpy as np

Address = tuple[str, int]

_MAX_DATAGRAM = 65535


@dataclass
class LinkFaults:
    """What the link does to packets now (mutable: tests and the fault schedule change it)."""

    loss_out: float = 0.0  # probability of dropping an autopilot -> client packet
    loss_in: float = 0.0  # probability of dropping a client -> autopilot packet
    latency_s: float = 0.0  # added one-way delay, both ways
    cut_until_s: float = -1.0  # nothing passes until this simulation time

    def cut(self, now_s: float) -> bool:
        """Whether the link is cut at now_s."""
        return now_s < self.cut_until_s


class UdpLink:
    """A UDP socket bound on loopback that talks to its remotes through the faults."""

    def __init__(
        self,
        remotes: list[Address],
        rng: np.random.Generator,
        bind: Address = ("127.0.0.1", 0),
        learn_remotes: bool = True,
    ) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._sock.bind(bind)
        self._remotes: list[Address] = list(remotes)
        self._learn = learn_remotes
        self._rng = rng
        self.faults = LinkFaults()
        self._outbox: list[tuple[float, int, bytes]] = []  # (due, seq, data)
        self._inbox: list[tuple[float, int, bytes, Address]] = []
        self._seq = 0
        self.sent = self.dropped_out = self.received = self.dropped_in = 0

    @property
    def address(self) -> Address:
        """Where the link listens."""
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    @property
    def remotes(self) -> list[Address]:
        """Where it sends."""
        return list(self._remotes)

    def send(self, data: bytes, now_s: float) -> None:
        """Send to every remote, unless the faults say otherwise."""
        if self.faults.cut(now_s) or self._rng.random() < self.faults.loss_out:
            self.dropped_out += 1
            return
        self._seq += 1
        heapq.heappush(self._outbox, (now_s + self.faults.latency_s, self._seq, data))
        self._flush_out(now_s)

    def receive(self, now_s: float, wait_wall_s: float = 0.0) -> list[tuple[bytes, Address]]:
        """The packets that have arrived and passed the faults (waits up to wait_wall_s)."""
        if wait_wall_s > 0.0 and not self._inbox:
            select.select([self._sock], [], [], wait_wall_s)
        while True:
            try:
                data, addr = self._sock.recvfrom(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionError:  # an ICMP port-unreachable from a gone remote
                continue
            address = (str(addr[0]), int(addr[1]))
            if self._learn and address not in self._remotes:
                self._remotes.append(address)
            if self.faults.cut(now_s) or self._rng.random() < self.faults.loss_in:
                self.dropped_in += 1
                continue
            self._seq += 1
            heapq.heappush(self._inbox, (now_s + self.faults.latency_s, self._seq, data, address))
        out: list[tuple[bytes, Address]] = []
        while self._inbox and self._inbox[0][0] <= now_s:
            _, _, data, address = heapq.heappop(self._inbox)
            self.received += 1
            out.append((data, address))
        self._flush_out(now_s)
        return out

    def _flush_out(self, now_s: float) -> None:
        while self._outbox and self._outbox[0][0] <= now_s:
            _, _, data = heapq.heappop(self._outbox)
            for remote in self._remotes:
                try:
                    self._sock.sendto(data, remote)
                except OSError:  # the remote is gone; UDP does not care
                    continue
            self.sent += 1

    def close(self) -> None:
        """Close the socket."""
        self._sock.close()


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port on host that nobody uses now (for tests and the demo)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])
