"""Fixtures of the benchmark smoke tests."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def sift_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One ``--cache`` folder for the quick runs of bench_real, bench_colmap and bench_match:
    all three take COLMAP's SIFT of the same five images at 1000 px
    (``bench_colmap.colmap_database``, keyed by the images' names and sizes, pycolmap's version
    and the size; the matched database is a copy of the features one, matched), so the first
    to run extracts and the others read the very files the same code would build again.
    Fresh for every session."""
    return tmp_path_factory.mktemp("sift-cache")
