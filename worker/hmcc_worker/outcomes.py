"""What happened to each pair of a job: finished with a result, or failed with an error, each
encoded once, as JSON (a result the service keeps also as MessagePack).

The process that verifies a pair encodes its result (the core's, in the form its options ask
for) or its error (``{"code", "message", "issues"?}``); the API splices those bytes into its
answers without parsing them again. A result the service keeps is encoded twice, as JSON and
as MessagePack with its arrays (``inliers``, and ``matches`` where it has them) as raw
little-endian buffers (``{"dtype", "shape", "data"}``, the request bodies' form:
:func:`encode_result`), so that either kind of answer (``Accept``) is spliced from stored
bytes. Stored, an outcome is one status byte and its bytes (:meth:`PairOutcome.pack`,
:func:`unpack`, :func:`unpack_msgpack`): ``r`` and the result's JSON, ``e`` and the error's
JSON, ``m``, the JSON's length (4 bytes, little-endian), the result's JSON and its
MessagePack. Stage timings travel beside it for the metrics.
"""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import groupby
from typing import TYPE_CHECKING, Any

import msgpack
import numpy as np
import orjson
from pydantic import ValidationError

from hmcc import InputError
from hmcc.flight import Flight
from hmcc_schema import validation_issues
from hmcc_schema.flight_file import wire_array, wire_buffer

from .metrics import increments
from .protocol import ErrorCode, JobStatus

if TYPE_CHECKING:
    from hmcc import Verification

__all__ = [
    "PairOutcome",
    "StoredOutcomes",
    "crashed",
    "encode_result",
    "failed",
    "finished",
    "flight_line",
    "invalid",
    "timed_out",
    "unpack",
    "unpack_msgpack",
    "verify_flight",
    "verify_flight_lean",
    "verify_flight_lines",
    "verify_flight_stored",
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


#: The arrays of a result that MessagePack carries as raw buffers (integer indices).
RESULT_ARRAYS = ("matches", "inliers")


@dataclass(frozen=True)
class PairOutcome:
    """``status`` finished or failed; ``body`` the JSON of the result or of the error;
    ``msgpack`` the result's MessagePack (:func:`encode_result`), where it was made;
    ``timings_ms`` the stages' times and ``compute`` (their sum) of a finished pair, for the
    metrics."""

    status: JobStatus
    body: bytes
    timings_ms: dict[str, float] = field(default_factory=dict)
    msgpack: bytes | None = None

    def pack(self) -> bytes:
        """The stored form: a status byte, then the JSON (and the MessagePack, where made)."""
        if self.status is not JobStatus.finished:
            return b"e" + self.body
        if self.msgpack is None:
            return b"r" + self.body
        return b"m" + len(self.body).to_bytes(4, "little") + self.body + self.msgpack


def unpack(stored: bytes) -> tuple[JobStatus, bytes]:
    """``(finished | failed, result or error JSON)`` of a stored outcome."""
    kind = stored[:1]
    if kind == b"m":
        return JobStatus.finished, stored[5 : 5 + int.from_bytes(stored[1:5], "little")]
    return (JobStatus.finished if kind == b"r" else JobStatus.failed), stored[1:]


def unpack_msgpack(stored: bytes) -> tuple[JobStatus, memoryview | None]:
    """``(finished | failed, the result's MessagePack)`` of a stored outcome, a view of
    ``stored`` (not a copy); None where only JSON was stored (an error, or a result stored
    without it): :func:`unpack` has that."""
    if stored[:1] == b"m":
        return JobStatus.finished, memoryview(stored)[5 + int.from_bytes(stored[1:5], "little") :]
    return (JobStatus.finished if stored[:1] == b"r" else JobStatus.failed), None


def _plain(value: Any) -> Any:
    """numpy values for MessagePack, as JSON writes them (scalars as numbers, arrays as lists)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} cannot be packed")


def encode_result(doc: dict[str, Any]) -> bytes:
    """A result (``to_dict``'s keys, in its order) as MessagePack: the index arrays of
    :data:`RESULT_ARRAYS` (lists or ndarrays) as raw buffers, ``<i4`` when they fit (as a
    request's matches travel, :func:`hmcc_schema.flight_file.wire_array`), anything else as
    JSON has it."""
    doc = {
        k: wire_buffer(wire_array(v, "matches")) if k in RESULT_ARRAYS and v is not None else v
        for k, v in doc.items()
    }
    return msgpack.packb(doc, default=_plain)  # type: ignore[no-any-return]


def finished(
    verification: Verification, result: dict[str, Any] | None = None, binary: bool = False
) -> PairOutcome:
    """A verified pair's outcome: the JSON of ``result`` (by default the verification's, in
    the form its options ask for), with ``binary`` also its MessagePack (:func:`encode_result`),
    and the stage timings (with ``match``, the matcher's, for a pair that asked for
    matching)."""
    timings = {s.name: s.time_ms for s in verification.stages}
    if verification.matching is not None:
        timings["match"] = float(verification.matching["time_ms"])
    timings["compute"] = sum(timings.values())
    doc = verification.to_dict() if result is None else result
    body = orjson.dumps(doc, option=_NUMPY)
    packed = None
    if binary:
        if result is None:  # the verification's own arrays rather than its lists
            arrays = {"inliers": verification.inliers, "matches": verification.matches}
            doc = {k: arrays[k] if k in arrays else v for k, v in doc.items()}
        packed = encode_result(doc)
    return PairOutcome(JobStatus.finished, body, timings, packed)


def _finished(index: int, verification: Verification) -> PairOutcome:
    return finished(verification, binary=True)


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
    (default :func:`finished` with the MessagePack, as the service keeps it), for a caller
    that works on the result before it is encoded."""
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
    """:func:`verify_flight_lean` with the outcomes already the lines :func:`flight_line`
    writes, in order, so that the process collecting them only writes bytes: the lines of
    consecutive pairs of one status joined in one outcome (one for a task whose pairs all
    finished; count a run's lines by its newlines), as one object a pair cost that process
    0.07 of its 0.26 CPU s collecting the 18 283 pairs of the benchmark flight. The pairs'
    indices are the flight's own, or those of the whole flight for a shared one
    (``flight.indices``)."""
    indices = getattr(flight, "indices", None) or range(len(flight.pairs))
    outcomes = verify_flight(flight, _finished_lean)
    lines = [
        flight_line(i, pair.id, outcome)
        for i, pair, outcome in zip(indices, flight.pairs, outcomes, strict=True)
    ]
    return [
        PairOutcome(status, b"".join(line.body for line in run))
        for status, run in groupby(lines, key=lambda line: line.status)
    ]


@dataclass(frozen=True)
class StoredOutcomes:
    """A job's outcomes as the service keeps them, made in the process that verified them
    (:func:`verify_flight_stored`): each pair's stored form (:meth:`PairOutcome.pack`), how many
    failed, and the metrics' increments of its pairs (:func:`~hmcc_worker.metrics.increments`).
    The process that collects them stores them as they are: handing back each pair's
    :class:`PairOutcome` (a dataclass and a dict of timings a pair, unpickled there) cost the
    embedded API 0.1 of its CPU seconds on the 18 283 pairs of the benchmark flight."""

    packed: list[bytes]
    failed: int
    increments: dict[str, float]

    @classmethod
    def of(cls, outcomes: list[PairOutcome]) -> StoredOutcomes:
        failed = sum(o.status is JobStatus.failed for o in outcomes)
        return cls([o.pack() for o in outcomes], failed, increments(outcomes))


def verify_flight_stored(flight: Flight) -> StoredOutcomes:
    """:func:`verify_flight` as the service stores it (:class:`StoredOutcomes`)."""
    return StoredOutcomes.of(verify_flight(flight))
