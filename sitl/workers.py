"""Daemon threads that run until their stop event is set: how the SITL's parts start and stop."""

from __future__ import annotations

import threading
from collections.abc import Callable

__all__ = ["Workers"]

_JOIN_WALL_S = 5.0


class Workers:
    """Named daemon threads sharing one stop event (`stopping`, which their loops watch)."""

    def __init__(self) -> None:
        self.stopping = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self, *targets: tuple[str, Callable[[], None]]) -> None:
        """Clear the stop event and run each (name, target) in a daemon thread."""
        self.stopping.clear()
        for name, target in targets:
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        """Set the stop event and wait up to 5 s for each thread. Idempotent."""
        self.stopping.set()
        for thread in self._threads:
            thread.join(timeout=_JOIN_WALL_S)
        self._threads.clear()
