"""Robot models shared by the core tests (each takes seconds to build: once per session)."""

from __future__ import annotations

import pytest

from damon_ros.core.robot import Robot


@pytest.fixture(scope="session")
def mesh() -> Robot:
    return Robot("mesh")


@pytest.fixture(scope="session")
def fast() -> Robot:
    return Robot("fast")
