"""Fixtures of the service's tests."""

from __future__ import annotations

import os

import pytest


@pytest.fixture
def hermetic_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """No REDIS_URL (the embedded queue) and no HMCC_* setting from the caller's shell."""
    for name in list(os.environ):
        if name == "REDIS_URL" or name.startswith("HMCC_"):
            monkeypatch.delenv(name)
