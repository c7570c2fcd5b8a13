"""Fixtures of the webhook tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.interop_helpers import Receiver


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    """A webhook receiver of the test's own (a real HTTP server on a loopback port), closed after it."""
    made = Receiver()
    yield made
    made.close()
