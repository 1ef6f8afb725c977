"""Where a command verifies its pairs: here, on child processes, or through a running service
(``--url``, ``--api-key``); the arguments ``hmcc flight`` and ``hmcc colmap`` share."""

from __future__ import annotations

import argparse
import os

__all__ = ["add_where_arguments"]


def add_where_arguments(p: argparse.ArgumentParser, processes_help: str) -> None:
    """``--url`` or ``--processes`` (default: all cores), and ``--api-key``."""
    where = p.add_mutually_exclusive_group()
    where.add_argument("--url", help="verify through this running service (default: here)")
    where.add_argument("--processes", type=int, default=os.cpu_count() or 1, help=processes_help)
    p.add_argument("--api-key", default=None, help="X-API-Key (default $HMCC_API_KEY)")
