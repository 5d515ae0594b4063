"""Fixtures shared by the integration tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.integration.local_ray import local_ray


@pytest.fixture(scope="module")
def cluster() -> Iterator[str]:
    """One local Ray cluster for a test module's sweeps (start-up is the slow part on 2 CPUs)."""
    with local_ray() as address:
        yield address
