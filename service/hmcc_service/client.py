"""The service's client moved to its own distribution, ``hmcc-client`` (``client/`` in this
repository, package :mod:`hmcc_client`), which installs without the core. This module
re-exports it for code that imported it from here; new code imports ``hmcc_client``."""

from __future__ import annotations

from hmcc_client import (
    MAX_WAIT_S,
    AsyncHmccClient,
    Batch,
    BatchItem,
    HmccClient,
    HmccError,
    Issue,
    Job,
    Limits,
    Pair,
)

__all__ = [
    "MAX_WAIT_S",
    "AsyncHmccClient",
    "Batch",
    "BatchItem",
    "HmccClient",
    "HmccError",
    "Issue",
    "Job",
    "Limits",
    "Pair",
]
