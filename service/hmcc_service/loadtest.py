"""``hmcc loadtest``: load a running service on this machine and print what it sustained.

A few simulated pairs (``--matches`` matches each, ``--outlier-ratio`` of them outliers) are
built and JSON-encoded once; ``--concurrency`` asyncio workers then send
``POST /v1/verifications?wait=60`` with them in turn until ``--count`` requests have been sent
or ``--duration`` seconds have passed (requests in flight then finish). Printed: throughput
(finished pairs per second of wall time), latency p50/p95/p99 (ms, the whole HTTP exchange
seen by the client), the service overhead p50 (latency minus the result's
``timings_ms.total``, the stages' sum), and how many requests finished, failed (the job
failed), did not finish within the 60 s wait, or got an HTTP error (by status; transport
errors by name).

Only loopback URLs are accepted (127.0.0.0/8, ::1, localhost): this is a tool for measuring
one's own deployment, not for loading someone else's.

Exit codes: 0 every request finished, 1 any failure or error, 2 bad arguments.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import math
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

if TYPE_CHECKING:  # httpx and asyncio load when a load test runs, not with the hmcc command
    import httpx

__all__ = [
    "LoadStats",
    "add_arguments",
    "check_url",
    "is_loopback_url",
    "main",
    "make_bodies",
    "percentile",
    "run_load",
]

MAX_CONCURRENCY = 64
MAX_COUNT = 100_000
MAX_DURATION_S = 600.0
MAX_MATCHES = 100_000
#: ``?wait=`` of every request (the service's maximum), seconds.
WAIT_S = 60.0


def add_arguments(lt: argparse.ArgumentParser) -> None:
    """The options of ``hmcc loadtest`` (its limits are this module's)."""
    lt.add_argument(
        "--url", default="http://127.0.0.1:8000", help="service URL; loopback hosts only"
    )
    lt.add_argument(
        "--concurrency", type=int, default=4, help=f"requests in flight (1-{MAX_CONCURRENCY})"
    )
    lt.add_argument(
        "--count",
        type=int,
        default=200,
        help=f"requests in all (1-{MAX_COUNT}); stops at --count or --duration",
    )
    lt.add_argument(
        "--duration",
        type=float,
        default=60.0,
        help=f"stop after this many seconds (at most {MAX_DURATION_S:g})",
    )
    lt.add_argument("--matches", type=int, default=1000, help="matches per pair (simulated)")
    lt.add_argument("--outlier-ratio", type=float, default=0.5)
    lt.add_argument(
        "--pairs", type=int, default=4, help="distinct simulated pairs sent in turn (1-64)"
    )
    lt.add_argument("--method", default=None, help="method (default: the service's default)")
    lt.add_argument("--api-key", default=None, help="X-API-Key (default $HMCC_API_KEY)")
    lt.add_argument("--json", action="store_true", help="print the figures as JSON")


def is_loopback_url(url: str) -> bool:
    """True for an http(s) URL whose host is 127.0.0.0/8, ::1 or ``localhost``."""
    try:
        parts = urlsplit(url)
        host = parts.hostname
        parts.port  # noqa: B018 - raises ValueError on a malformed port
    except ValueError:
        return False
    if parts.scheme not in ("http", "https") or not host:
        return False
    if host.rstrip(".").lower() == "localhost":
        return True
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return False
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return address.is_loopback


def check_url(url: str) -> str | None:
    """Why ``url`` is refused, or None."""
    if is_loopback_url(url):
        return None
    return (
        f"--url {url!r}: hmcc loadtest only loads a service on this machine "
        "(http(s) on 127.0.0.0/8, ::1 or localhost)"
    )


def _check_args(args: argparse.Namespace) -> list[str]:
    problems = []
    if (why := check_url(args.url)) is not None:
        problems.append(why)
    if not 1 <= args.concurrency <= MAX_CONCURRENCY:
        problems.append(f"--concurrency: must be 1-{MAX_CONCURRENCY}, got {args.concurrency}")
    if not 1 <= args.count <= MAX_COUNT:
        problems.append(f"--count: must be 1-{MAX_COUNT}, got {args.count}")
    if not (math.isfinite(args.duration) and 0 < args.duration <= MAX_DURATION_S):
        problems.append(f"--duration: must be > 0 and <= {MAX_DURATION_S:g} s, got {args.duration}")
    if not 1 <= args.matches <= MAX_MATCHES:
        problems.append(f"--matches: must be 1-{MAX_MATCHES}, got {args.matches}")
    if not 0 <= args.outlier_ratio < 1:
        problems.append(f"--outlier-ratio: must be in [0, 1), got {args.outlier_ratio}")
    if not 1 <= getattr(args, "pairs", 1) <= 64:
        problems.append(f"--pairs: must be 1-64, got {args.pairs}")
    if args.method is not None:
        from hmcc import METHODS

        if args.method not in METHODS:
            problems.append(f"--method: unknown {args.method!r}; one of {list(METHODS)}")
    return problems


def make_bodies(
    matches: int,
    outlier_ratio: float,
    n_pairs: int = 4,
    method: str | None = None,
    decimals: int | None = None,
    seed: int = 0,
) -> list[bytes]:
    """``n_pairs`` simulated pairs (seeds ``seed``..) of about ``matches`` matches as JSON
    request bodies, without their ground truth. ``decimals``: round keypoint values to that
    many decimals (smaller bodies; detectors give float32 anyway)."""
    from hmcc.simulate import SimulationOptions, simulate_pair

    options = SimulationOptions(
        n_inliers=max(1, round(matches * (1.0 - outlier_ratio))), outlier_ratio=outlier_ratio
    )
    bodies = []
    for k in range(n_pairs):
        pair = simulate_pair(options, seed=seed + k)
        pair.pop("ground_truth", None)
        if method is not None:
            pair["method"] = method
        if decimals is not None:
            for key in ("keypoints1", "keypoints2"):
                pair[key] = [[round(v, decimals) for v in kp] for kp in pair[key]]
        bodies.append(json.dumps(pair, separators=(",", ":")).encode())
    return bodies


def percentile(values: list[float], q: float) -> float | None:
    """The ``q``-th percentile (0-100, linear interpolation), None for no values."""
    if not values:
        return None
    ordered = sorted(values)
    rank = (len(ordered) - 1) * q / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


@dataclass
class LoadStats:
    """What one load run saw; times in ms unless named ``_s``."""

    url: str
    concurrency: int
    sent: int = 0
    elapsed_s: float = 0.0
    finished: int = 0
    failed: int = 0
    unfinished: int = 0
    failed_codes: Counter[str] = field(default_factory=Counter)
    http_errors: Counter[str] = field(default_factory=Counter)
    latency_ms: list[float] = field(default_factory=list)
    overhead_ms: list[float] = field(default_factory=list)
    compute_ms: list[float] = field(default_factory=list)
    #: The job's ``timings_ms.run``: the job's own time (its input, the pair, its output).
    job_ms: list[float] = field(default_factory=list)
    queue_wait_ms: list[float] = field(default_factory=list)
    #: The job's ``timings_ms.turnaround`` minus the result's ``timings_ms.total``: the
    #: service's own overhead, submitted -> finished minus the stages (no HTTP, no parsing of
    #: the body by the API).
    service_overhead_ms: list[float] = field(default_factory=list)

    @property
    def errors(self) -> int:
        return self.failed + self.unfinished + sum(self.http_errors.values())

    def summary(self) -> dict[str, Any]:
        """The figures as a JSON-ready dict."""

        def pcts(values: list[float], *qs: int) -> dict[str, float | None]:
            return {f"p{q}": _round(percentile(values, q)) for q in qs}

        elapsed = max(self.elapsed_s, 1e-9)
        return {
            "url": self.url,
            "concurrency": self.concurrency,
            "requests": self.sent,
            "elapsed_s": round(self.elapsed_s, 3),
            "throughput_pairs_s": round(self.finished / elapsed, 2),
            "requests_s": round(self.sent / elapsed, 2),
            "latency_ms": {
                **pcts(self.latency_ms, 50, 95, 99),
                "max": _round(max(self.latency_ms, default=None)),
            },
            "overhead_ms": pcts(self.overhead_ms, 50, 95),
            "compute_ms": pcts(self.compute_ms, 50),
            "job_ms": pcts(self.job_ms, 50),
            "queue_wait_ms": pcts(self.queue_wait_ms, 50),
            "service_overhead_ms": pcts(self.service_overhead_ms, 50, 99),
            "finished": self.finished,
            "failed": self.failed,
            "failed_codes": dict(self.failed_codes),
            "unfinished": self.unfinished,
            "http_errors": dict(self.http_errors),
            "errors": self.errors,
        }


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 3)


def _record(stats: LoadStats, response: httpx.Response, latency_ms: float) -> None:
    if response.status_code not in (200, 202):
        stats.http_errors[str(response.status_code)] += 1
        return
    try:
        job = response.json()
        status = job["status"]
        timings = job["timings_ms"]
        compute = float(job["result"]["timings_ms"]["total"]) if status == "finished" else 0.0
    except (ValueError, KeyError, TypeError):
        stats.http_errors["bad_body"] += 1
        return
    if status == "finished":
        stats.finished += 1
        stats.latency_ms.append(latency_ms)
        stats.compute_ms.append(compute)
        stats.overhead_ms.append(latency_ms - compute)
        if timings.get("run") is not None:
            stats.job_ms.append(timings["run"])
        if timings.get("queue_wait") is not None:
            stats.queue_wait_ms.append(timings["queue_wait"])
        if timings.get("turnaround") is not None:
            stats.service_overhead_ms.append(timings["turnaround"] - compute)
    elif status in ("failed", "canceled"):
        stats.failed += 1
        stats.latency_ms.append(latency_ms)
        stats.failed_codes[(job.get("error") or {}).get("code", status)] += 1
    else:
        stats.unfinished += 1


async def run_load(
    url: str,
    bodies: list[bytes],
    *,
    concurrency: int,
    count: int,
    duration_s: float,
    api_key: str | None = None,
) -> LoadStats:
    """Send ``count`` verification requests (``bodies`` in turn) from ``concurrency``
    workers, stopping early after ``duration_s`` seconds; no URL check here."""
    import asyncio

    import httpx

    stats = LoadStats(url=url, concurrency=concurrency)
    headers = {"Content-Type": "application/json"}
    if api_key:
        headers["X-API-Key"] = api_key
    limits = httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency)
    timeout = httpx.Timeout(30.0, read=WAIT_S + 30.0)
    params = {"wait": f"{WAIT_S:g}"}
    async with httpx.AsyncClient(
        base_url=url.rstrip("/"),
        headers=headers,
        limits=limits,
        timeout=timeout,
        trust_env=False,
    ) as http:
        start = time.perf_counter()
        deadline = start + duration_s

        async def worker() -> None:
            while stats.sent < count and time.perf_counter() < deadline:
                body = bodies[stats.sent % len(bodies)]
                stats.sent += 1
                t0 = time.perf_counter()
                try:
                    response = await http.post("/v1/verifications", params=params, content=body)
                except httpx.HTTPError as e:
                    stats.http_errors[type(e).__name__] += 1
                    continue
                _record(stats, response, (time.perf_counter() - t0) * 1e3)

        await asyncio.gather(*(worker() for _ in range(concurrency)))
        stats.elapsed_s = time.perf_counter() - start
    return stats


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _text(s: dict[str, Any], args: argparse.Namespace, n_pairs: int) -> str:
    lat, over = s["latency_ms"], s["overhead_ms"]
    errors = ", ".join(f"{k}: {v}" for k, v in sorted(s["http_errors"].items())) or "none"
    failed = "".join(f" ({k}: {v})" for k, v in sorted(s["failed_codes"].items()))
    return "\n".join(
        [
            f"hmcc loadtest {s['url']}: concurrency {s['concurrency']}, {args.matches} matches "
            f"per pair (outlier ratio {args.outlier_ratio:g}, {n_pairs} distinct "
            f"{'pair' if n_pairs == 1 else 'pairs'})",
            f"requests      {s['requests']} in {s['elapsed_s']:.2f} s",
            f"throughput    {s['throughput_pairs_s']:.2f} pairs/s",
            f"latency ms    p50 {_fmt(lat['p50'])}  p95 {_fmt(lat['p95'])}  p99 {_fmt(lat['p99'])}"
            f"  max {_fmt(lat['max'])}",
            f"overhead ms   p50 {_fmt(over['p50'])}  p95 {_fmt(over['p95'])}  "
            "(latency - result timings_ms.total)",
            f"service ms    compute p50 {_fmt(s['compute_ms']['p50'])}  job (parse + compute) "
            f"p50 {_fmt(s['job_ms']['p50'])}  queue wait p50 {_fmt(s['queue_wait_ms']['p50'])}  "
            f"total - compute p50 {_fmt(s['service_overhead_ms']['p50'])}",
            f"finished {s['finished']}  failed {s['failed']}{failed}  "
            f"unfinished {s['unfinished']}  HTTP errors: {errors}",
        ]
    )


def main(args: argparse.Namespace) -> int:
    """Run ``hmcc loadtest`` with the parsed arguments (see ``hmcc loadtest --help``)."""
    import asyncio

    import httpx

    problems = _check_args(args)
    if problems:
        for p in problems:
            print(f"error: {p}", file=sys.stderr)
        return 2
    n_pairs = getattr(args, "pairs", 4)
    api_key = args.api_key or os.environ.get("HMCC_API_KEY") or None
    bodies = make_bodies(args.matches, args.outlier_ratio, n_pairs, args.method)
    try:
        # trust_env=False here and below: no proxy from the environment may carry the load away.
        httpx.get(
            f"{args.url.rstrip('/')}/healthz", timeout=5.0, trust_env=False
        ).raise_for_status()
    except httpx.HTTPError as e:
        print(f"error: {args.url} does not answer /healthz: {e}", file=sys.stderr)
        return 1
    stats = asyncio.run(
        run_load(
            args.url,
            bodies,
            concurrency=args.concurrency,
            count=args.count,
            duration_s=args.duration,
            api_key=api_key,
        )
    )
    summary = stats.summary()
    print(json.dumps(summary) if args.json else _text(summary, args, n_pairs))
    return 0 if stats.errors == 0 else 1
