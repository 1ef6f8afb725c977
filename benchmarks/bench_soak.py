"""Soak benchmark: does the service's memory level off under sustained load (issue #11)?

For each mode, embedded (``hmcc serve`` alone) and RQ (a private ``redis-server``, ``hmcc
serve`` with ``REDIS_URL`` and two ``hmcc worker``), the equivalent of ``hmcc loadtest
--concurrency 16 --count 3000 --matches 1000`` runs three times in a row
(:func:`hmcc_service.loadtest.run_load`, the same code). Before the first run and after each,
the resident set (``VmRSS``, ``/proc``) of the API process and of each worker process tree
(the worker and its compute child; in embedded mode the API's compute children) is read.
Printed per run: throughput, latency p50/p99, errors, and the RSS figures.

Memory levels off when the third run ends within a few percent of the second (the first
warms caches and allocators). The embedded API keeps finished results in memory up to
``HMCC_RESULT_MEMORY_MB`` (256 by default; 3 000 results are about 24 MiB): the soak sets it to
``--result-memory-mb`` (32) so that the bound is reached within the runs and shows.
Results: ``<out>/soak.json`` and ``<out>/soak.md``.

Usage (from the checkout's root)::

    .venv/bin/python -m benchmarks.bench_soak [--count N] [--runs N] [--out DIR]
"""

from __future__ import annotations

import argparse
import asyncio
import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from tests.support.procs import (
    Proc,
    redis_server,
    running,
    service_env,
    start_api,
    start_worker,
    wait_for_workers,
)

from hmcc_service.loadtest import make_bodies, run_load

from .common import DEFAULT_OUT, Table, environment, fmt, jsonable, with_code_hash

MIB = 2**20


def _children(pid: int) -> list[int]:
    """Every descendant (a child belongs to the thread that started it: read every task's)."""
    kids: list[str] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            kids += (task / "children").read_text().split()
        except OSError:
            continue
    out = []
    for kid in map(int, kids):
        out += [kid, *_children(kid)]
    return out


def rss(pid: int) -> int:
    """Resident bytes of one process (0 once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def memory(api: Proc, workers: Sequence[Proc]) -> dict[str, int]:
    """The API process alone, its children together, and each worker's tree."""
    figures = {
        "api": rss(api.proc.pid),
        "api_children": sum(rss(p) for p in _children(api.proc.pid)),
    }
    for k, w in enumerate(workers):
        figures[f"worker{k}"] = rss(w.proc.pid) + sum(rss(p) for p in _children(w.proc.pid))
    return figures


@contextmanager
def embedded(result_memory_mb: int) -> Iterator[tuple[str, Proc, list[Proc]]]:
    api, url = start_api(service_env(HMCC_RESULT_MEMORY_MB=str(result_memory_mb)))
    with running(api):
        yield url, api, []


@contextmanager
def rq(workers: int) -> Iterator[tuple[str, Proc, list[Proc]]]:
    with redis_server() as redis:
        env = service_env(REDIS_URL=redis.url)
        api, url = start_api(env)
        procs = [start_worker(env, f"soak-{k}") for k in range(workers)]
        with running(*procs, api):
            wait_for_workers(url, workers, timeout=60)
            yield url, api, procs


def soak(mode: str, args: argparse.Namespace, bodies: list[bytes]) -> dict[str, Any]:
    setup = embedded(args.result_memory_mb) if mode == "embedded" else rq(2)
    with setup as (url, api, workers):
        asyncio.run(run_load(url, bodies, concurrency=4, count=40, duration_s=120))  # warm
        runs = [{"run": 0, "memory": memory(api, workers)}]
        for k in range(1, args.runs + 1):
            stats = asyncio.run(
                run_load(
                    url,
                    bodies,
                    concurrency=args.concurrency,
                    count=args.count,
                    duration_s=600,
                )
            )
            runs.append({"run": k, **stats.summary(), "memory": memory(api, workers)})
            print(
                f"  {mode} run {k}: {runs[-1]['throughput_pairs_s']} pairs/s, "
                f"errors {runs[-1]['errors']}, memory {runs[-1]['memory']}",
                flush=True,
            )
    return {"mode": mode, "runs": runs}


def levelled(runs: list[dict[str, Any]], key: str, tolerance: float = 0.05) -> bool:
    """The last run ends within ``tolerance`` (or 8 MiB) of the one before."""
    a, b = runs[-2]["memory"].get(key, 0), runs[-1]["memory"].get(key, 0)
    return b <= a * (1 + tolerance) or b - a <= 8 * MIB


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--concurrency", type=int, default=16)
    p.add_argument("--count", type=int, default=3000)
    p.add_argument("--matches", type=int, default=1000)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument(
        "--result-memory-mb", type=int, default=32, help="embedded: HMCC_RESULT_MEMORY_MB"
    )
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    bodies = make_bodies(args.matches, 0.5, decimals=2)
    results = [soak(mode, args, bodies) for mode in ("embedded", "rq")]
    table = Table(
        f"loadtest --concurrency {args.concurrency} --count {args.count} --matches "
        f"{args.matches}, {args.runs} runs a mode; RSS in MiB after each run (run 0: before)",
        [
            "mode",
            "run",
            "pairs/s",
            "p50 ms",
            "p99 ms",
            "errors",
            "API",
            "API children",
            "worker 0",
            "worker 1",
        ],
        [],
        left=1,
    )
    checks = []
    for result in results:
        for r in result["runs"]:
            m = r["memory"]
            table.rows.append(
                [
                    result["mode"],
                    str(r["run"]),
                    fmt(r.get("throughput_pairs_s"), 1),
                    fmt((r.get("latency_ms") or {}).get("p50"), 0),
                    fmt((r.get("latency_ms") or {}).get("p99"), 0),
                    str(r.get("errors", "")),
                    *(
                        fmt(m[k] / MIB, 0) if k in m else ""
                        for k in ("api", "api_children", "worker0", "worker1")
                    ),
                ]
            )
        for key in result["runs"][-1]["memory"]:
            checks.append(
                {
                    "mode": result["mode"],
                    "process": key,
                    "levels_off": levelled(result["runs"], key),
                }
            )
    errors = sum(r.get("errors", 0) for res in results for r in res["runs"])
    env = environment()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "soak.json").write_text(
        json.dumps(
            jsonable(
                with_code_hash({"results": results, "checks": checks, "environment": env}, __file__)
            ),
            indent=2,
        )
        + "\n"
    )
    lines = [
        "# Soak benchmark (`python -m benchmarks.bench_soak`)",
        "",
        f"Commit {env.get('git_commit')}, {env.get('cpu_count')} cores.",
        "",
        table.markdown(),
        "",
        "| mode | process | RSS levels off (run 3 within 5 % of run 2) |",
        "|---|---|---|",
    ]
    lines += [
        f"| {c['mode']} | {c['process']} | {'yes' if c['levels_off'] else 'NO'} |" for c in checks
    ]
    (out / "soak.md").write_text("\n".join(lines) + "\n")
    print(table.text())
    for c in checks:
        print(f"{'ok ' if c['levels_off'] else 'NO '} {c['mode']} {c['process']} levels off")
    return 0 if errors == 0 and all(c["levels_off"] for c in checks) else 1


if __name__ == "__main__":
    raise SystemExit(main())
