"""Fixtures shared by the test files; the session's figures folder (sitl/figures.py)."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from sitl.figures import FIGURES_DIR_ENV
from tests.mavlink_client import Client

ROOT = Path(__file__).resolve().parent.parent


def pytest_configure(config: pytest.Config) -> None:
    """Figures go to the checkout's out/reliability (for `make reliability`) unless set."""
    os.environ.setdefault(FIGURES_DIR_ENV, str(ROOT / "out" / "reliability"))


@pytest.fixture
def client() -> Iterator[Client]:
    """A pymavlink ground station on a free loopback port, closed afterwards."""
    c = Client()
    yield c
    c.close()


@pytest.fixture
def no_thread_left() -> Iterator[None]:
    """Fail if the test leaves a thread running."""
    before = set(threading.enumerate())
    yield
    left = [t for t in threading.enumerate() if t not in before and t.is_alive()]
    assert not left, f"threads left running: {left}"
