"""Service benchmark: what the HTTP API and its queues cost against verifying in-process.

One run, one set of simulated pairs (``--matches`` matches, ``--outlier-ratio`` outliers,
``--method``; keypoints rounded to ``--decimals``; every pair gets the first pair's plane, so
that a batch, whose plane is shared, does the same work), verified by four set-ups:

a. **in-process**: ``hmcc_worker.jobs.run_pair(json_text)`` in a loop, one process, one thread
   (parse + verify + result dict: what a worker does per pair, without any queue);
b. **embedded**: ``hmcc serve`` without ``REDIS_URL`` (jobs on the API's thread pool,
   ``HMCC_EMBEDDED_WORKERS`` default 2);
c. **rq-1**: a private ``redis-server``, ``hmcc serve`` with ``REDIS_URL`` and one
   ``hmcc worker``;
d. **rq-2**: the same with a second ``hmcc worker``.

Each HTTP set-up is measured, after a few untimed warm-up requests, by

* **batch throughput**: ``--batches`` batches of ``--batch-pairs`` pairs are POSTed to
  ``/v1/batches`` one after the other (bodies encoded before the clock starts), then each is
  polled (``limit=0``, every 20 ms) until finished and its results are read (pages of 1000);
  pairs / (first POST -> last result page);
* **concurrent throughput**: ``--concurrent`` single-pair ``POST /v1/verifications?wait=60``
  from ``--concurrency`` asyncio clients (``hmcc_service.loadtest.run_load``); finished pairs
  per second;
* **sequential latency**: ``--sequential`` such requests one at a time: latency p50/p99 (ms, the
  whole HTTP exchange seen by the client) and the service overhead p50 = latency minus the
  result's ``timings_ms.compute`` (the pipeline's stage sum); ``job`` (the job function's own
  time: parse + compute + result) and ``queue_wait`` (submitted -> started) come from the
  result's ``timings_ms``.

Ratios are against the in-process throughput of the same run. Targets: rq-1 batch throughput
>= 70 % of in-process (one worker against one in-process loop), single-pair overhead p50
<= 5 ms. The client runs on the same machine and takes CPU from the service: on a 2-core box
that is part of what is measured.

Results go to ``<out>/service.json`` (every number) and ``<out>/service.md`` (the table).

Usage::

    .venv/bin/python -m benchmarks.bench_service [--quick] [--matches N] [--out DIR]
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
from tests.support.procs import (
    Proc,
    redis_server,
    running,
    service_env,
    start_api,
    start_worker,
    wait_for_workers,
)

from hmcc import __version__ as hmcc_version
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_client import HmccClient
from hmcc_schema import parse_pair
from hmcc_service.loadtest import LoadStats, percentile, run_load
from hmcc_worker.outcomes import verify_flight

from .common import verdict, with_code_hash

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "benchmarks" / "results"


def run_pair(text: str) -> tuple[str, dict[str, float]]:
    """What a job does with one pair, in this process: parse, verify, encode the outcome."""
    (outcome,) = verify_flight(parse_pair(text))
    return outcome.status.value, outcome.timings_ms


TARGET_BATCH_RATIO = 0.70  # rq-1 batch throughput / in-process throughput, at least
TARGET_OVERHEAD_MS = 5.0  # sequential single-pair latency - compute, p50, at most
TARGET_MODE = "rq-1"


@dataclass(frozen=True)
class Config:
    """Sizes of one run."""

    quick: bool
    matches: int
    outlier_ratio: float
    method: str
    decimals: int | None
    distinct: int
    inprocess: int
    batch_pairs: int
    batches: int
    concurrent: int
    concurrency: int
    sequential: int
    warmup: int
    out: Path


def make_config(args: argparse.Namespace) -> Config:
    quick = args.quick
    return Config(
        quick=quick,
        matches=args.matches,
        outlier_ratio=args.outlier_ratio,
        method=args.method,
        decimals=None if args.decimals < 0 else args.decimals,
        distinct=4 if quick else 8,
        inprocess=args.inprocess or (24 if quick else 400),
        batch_pairs=args.batch_pairs or (12 if quick else 100),
        batches=2 if quick else 4,
        concurrent=args.concurrent or (24 if quick else 400),
        concurrency=args.concurrency,
        sequential=args.sequential or (16 if quick else 300),
        warmup=4 if quick else 10,
        out=args.out,
    )


# --------------------------------------------------------------------------- the pairs


@dataclass(frozen=True)
class Workload:
    """The pairs: dicts (for batches) and their JSON bodies (single pairs, in-process)."""

    pairs: list[dict[str, Any]]
    bodies: list[bytes]

    def batch_body(self, n: int, tag: str) -> bytes:
        """A batch of ``n`` pairs cycling over the distinct ones (images sent once each)."""
        images: dict[str, Any] = {}
        items = []
        for k, pair in enumerate(self.pairs):
            images[f"{k}a"], images[f"{k}b"] = pair["image1"], pair["image2"]
        for j in range(n):
            k = j % len(self.pairs)
            p = self.pairs[k]
            items.append(
                {
                    "id": f"{tag}-{j}",
                    "image1": f"{k}a",
                    "image2": f"{k}b",
                    "keypoints1": p["keypoints1"],
                    "keypoints2": p["keypoints2"],
                    "matches": p["matches"],
                }
            )
        first = self.pairs[0]
        body = {
            "images": images,
            "pairs": items,
            "plane": first["plane"],
            "method": first["method"],
        }
        return json.dumps(body, separators=(",", ":")).encode()


def make_workload(cfg: Config) -> Workload:
    options = SimulationOptions(
        n_inliers=max(1, round(cfg.matches * (1 - cfg.outlier_ratio))),
        outlier_ratio=cfg.outlier_ratio,
    )
    pairs = []
    for seed in range(cfg.distinct):
        pair = simulate_pair(options, seed)
        pair.pop("ground_truth")
        pair["method"] = cfg.method
        if cfg.decimals is not None:
            for key in ("keypoints1", "keypoints2"):
                pair[key] = [[round(v, cfg.decimals) for v in kp] for kp in pair[key]]
        pairs.append(pair)
    for pair in pairs[1:]:
        pair["plane"] = pairs[0]["plane"]
    bodies = [json.dumps(p, separators=(",", ":")).encode() for p in pairs]
    return Workload(pairs, bodies)


# --------------------------------------------------------------------------- measurements


def _p(values: list[float], q: float) -> float | None:
    return percentile(values, q)


def bench_inprocess(cfg: Config, work: Workload) -> dict[str, Any]:
    """``run_pair`` in a loop: throughput, wall per call, compute per call."""
    texts = [b.decode() for b in work.bodies]
    for text in texts:  # warm-up, and every pair must verify
        status, _ = run_pair(text)
        if status != "finished":
            raise RuntimeError("a benchmark pair does not verify")
    walls, computes, jobs = [], [], []
    start = time.perf_counter()
    for i in range(cfg.inprocess):
        t0 = time.perf_counter()
        _, timings = run_pair(texts[i % len(texts)])
        walls.append((time.perf_counter() - t0) * 1e3)
        computes.append(timings["compute"])
        jobs.append(walls[-1])
    elapsed = time.perf_counter() - start
    overheads = [w - c for w, c in zip(walls, computes, strict=True)]
    return {
        "pairs": cfg.inprocess,
        "elapsed_s": elapsed,
        "throughput_pairs_s": cfg.inprocess / elapsed,
        "latency_ms": {"p50": _p(walls, 50), "p99": _p(walls, 99)},
        "overhead_ms": {"p50": _p(overheads, 50)},
        "compute_ms": {"p50": _p(computes, 50)},
        "job_ms": {"p50": _p(jobs, 50)},
    }


def bench_batches(url: str, cfg: Config, work: Workload) -> dict[str, Any]:
    """POST ``cfg.batches`` batches, wait for each, read every result: pairs per second."""
    bodies = [work.batch_body(cfg.batch_pairs, f"b{k}") for k in range(cfg.batches)]
    total = cfg.batches * cfg.batch_pairs
    headers = {"Content-Type": "application/json"}
    with (
        httpx.Client(base_url=url, timeout=120, trust_env=False) as http,
        HmccClient(url, timeout=120) as client,
    ):
        start = time.perf_counter()
        ids, post_ms = [], []
        for body in bodies:
            t0 = time.perf_counter()
            response = http.post("/v1/batches", content=body, headers=headers)
            post_ms.append((time.perf_counter() - t0) * 1e3)
            response.raise_for_status()
            ids.append(response.json()["batch_id"])
        finished = failed = 0
        for batch_id in ids:
            if not client.wait_batch(batch_id, timeout=600, poll_s=0.02).done:
                raise RuntimeError(f"batch {batch_id} did not finish within 600 s")
            for item in client.batch_results(batch_id):
                finished += item.status == "finished"
                failed += item.status != "finished"
        elapsed = time.perf_counter() - start
    return {
        "pairs": total,
        "batches": cfg.batches,
        "batch_pairs": cfg.batch_pairs,
        "body_mb": round(sum(len(b) for b in bodies) / cfg.batches / 1e6, 2),
        "post_ms": {"p50": _p(post_ms, 50), "max": max(post_ms)},
        "elapsed_s": elapsed,
        "throughput_pairs_s": finished / elapsed,
        "finished": finished,
        "failed": failed,
    }


def _load(url: str, work: Workload, count: int, concurrency: int) -> LoadStats:
    return asyncio.run(
        run_load(url, work.bodies, concurrency=concurrency, count=count, duration_s=600.0)
    )


def bench_http(url: str, cfg: Config, work: Workload) -> dict[str, Any]:
    """Warm-up, batch throughput, concurrent throughput, sequential latency."""
    _load(url, work, cfg.warmup, min(cfg.concurrency, cfg.warmup))
    batch = bench_batches(url, cfg, work)
    concurrent = _load(url, work, cfg.concurrent, cfg.concurrency).summary()
    sequential = _load(url, work, cfg.sequential, 1).summary()
    return {"batch": batch, "concurrent": concurrent, "sequential": sequential}


# --------------------------------------------------------------------------- set-ups


@contextmanager
def embedded() -> Iterator[str]:
    api, url = start_api(service_env())
    with running(api):
        yield url


@contextmanager
def rq_service() -> Iterator[tuple[str, dict[str, str], list[Proc]]]:
    """Redis + the API on it; the caller starts the workers (listed for the clean-up)."""
    with redis_server() as redis:
        env = service_env(REDIS_URL=redis.url)
        api, url = start_api(env)
        workers: list[Proc] = []
        try:
            yield url, env, workers
        finally:
            for proc in (*workers, api):
                proc.stop()


def run_all(cfg: Config, work: Workload) -> dict[str, dict[str, Any]]:
    modes: dict[str, dict[str, Any]] = {}
    modes["in-process"] = section("a in-process", lambda: bench_inprocess(cfg, work))
    with embedded() as url:
        modes["embedded"] = section("b embedded", lambda: bench_http(url, cfg, work))
    with rq_service() as (url, env, workers):
        for n in (1, 2):
            workers.append(start_worker(env, f"bench-{n}"))
            wait_for_workers(url, n)
            modes[f"rq-{n}"] = section(f"{'cd'[n - 1]} rq-{n}", lambda: bench_http(url, cfg, work))
    return modes


# --------------------------------------------------------------------------- report


def section(title: str, run: Any) -> Any:
    print(f"[{title}] ...", end=" ", flush=True)
    t0 = time.perf_counter()
    out = run()
    print(f"{time.perf_counter() - t0:.1f} s", flush=True)
    return out


def fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


HEADERS = [
    "set-up",
    "batch pairs/s",
    "x in-proc",
    "concurrent pairs/s",
    "x in-proc",
    "latency p50 ms",
    "latency p99 ms",
    "overhead p50 ms",
    "total-compute p50 ms",
    "compute p50 ms",
    "job p50 ms",
    "queue wait p50 ms",
]


def table_rows(modes: dict[str, dict[str, Any]]) -> list[list[str]]:
    base = modes["in-process"]["throughput_pairs_s"]
    ip = modes["in-process"]
    rows = [
        [
            "in-process",
            fmt(base, 1),
            "1.00",
            "-",
            "-",
            fmt(ip["latency_ms"]["p50"]),
            fmt(ip["latency_ms"]["p99"]),
            fmt(ip["overhead_ms"]["p50"]),
            "-",
            fmt(ip["compute_ms"]["p50"]),
            fmt(ip["job_ms"]["p50"]),
            "-",
        ]
    ]
    for name, m in modes.items():
        if name == "in-process":
            continue
        b, c, s = m["batch"]["throughput_pairs_s"], m["concurrent"], m["sequential"]
        rows.append(
            [
                name,
                fmt(b, 1),
                fmt(b / base),
                fmt(c["throughput_pairs_s"], 1),
                fmt(c["throughput_pairs_s"] / base),
                fmt(s["latency_ms"]["p50"]),
                fmt(s["latency_ms"]["p99"]),
                fmt(s["overhead_ms"]["p50"]),
                fmt(s["service_overhead_ms"]["p50"]),
                fmt(s["compute_ms"]["p50"]),
                fmt(s["job_ms"]["p50"]),
                fmt(s["queue_wait_ms"]["p50"]),
            ]
        )
    return rows


def check_targets(modes: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    base = modes["in-process"]["throughput_pairs_s"]
    ratio = modes[TARGET_MODE]["batch"]["throughput_pairs_s"] / base
    targets = [
        {
            "target": f"{TARGET_MODE} batch throughput >= {TARGET_BATCH_RATIO:.0%} of in-process",
            "value": ratio,
            "ok": ratio >= TARGET_BATCH_RATIO,
        }
    ]
    for name in ("embedded", "rq-1", "rq-2"):
        seq = modes[name]["sequential"]
        for label, key in (
            ("latency - compute", "overhead_ms"),
            ("total - compute", "service_overhead_ms"),
        ):
            over = seq[key]["p50"]
            targets.append(
                {
                    "target": f"{name} single-pair {label} p50 <= {TARGET_OVERHEAD_MS:g} ms",
                    "value": over,
                    "ok": over is not None and over <= TARGET_OVERHEAD_MS,
                }
            )
    return targets


def render_text(rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(HEADERS)]

    def line(cells: Sequence[str]) -> str:
        pairs = enumerate(zip(cells, widths, strict=True))
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in pairs)

    return "\n".join([line(HEADERS), line(["-" * w for w in widths]), *map(line, rows)])


def render_markdown(rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(HEADERS) + " |", "|:---|" + "---:|" * (len(HEADERS) - 1)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def environment() -> dict[str, Any]:
    def git(*args: str) -> str:
        try:
            return subprocess.run(
                ["git", "-C", str(REPO), *args],
                capture_output=True,
                text=True,
                timeout=10,
                check=False,
            ).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "hmcc": hmcc_version,
        "git_commit": git("rev-parse", "--short", "HEAD") or None,
        "uncommitted": [ln[3:] for ln in git("status", "--porcelain").splitlines()],
        "load_average_at_start": list(os.getloadavg()),
    }


def header(cfg: Config, env: dict[str, Any], work: Workload) -> list[str]:
    size_kb = sum(len(b) for b in work.bodies) / len(work.bodies) / 1e3
    return [
        "hmcc-match service benchmark" + (" (QUICK)" if cfg.quick else ""),
        f"{cfg.method}, {len(work.pairs[0]['matches'])} matches/pair (outlier ratio "
        f"{cfg.outlier_ratio:g}), {cfg.distinct} distinct pairs, ~{size_kb:.0f} kB/pair body "
        f"(keypoints rounded to {cfg.decimals} decimals)",
        f"in-process {cfg.inprocess} pairs; batches {cfg.batches} x {cfg.batch_pairs}; "
        f"concurrent {cfg.concurrent} at concurrency {cfg.concurrency}; sequential "
        f"{cfg.sequential}; {cfg.warmup} warm-up requests per set-up",
        f"python {env['python']}, hmcc {env['hmcc']}, commit {env['git_commit']}"
        + (" + uncommitted changes" if env["uncommitted"] else "")
        + f"; {env['platform']}, {env['cpu_count']} CPUs, load average "
        + " ".join(f"{x:.2f}" for x in env["load_average_at_start"])
        + " at start",
    ]


NOTES = """\
Columns: *batch* = pairs / (first POST /v1/batches -> last result page read); *concurrent* =
finished pairs / wall time of single-pair POST ?wait=60 requests from `concurrency` clients;
latency / overhead / compute / job / queue wait are percentiles in ms over the *sequential*
requests (one at a time). overhead = client-side latency - `timings_ms.compute`; it includes
the API's own validation of the body, the queue, the worker's second parse, the result
building and the HTTP exchange. total-compute = `timings_ms.total - timings_ms.compute`, the
service's own overhead between accepting the job and finishing it (queue, worker's parse,
result). In-process row: one `run_pair` call (parse + verify + result
dict) per pair in a loop; its latency is the call's wall time. Ratios: throughput / in-process
throughput of the same run."""


def write_outputs(result: dict[str, Any], rows: list[list[str]], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "service.json").write_text(
        json.dumps(with_code_hash(result, __file__), indent=1, default=str) + "\n"
    )
    meta = result["meta"]
    lines = ["# hmcc-match service benchmark", ""]
    lines += [f"- {line}" for line in meta["header"][1:]]
    lines += [
        f"- command: `{meta['command']}`",
        f"- wall time of the run: {meta['run_wall_s']:.1f} s",
        "",
        render_markdown(rows),
        "",
        NOTES,
        "",
        "**Targets**",
        "",
    ]
    lines += [f"- {verdict(t['ok'])}: {t['target']} ({fmt(t['value'])})" for t in result["targets"]]
    (out / "service.md").write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------- main


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="small sizes: checks that it runs")
    p.add_argument("--matches", type=int, default=1000, help="matches per pair")
    p.add_argument("--outlier-ratio", type=float, default=0.5)
    p.add_argument("--method", default="hmcc-ransac")
    p.add_argument(
        "--decimals",
        type=int,
        default=2,
        help="round keypoint values to this many decimals (-1: full precision)",
    )
    p.add_argument("--inprocess", type=int, help="pairs of the in-process loop")
    p.add_argument("--batch-pairs", type=int, help="pairs per batch")
    p.add_argument("--concurrent", type=int, help="single-pair requests, concurrent")
    p.add_argument("--concurrency", type=int, default=4, help="clients of the concurrent run")
    p.add_argument("--sequential", type=int, help="single-pair requests, one at a time")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output directory")
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    t_run = time.perf_counter()
    started = datetime.now(UTC).isoformat(timespec="seconds")
    args = parse_args(argv)
    cfg = make_config(args)
    env = environment()
    work = make_workload(cfg)
    head = header(cfg, env, work)
    print("\n".join(head), flush=True)
    modes = run_all(cfg, work)
    rows = table_rows(modes)
    targets = check_targets(modes)
    print()
    print(render_text(rows))
    print()
    for t in targets:
        print(f"{verdict(t['ok'])}  {t['target']}: {fmt(t['value'])}")
    run_wall_s = time.perf_counter() - t_run
    load_end = list(os.getloadavg())
    print(
        f"wall time of the run: {run_wall_s:.1f} s; load average at the end "
        + " ".join(f"{x:.2f}" for x in load_end)
    )
    result = {
        "meta": {
            "header": head,
            "environment": env,
            "config": dataclasses.asdict(cfg),
            "command": " ".join(["benchmarks/bench_service.py", *(argv or sys.argv[1:])]),
            "run_wall_s": run_wall_s,
            "load_average_at_end": load_end,
            "started_utc": started,
            "notes": NOTES,
        },
        "modes": modes,
        "targets": targets,
    }
    write_outputs(result, rows, cfg.out)
    print(f"wrote {cfg.out / 'service.json'} and {cfg.out / 'service.md'}")
    failed = sum(
        m["batch"]["failed"] + m["concurrent"]["errors"] + m["sequential"]["errors"]
        for k, m in modes.items()
        if k != "in-process"
    )
    if failed:
        print(f"error: {failed} requests or pairs failed", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
