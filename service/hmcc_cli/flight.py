"""``hmcc flight FILE``: verify every pair of a flight, in this process's children or through a
running service, with a progress bar on a terminal.

The file is a batch body without its size limit (``images``: id -> ``{camera, pose,
keypoints}``, ``pairs``: ``[{id?, image1, image2, matches}]``, optional ``method``,
``params``, ``plane``), as JSON or as its MessagePack form with raw array buffers (a binary
flight file, :mod:`hmcc_schema.flight_file`; ``hmcc convert-flight`` writes one from JSON).
Each pair's outcome is one JSON line (``{"index", "id", "status", "result" | "error"}``) on
standard output or in ``--output``; a summary goes to standard error, with the CPU time of
this process and of its children (the serial share of the run).

Here, the children start first (when the file's pairs, counted without parsing it, are more
than :data:`~hmcc_worker.cutover.INPROCESS_MAX_PAIRS`): forked from a fork server that imports
and warms the core (started before this command's own imports where the file is big,
:mod:`.flight_args`), they start in the background while this process reads the flight once
(no Python object per number, in either format; every array is still checked here, so a bad
flight exits 2 before any pair is verified), writes what the children need to a shared file
(:mod:`hmcc_worker.shared_flight`) and hands its pairs to the children as index ranges; each
child reads its pairs' arrays from there and sends back each pair's whole output line, which
this process writes out a task at a time, as bytes (``--timings``: when each of these steps
ended, and this process's CPU time then: where the serial share goes).

A binary flight file is read in place (:class:`~hmcc_schema.flight_file.MappedFlightFile`):
mapped in memory, its MessagePack walked for where each array lies, each array checked there
(dtype, shape, keypoints' values, the matches' index range), nothing copied; the shared file
then holds the cameras, poses and where each array lies in the flight file, which each child
maps itself, copying out its own pairs' arrays. A binary file not plainly valid is parsed
whole, which says what is wrong; a JSON file (or standard input) is parsed whole, its arrays
written to the shared file. A binary file whose pairs are columns
(:mod:`hmcc_schema.flight_columns`) is read without Python work a pair: its pairs stay columns
(their image ids, and where each pair's matches start in one array of them all) through the
shared file to the children. A flight of at
most :data:`~hmcc_worker.cutover.INPROCESS_MAX_PAIRS` pairs is verified in this process
instead: starting the children costs more than they save (measured in
``benchmarks/results/flight.md``), and a crash then ends the command, not the service.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import os
import resource
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import msgpack
import numpy as np
import orjson
from pydantic import ValidationError
from tqdm import tqdm

from hmcc import InputError
from hmcc.flight import Flight
from hmcc.method_names import METHOD_NAMES as METHODS
from hmcc_schema import parse_batch, validation_issues
from hmcc_schema.columns import PairColumns, pairs_are_columns
from hmcc_schema.flight_columns import (
    column_rows,
    encode_flight_columns,
    read_columns_bytes,
    read_flight_columns,
)
from hmcc_schema.flight_file import MappedFlightFile, flight_media_type
from hmcc_schema.parse import MSGPACK
from hmcc_worker.cutover import INPROCESS_MAX_PAIRS
from hmcc_worker.outcomes import PairOutcome, flight_line, verify_flight_lines
from hmcc_worker.protocol import JobStatus

from .flight_args import add_arguments, stop_early
from .outputs import checked_output
from .plural import counted
from .where import service_error, service_errors

__all__ = ["INPROCESS_MAX_PAIRS", "add_arguments", "convert", "run"]


def run(args: argparse.Namespace) -> int:
    timeline = Timeline()
    timeline.mark("imports")
    output = None if args.output is None else checked_output(args.output, "--output")
    if args.output is not None and output is None:
        return 2
    try:
        mapped = None if args.flight == "-" or args.url else MappedFlightFile.open(args.flight)
        raw = b"" if mapped is not None else _read(args.flight)
    except OSError as e:
        print(f"error: {args.flight}: {e}", file=sys.stderr)
        return 2
    timeline.mark("read")
    if args.method and args.method not in METHODS:
        known = list(METHODS)
        print(f"error: --method: unknown method {args.method!r}; one of {known}", file=sys.stderr)
        return 2
    out: IO[bytes] = open(output, "wb") if output is not None else sys.stdout.buffer
    bar = tqdm(unit="pair", disable=not sys.stderr.isatty(), file=sys.stderr)
    t0 = time.perf_counter()
    counts = {"finished": 0, "failed": 0}
    pool = None
    columns = mapped is not None and pairs_are_columns(mapped.data)  # a binary file of columns
    pairs = mapped.pair_count() if mapped is not None else pair_estimate(raw)
    if not args.url and args.processes > 0 and pairs > args.in_process_max:
        pool = _early_pool(args.processes, timeline)
    else:
        stop_early()
    if mapped is not None and pool is None and not columns:  # verified here: as any file
        raw, mapped = _read(args.flight), None
    try:
        if args.url:
            with _collector_paused():  # the document is kept whole to the end
                doc = _document(raw)
            if doc is None:
                what = "a flight is a JSON or MessagePack object"
                print(f"error: {args.flight}: {what}", file=sys.stderr)
                return 2
            bar.total = len(doc["pairs"]) if isinstance(doc.get("pairs"), list) else 0
            for status, line in _remote(_overridden(doc, args), args, bar):
                counts[status] = counts.get(status, 0) + 1
                out.write(line + b"\n")
        else:
            with _collector_paused():
                if mapped is None:
                    flight = None
                elif columns:
                    flight = read_flight_columns(mapped)
                else:
                    flight = mapped.flight()
                if flight is None:  # not read in place: parsed whole (which says what is wrong)
                    raw = raw or _read(args.flight)
                    flight, mapped = read_columns_bytes(raw), None  # (from standard input)
                    if flight is None:
                        flight = parse_batch(raw, 10**9, flight_media_type(raw))
            flight = _overrides(flight, args)
            del raw
            timeline.mark("parsed")
            bar.total = len(flight.pairs)
            local = _local(flight, args.processes, bar, args.in_process_max, pool, timeline, mapped)
            for lines in local:
                if not counts["finished"] + counts["failed"]:
                    timeline.mark("first result")
                for part in lines:  # lines of one status (a line has no raw newline)
                    out.write(part.body)
                    key = "finished" if part.status is JobStatus.finished else "failed"
                    counts[key] += part.body.count(b"\n")
            timeline.mark("last result")
    except (ValidationError, InputError) as e:
        for issue in validation_issues(e):
            print(f"error: {issue.field}: {issue.reason}", file=sys.stderr)
        return 2
    except service_errors() as e:
        return service_error(e, args.url)
    finally:
        if pool is not None:
            pool.close(wait=False)
        bar.close()
        if output is not None:
            out.close()
        else:
            out.flush()
    elapsed = time.perf_counter() - t0
    total = sum(counts.values())
    here, children = _cpu_s(resource.RUSAGE_SELF), _children_cpu_s()
    print(
        f"{counted(total, 'pair')} in {elapsed:.1f} s ({total / max(elapsed, 1e-9):.0f} pairs/s): "
        f"{counts['finished']} finished, {counts['failed']} failed; CPU {here:.2f} s here, "
        f"{children:.2f} s in child processes",
        file=sys.stderr,
    )
    if args.timings:
        timeline.mark("exit")
        print(timeline.line(), file=sys.stderr)
        print(timeline.cpu_line(), file=sys.stderr)
    return 0


class Timeline:
    """When each step of the command ended, in seconds from this process's start (read from
    ``/proc/self/stat``; from the timeline's creation where there is none): the wall-clock
    timeline ``--timings`` prints."""

    def __init__(self) -> None:
        self._t0 = time.perf_counter() - _since_process_start()
        self._marks: dict[str, float] = {}
        self._cpu: dict[str, float] = {}
        self._lock = threading.Lock()

    def mark(self, step: str) -> None:
        """``step`` ended now (the first time only)."""
        with self._lock:
            if step not in self._marks:
                self._marks[step] = time.perf_counter() - self._t0
                self._cpu[step] = time.process_time()

    def marks(self) -> dict[str, float]:
        with self._lock:
            return dict(sorted(self._marks.items(), key=lambda kv: kv[1]))

    def line(self) -> str:
        steps = ", ".join(f"{step} {t:.2f}" for step, t in self.marks().items())
        return f"timeline (s from the process's start): {steps}"

    def cpu_line(self) -> str:
        """This process's CPU seconds (all its threads, not its children) when each step
        ended: where the serial share goes."""
        with self._lock:
            cpu = dict(self._cpu)
        steps = ", ".join(f"{step} {cpu[step]:.2f}" for step in self.marks())
        return f"CPU here (s from the process's start): {steps}"


@contextmanager
def _collector_paused() -> Iterator[None]:
    """Python's cyclic garbage collector off while the flight is read and parsed, and what was
    made by then frozen (:func:`gc.freeze`: later collections skip it). The parse makes objects
    a pair and an array (dicts, views, the core's pairs) that live until the end, and each
    collection they set off went through all those made before: 0.1 of the parse's 0.36 CPU s
    on the 18 283-pair benchmark flight."""
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        gc.enable()


def _since_process_start() -> float:
    """Seconds since this process started (0 where ``/proc`` does not tell)."""
    try:
        stat = Path("/proc/self/stat").read_text()
        started = int(stat.rsplit(")", 1)[1].split()[19]) / os.sysconf("SC_CLK_TCK")
        return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - started)
    except (OSError, ValueError, IndexError, AttributeError):
        return 0.0


def _read(flight: str) -> bytes:
    return sys.stdin.buffer.read() if flight == "-" else Path(flight).read_bytes()


def pair_estimate(raw: bytes) -> int:
    """About how many pairs the flight file ``raw`` has, without parsing it: how often a pair's
    ``image1`` key occurs (a quoted JSON string, or a MessagePack fixstr). It decides whether
    the children are started before the file is parsed; a wrong guess costs time, not
    results (a small flight is still verified here, a large one still by children)."""
    key = b'"image1"' if flight_media_type(raw) != MSGPACK else b"\xa6image1"
    return raw.count(key)


def _early_pool(processes: int, timeline: Timeline) -> Any:
    """A compute pool whose children start now, in the background, starting and warming while
    this process parses the file (marks "children warm" when each has run a first short
    task)."""
    from hmcc_worker.pool import ComputePool

    pool = ComputePool(processes, forked=True)

    def warm(started: Future[list[int]]) -> None:
        if not started.cancelled() and started.exception() is None and started.result():
            timeline.mark("children warm")

    pool.prestart().add_done_callback(warm)
    return pool


def _cpu_s(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def _children_cpu_s() -> float:
    """CPU seconds of the child processes (once the pool is closed): those waited for here,
    and the fork server's, with its children's (the compute pool's, forked from it)."""
    total = _cpu_s(resource.RUSAGE_CHILDREN)
    if "hmcc_worker.pool" in sys.modules:
        from hmcc_worker.pool import forkserver_cpu_s

        total += forkserver_cpu_s()
    return total


def _overrides(flight: Flight, args: argparse.Namespace) -> Flight:
    """``--method`` and ``--result`` over the file's."""
    if args.method:
        flight = dataclasses.replace(flight, method=args.method)
    if args.result:
        options = dataclasses.replace(flight.options, result=args.result)
        flight = dataclasses.replace(flight, options=options)
    return flight


def _overridden(doc: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    if args.method:
        doc["method"] = args.method
    if args.result:
        doc["params"] = {**(doc.get("params") or {}), "result": args.result}
    return doc


def _document(raw: bytes) -> dict[str, Any] | None:
    """A flight file as a document for the client (a binary file's arrays as ndarrays), or
    None when it is not an object."""
    try:
        if flight_media_type(raw) != MSGPACK:
            doc = orjson.loads(raw)
        else:
            doc = msgpack.unpackb(raw, raw=False, strict_map_key=True)
    except (ValueError, TypeError, msgpack.UnpackException):
        return None
    if not isinstance(doc, dict):
        return None
    if isinstance(doc.get("pairs"), dict):  # pairs as columns: as rows
        doc["pairs"] = column_rows(doc["pairs"])
    for image in (doc.get("images") or {}).values() if isinstance(doc.get("images"), dict) else ():
        _unbuffer(image, ("keypoints",))
    for pair in doc.get("pairs") or () if isinstance(doc.get("pairs"), list) else ():
        _unbuffer(pair, ("matches", "keypoints1", "keypoints2"))
    return doc


def _unbuffer(doc: Any, keys: tuple[str, ...]) -> None:
    """Raw buffers (``{dtype, shape, data}``) of ``doc[key]`` as ndarrays (left as they are when
    they do not read: the service then says why)."""
    if not isinstance(doc, dict):
        return
    for key in keys:
        value = doc.get(key)
        if isinstance(value, dict) and set(value) == {"dtype", "shape", "data"}:
            try:
                dtype = np.dtype(value["dtype"])
                doc[key] = np.frombuffer(value["data"], dtype=dtype).reshape(value["shape"])
            except (TypeError, ValueError):
                pass


def convert(args: argparse.Namespace) -> int:
    """``hmcc convert-flight IN OUT``: a JSON flight file as a binary one (or back, when OUT
    ends in ``.json``)."""
    from hmcc_schema.flight_file import encode_flight

    try:
        raw = sys.stdin.buffer.read() if args.input == "-" else Path(args.input).read_bytes()
    except OSError as e:
        print(f"error: {args.input}: {e}", file=sys.stderr)
        return 2
    try:
        doc = _document(raw)
    except InputError as e:
        print(f"error: {args.input}: {e.field}: {e.reason}", file=sys.stderr)
        return 2
    if (
        doc is None
        or not isinstance(doc.get("images"), dict)
        or not isinstance(doc.get("pairs"), list)
    ):
        print(f"error: {args.input}: a flight is an object with images and pairs", file=sys.stderr)
        return 2
    if str(args.output).endswith(".json"):
        if args.columns:
            print("error: --columns: a JSON flight file has its pairs as rows", file=sys.stderr)
            return 2
        data = orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY)
    elif args.columns:
        images, pairs = doc.pop("images"), doc.pop("pairs")
        try:
            data = encode_flight_columns(images, pairs, **doc)
        except ValueError as e:
            print(f"error: --columns: {e}", file=sys.stderr)
            return 2
    else:
        images, pairs = doc.pop("images"), doc.pop("pairs")
        data = encode_flight(images, pairs, **doc)
    Path(args.output).write_bytes(data)
    print(f"{args.output}: {len(data) / 2**20:.1f} MiB", file=sys.stderr)
    return 0


def _line(index: int, pair_id: str | None, status: str, key: str, body: Any) -> bytes:
    return orjson.dumps({"index": index, "id": pair_id, "status": status, key: body})


def _local(
    flight: Flight,
    processes: int,
    bar: tqdm[Any],
    in_process_max: int = INPROCESS_MAX_PAIRS,
    pool: Any = None,
    timeline: Timeline | None = None,
    mapped: MappedFlightFile | None = None,
) -> Iterator[list[PairOutcome]]:
    """Each task's outcomes as they finish, their bodies its whole lines in runs of one
    status (:func:`~hmcc_worker.outcomes.verify_flight_lines`): verified here when
    ``processes`` is 0 or the flight has at most ``in_process_max`` pairs, else by
    ``processes`` children reading the
    shared flight and encoding their lines (those of ``pool`` when given, started already; the
    caller closes it). ``mapped``: the file ``flight`` was read from in place (its arrays the
    children read from it; a flight so read is verified by children, whatever its size: its
    matches are not in the core's dtype, unless its pairs are columns, which give each pair's
    matches as the core's)."""
    core_dtype = mapped is None or isinstance(flight.pairs, PairColumns)
    if core_dtype and (processes <= 0 or len(flight.pairs) <= in_process_max):
        outcomes = verify_flight_lines(flight)
        bar.update(len(flight.pairs))
        yield outcomes
        return
    from hmcc_worker.pool import ComputePool
    from hmcc_worker.shared_flight import shared_flight

    own = pool is None
    if pool is None:
        pool = ComputePool(processes, forked=True)
    try:
        with shared_flight(flight, mapped) as shared:
            if timeline is not None:
                timeline.mark("shared file")
            for indices, lines in pool.map_tasks(shared, fn=verify_flight_lines, lost=_lost_line):
                bar.update(len(indices))
                yield lines
    finally:
        if own:
            pool.close(wait=False)


def _lost_line(single: Flight, outcome: PairOutcome) -> PairOutcome:
    """The line of a pair whose child was lost (``single``: the shared flight of that pair)."""
    index = getattr(single, "indices", (0,))[0]
    return flight_line(index, single.pairs[0].id, outcome)


def _remote(
    doc: dict[str, Any], args: argparse.Namespace, bar: tqdm[Any]
) -> Iterator[tuple[str, bytes]]:
    """Through the service's batch API: images once per batch, bodies in MessagePack."""
    from hmcc_client import HmccClient

    key = args.api_key or os.environ.get("HMCC_API_KEY")
    with HmccClient(args.url, api_key=key) as client:
        items = client.verify_flight(
            doc.get("images") or {},
            doc.get("pairs") or [],
            method=doc.get("method"),
            params=doc.get("params"),
            plane=doc.get("plane"),
            progress=lambda done, _: bar.update(done - bar.n),
            binary=not args.json,
        )
        for item in items:
            model = item.result or item.error
            body = None if model is None else model.to_dict()
            yield (
                item.status,
                _line(
                    item.index,
                    item.id,
                    item.status,
                    "result" if item.result is not None else "error",
                    body,
                ),
            )
