"""Fixtures shared by the test modules."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from service_harness import FakeServiceManager


@pytest.fixture
def manager() -> Iterator[FakeServiceManager]:
    """A fake service manager (``$NOTIFY_SOCKET``) for a daemon subprocess; closed after."""
    m = FakeServiceManager()
    yield m
    m.close()
