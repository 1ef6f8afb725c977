"""What happened to each pair of a job: finished with a result, or failed with an error, each
encoded once as JSON.

The process that verifies a pair encodes its result (the core's, in the form its options ask
for) or its error (``{"code", "message", "issues"?}``); the API splices those bytes into its
answers without parsing them again. Stored, an outcome is one status byte (``r`` result,
``e`` error) and the JSON (:meth:`PairOutcome.pack`, :func:`unpack`). Stage timings travel
beside it for the metrics.
"""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import orjson
from pydantic import ValidationError

from hmcc import InputError
from hmcc.flight import Flight
from hmcc_schema import validation_issues

from .protocol import ErrorCode, JobStatus

if TYPE_CHECKING:
    from hmcc import Verification

__all__ = [
    "PairOutcome",
    "crashed",
    "failed",
    "finished",
    "flight_line",
    "invalid",
    "timed_out",
    "unpack",
    "verify_flight",
    "verify_flight_lean",
    "verify_flight_lines",
]

log = logging.getLogger("hmcc.worker")
_NUMPY = orjson.OPT_SERIALIZE_NUMPY

#: Fault injection for the tests of crash isolation (no valid input crashes the core, so a
#: crash has to be made): a pair whose ``id`` is this value (``*``: every pair) kills the
#: process verifying it with SIGSEGV, as a native crash would. Unset in production.
FAULT_CRASH_PAIR_ID = "HMCC_FAULT_CRASH_PAIR_ID"
#: Fault injection for the tests that need a job still running (kill its worker, cancel
#: behind it, stop its worker): a pair whose ``id`` is this value (``*``: every pair, as a
#: single-pair request has no id) sleeps ``HMCC_FAULT_SLOW_S`` seconds (default 5) before it
#: is verified, however fast the machine. Unset in production.
FAULT_SLOW_PAIR_ID = "HMCC_FAULT_SLOW_PAIR_ID"
FAULT_SLOW_S = "HMCC_FAULT_SLOW_S"


@dataclass(frozen=True)
class PairOutcome:
    """``status`` finished or failed; ``body`` the JSON of the result or of the error;
    ``timings_ms`` the stages' times and ``compute`` (their sum) of a finished pair, for the
    metrics."""

    status: JobStatus
    body: bytes
    timings_ms: dict[str, float] = field(default_factory=dict)

    def pack(self) -> bytes:
        """The stored form: a status byte, then the JSON."""
        return (b"r" if self.status is JobStatus.finished else b"e") + self.body


def unpack(stored: bytes) -> tuple[JobStatus, bytes]:
    """``(finished | failed, result or error JSON)`` of a stored outcome."""
    status = JobStatus.finished if stored[:1] == b"r" else JobStatus.failed
    return status, stored[1:]


def finished(verification: Verification, result: dict[str, Any] | None = None) -> PairOutcome:
    """A verified pair's outcome: the JSON of ``result`` (by default the verification's, in
    the form its options ask for) and the stage timings (with ``match``, the matcher's, for
    a pair that asked for matching)."""
    timings = {s.name: s.time_ms for s in verification.stages}
    if verification.matching is not None:
        timings["match"] = float(verification.matching["time_ms"])
    timings["compute"] = sum(timings.values())
    body = orjson.dumps(verification.to_dict() if result is None else result, option=_NUMPY)
    return PairOutcome(JobStatus.finished, body, timings)


def _finished(index: int, verification: Verification) -> PairOutcome:
    return finished(verification)


def failed(
    code: ErrorCode, message: str, issues: list[dict[str, str]] | None = None
) -> PairOutcome:
    error: dict[str, Any] = {"code": code.value, "message": message}
    if issues is not None:
        error["issues"] = issues
    return PairOutcome(JobStatus.failed, orjson.dumps(error))


def invalid(e: ValidationError | InputError) -> PairOutcome:
    issues = validation_issues(e)
    return failed(
        ErrorCode.invalid_input,
        "; ".join(f"{i.field}: {i.reason}" for i in issues[:5]),
        [i.model_dump() for i in issues],
    )


def crashed(exitcode: int | None) -> PairOutcome:
    """The pair killed the process verifying it (a native crash, or the system killed it)."""
    how = "ended unexpectedly"
    if exitcode is not None and exitcode < 0:
        try:
            how = f"was killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            how = f"was killed by signal {-exitcode}"
    elif exitcode is not None:
        how = f"exited with status {exitcode}"
    return failed(
        ErrorCode.worker_crashed,
        f"the process verifying this pair {how}; the pair is not retried (the service goes on)",
    )


def timed_out(timeout_s: float) -> PairOutcome:
    return failed(
        ErrorCode.timeout, f"the pair took longer than {timeout_s:g} s (HMCC_JOB_TIMEOUT_S)"
    )


def verify_flight(
    flight: Flight, finish: Callable[[int, Verification], PairOutcome] | None = None
) -> list[PairOutcome]:
    """Every pair of ``flight``, in order. Input only the core can refuse (cameras 1000 km
    apart, too few matches for the model) is that pair's outcome; so is a bug, logged: the
    other pairs go on. ``finish(index, verification)`` makes a verified pair's outcome
    (default :func:`finished`), for a caller that works on the result before it is encoded."""
    if finish is None:
        finish = _finished
    crash_on = os.environ.get(FAULT_CRASH_PAIR_ID)
    slow_on = os.environ.get(FAULT_SLOW_PAIR_ID)
    outcomes = []
    for i in range(len(flight.pairs)):
        if crash_on is not None and crash_on in ("*", flight.pairs[i].id):
            os.kill(os.getpid(), signal.SIGSEGV)
        if slow_on is not None and slow_on in ("*", flight.pairs[i].id):
            time.sleep(float(os.environ.get(FAULT_SLOW_S, "5")))
        try:
            outcomes.append(finish(i, flight.verify(i)))
        except InputError as e:
            outcomes.append(invalid(e))
        except Exception:
            log.exception("verifying a pair failed")
            outcomes.append(failed(ErrorCode.internal_error, "verifying this pair failed"))
    return outcomes


def _finished_lean(index: int, verification: Verification) -> PairOutcome:
    body = orjson.dumps(verification.to_dict(), option=_NUMPY)
    return PairOutcome(JobStatus.finished, body)


def verify_flight_lean(flight: Flight) -> list[PairOutcome]:
    """:func:`verify_flight` without the stage timings (a caller that keeps no metrics: each
    pair's timings would be a dict pickled back to it)."""
    return verify_flight(flight, _finished_lean)


def flight_line(index: int, pair_id: str | None, outcome: PairOutcome) -> PairOutcome:
    """``outcome`` of pair ``index`` as one line of ``hmcc flight``'s output, its body the
    whole line, newline included: ``{"index", "id", "status", "result" | "error"}``."""
    key = "result" if outcome.status is JobStatus.finished else "error"
    doc: dict[str, Any] = {"index": index, "id": pair_id, "status": outcome.status.value}
    doc[key] = orjson.Fragment(outcome.body)
    return PairOutcome(outcome.status, orjson.dumps(doc, option=orjson.OPT_APPEND_NEWLINE))


def verify_flight_lines(flight: Flight) -> list[PairOutcome]:
    """:func:`verify_flight_lean` with each outcome already the line :func:`flight_line`
    writes, so that the process collecting them only writes bytes. The pairs' indices are the
    flight's own, or those of the whole flight for a shared one (``flight.indices``)."""
    indices = getattr(flight, "indices", None) or range(len(flight.pairs))
    outcomes = verify_flight(flight, _finished_lean)
    return [
        flight_line(i, pair.id, outcome)
        for i, pair, outcome in zip(indices, flight.pairs, outcomes, strict=True)
    ]
