"""``hmcc flight``'s arguments, and its children started before the command's own imports.

The children of ``hmcc flight`` are forked from a fork server that imports and warms the core
(:mod:`hmcc_worker.forking`): some 2 s on 2 cores, longer than the command takes to import,
read and parse a binary flight file. Started first thing (:func:`start_early`, from the
package's ``__init__``, before it imports anything heavy), the warm-up runs beside all of that.
Whether the flight will be verified on children is known only once its file is read, so the
start is a guess from the command line and the file's size (:func:`starts_early`); when the
flight is then verified in the command's own process, the server is stopped at once
(:func:`hmcc_worker.forking.stop`). This module imports the standard library and two
modules that import nothing else (:mod:`hmcc_worker.cutover`, :mod:`.where`)."""

from __future__ import annotations

import argparse
import multiprocessing
import os
from collections.abc import Sequence

from hmcc_worker.cutover import INPROCESS_MAX_PAIRS

from .where import add_where_arguments

__all__ = ["EARLY_MIN_BYTES", "add_arguments", "start_early", "starts_early", "stop_early"]

#: A flight file at least this big starts the children before the command's imports: as a
#: binary file, the whole benchmark flight (about 730 matches a pair) takes 7.8 KiB a pair with
#: its images' keypoints, so 8 MiB is about :data:`~hmcc_worker.cutover.INPROCESS_MAX_PAIRS`
#: pairs (a part of it takes more a pair: its first 300 pairs and their images, 7.9 MiB). A
#: wrong guess costs CPU on an idle core, not time: the server is stopped once the file is read.
EARLY_MIN_BYTES = 8 * 2**20

# Whether :func:`start_early` started the fork server in this process.
_started = False


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("flight", help="flight file (JSON: images with keypoints, pairs), - = stdin")
    add_where_arguments(
        p, "child processes verifying pairs here (default: all cores; 0: in this process)"
    )
    p.add_argument("--method", help="override the file's method")
    p.add_argument(
        "--result",
        choices=["full", "inliers"],
        default=None,
        help="override params.result (inliers: inliers, model and time only)",
    )
    p.add_argument("--json", action="store_true", help="send JSON bodies (default MessagePack)")
    p.add_argument("-o", "--output", help="JSON lines here (default stdout)")
    p.add_argument(
        "--in-process-max",
        type=int,
        default=INPROCESS_MAX_PAIRS,
        metavar="PAIRS",
        help="verify a flight of at most this many pairs in this process, without children "
        f"(default {INPROCESS_MAX_PAIRS})",
    )
    p.add_argument(
        "--timings",
        action="store_true",
        help="also print when each step ended, in seconds from the start (read, parsed, "
        "children warm, shared file, first and last result, exit)",
    )


class _Quiet(argparse.ArgumentParser):
    """The command line read for a guess only: the real parser says what is wrong with it."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise ValueError(message)


def starts_early(argv: Sequence[str]) -> bool:
    """Whether ``hmcc flight ARGV`` starts its children before its imports: a file (not
    standard input) verified here (no ``--url``) on children (``--processes`` not 0), either of
    at least :data:`EARLY_MIN_BYTES` or with ``--in-process-max 0``. A command line that does
    not parse starts nothing."""
    parser = _Quiet(add_help=False)
    add_arguments(parser)
    try:
        args, _ = parser.parse_known_args(list(argv))
    except ValueError:
        return False
    if args.url or args.processes <= 0 or args.flight == "-":
        return False
    if args.in_process_max <= 0:
        return True
    try:
        return os.stat(args.flight).st_size >= EARLY_MIN_BYTES
    except (OSError, ValueError):
        return False


def start_early(argv: Sequence[str]) -> bool:
    """Start ``hmcc flight ARGV``'s fork server now when :func:`starts_early` says so, in the
    command's own process only; whether it was started."""
    global _started
    # A pool's child runs the main module again, handed this command line (multiprocessing's
    # spawn.prepare), under its own name: it starts nothing.
    if multiprocessing.current_process().name != "MainProcess" or not starts_early(argv):
        return False
    from hmcc_worker import forking

    _started = forking.start()
    return _started


def stop_early() -> None:
    """Stop the fork server :func:`start_early` started, if it did: the flight is verified
    in this process after all (the server's warm-up is cut short, not waited for)."""
    global _started
    if _started:
        from hmcc_worker import forking

        forking.stop()
        _started = False
