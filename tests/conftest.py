"""Fixtures shared by the test files."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.mavlink_client import Client


@pytest.fixture
def client() -> Iterator[Client]:
    """A pymavlink ground station on a free loopback port, closed afterwards."""
    c = Client()
    yield c
    c.close()
