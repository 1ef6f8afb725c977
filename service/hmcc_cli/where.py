"""Where a command verifies its pairs: here, on child processes, or through a running service
(``--url``, ``--api-key``); the arguments ``hmcc flight`` and ``hmcc colmap`` share."""

from __future__ import annotations

import argparse
import os
import sys

__all__ = ["add_where_arguments", "service_error", "service_errors"]


def add_where_arguments(p: argparse.ArgumentParser, processes_help: str) -> None:
    """``--url`` or ``--processes`` (default: all cores), and ``--api-key``."""
    where = p.add_mutually_exclusive_group()
    where.add_argument("--url", help="verify through this running service (default: here)")
    where.add_argument("--processes", type=int, default=os.cpu_count() or 1, help=processes_help)
    p.add_argument("--api-key", default=None, help="X-API-Key (default $HMCC_API_KEY)")


def service_errors() -> tuple[type[BaseException], ...]:
    """What verifying through a service can raise besides the caller's own input errors
    (imported when asked: every ``hmcc`` command builds the parser that imports this module,
    and only ``--url`` needs the client)."""
    import httpx

    from hmcc_client import HmccError

    return (HmccError, httpx.TransportError, TimeoutError)


def service_error(e: BaseException, url: str | None) -> int:
    """One line (and the field issues of a 422) for what the service answered or why it could
    not be reached; the exit code: 2 when it refused the caller's input (4xx), else 1."""
    from hmcc_client import HmccError

    if isinstance(e, HmccError):
        print(f"error: {url} answered {e.status} {e.code}: {e.message}", file=sys.stderr)
        for issue in e.issues[:20]:
            print(f"error: {issue.field}: {issue.reason}", file=sys.stderr)
        return 2 if 400 <= e.status < 500 else 1
    print(f"error: {url}: {e or type(e).__name__}", file=sys.stderr)
    return 1
