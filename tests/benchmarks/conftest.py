"""Fixtures of the benchmark smoke tests."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def sift_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One ``--cache`` folder for the quick runs of bench_real and bench_colmap: both extract and
    match the same five images at 1000 px (``bench_colmap.raw_database``, keyed by the images'
    names and sizes, pycolmap's version and the size), so the second reads the database the
    first built, the very file the same code would build again. Fresh for every session."""
    return tmp_path_factory.mktemp("sift-cache")
