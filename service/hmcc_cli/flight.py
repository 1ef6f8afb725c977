"""``hmcc flight FILE``: verify every pair of a flight, in this process's children or through a
running service, with a progress bar on a terminal.

The file is a batch body without its size limit (``images``: id -> ``{camera, pose,
keypoints}``, ``pairs``: ``[{id?, image1, image2, matches}]``, optional ``method``,
``params``, ``plane``). Each pair's outcome is one JSON line (``{"index", "id", "status",
"result" | "error"}``) on standard output or in ``--output``; a summary goes to standard error.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import orjson
from pydantic import ValidationError
from tqdm import tqdm

from hmcc import InputError
from hmcc_schema import parse_batch, validation_issues
from hmcc_worker.outcomes import unpack

from .outputs import checked_output
from .plural import counted
from .where import add_where_arguments, service_error, service_errors

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("flight", help="flight file (JSON: images with keypoints, pairs), - = stdin")
    add_where_arguments(p, "child processes verifying pairs here (default: all cores)")
    p.add_argument("--method", help="override the file's method")
    p.add_argument(
        "--result",
        choices=["full", "inliers"],
        default=None,
        help="override params.result (inliers: inliers, model and time only)",
    )
    p.add_argument("--json", action="store_true", help="send JSON bodies (default MessagePack)")
    p.add_argument("-o", "--output", help="JSON lines here (default stdout)")


def run(args: argparse.Namespace) -> int:
    output = None if args.output is None else checked_output(args.output, "--output")
    if args.output is not None and output is None:
        return 2
    try:
        raw = sys.stdin.buffer.read() if args.flight == "-" else Path(args.flight).read_bytes()
        doc = orjson.loads(raw)
    except (OSError, orjson.JSONDecodeError) as e:
        print(f"error: {args.flight}: {e}", file=sys.stderr)
        return 2
    if not isinstance(doc, dict):
        print(f"error: {args.flight}: a flight is a JSON object", file=sys.stderr)
        return 2
    if args.method:
        doc["method"] = args.method
    if args.result:
        doc["params"] = {**(doc.get("params") or {}), "result": args.result}
    pairs: list[Any] = doc["pairs"] if isinstance(doc.get("pairs"), list) else []
    out: IO[bytes] = open(output, "wb") if output is not None else sys.stdout.buffer
    bar = tqdm(total=len(pairs), unit="pair", disable=not sys.stderr.isatty(), file=sys.stderr)
    t0 = time.perf_counter()
    counts = {"finished": 0, "failed": 0}
    try:
        lines = _remote(doc, args, bar) if args.url else _local(doc, args.processes, bar)
        for status, line in lines:
            counts[status] = counts.get(status, 0) + 1
            out.write(line + b"\n")
    except (ValidationError, InputError) as e:
        for issue in validation_issues(e):
            print(f"error: {issue.field}: {issue.reason}", file=sys.stderr)
        return 2
    except service_errors() as e:
        return service_error(e, args.url)
    finally:
        bar.close()
        if output is not None:
            out.close()
    elapsed = time.perf_counter() - t0
    total = sum(counts.values())
    print(
        f"{counted(total, 'pair')} in {elapsed:.1f} s ({total / max(elapsed, 1e-9):.0f} pairs/s): "
        f"{counts['finished']} finished, {counts['failed']} failed",
        file=sys.stderr,
    )
    return 0


def _line(index: int, pair_id: str | None, status: str, key: str, body: Any) -> bytes:
    return orjson.dumps({"index": index, "id": pair_id, "status": status, key: body})


def _local(doc: dict[str, Any], processes: int, bar: tqdm[Any]) -> Iterator[tuple[str, bytes]]:
    """Parsed once here, verified by ``processes`` children."""
    from hmcc_worker.pool import ComputePool

    flight = parse_batch(doc, max_pairs=10**9)
    pool = ComputePool(processes)
    try:
        for index, outcome in pool.map_flight(flight):
            status, body = unpack(outcome.pack())
            key = "result" if status.value == "finished" else "error"
            bar.update()
            yield (
                status.value,
                _line(index, flight.pairs[index].id, status.value, key, orjson.Fragment(body)),
            )
    finally:
        pool.close(wait=False)


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
