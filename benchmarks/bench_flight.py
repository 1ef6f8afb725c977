"""Flight benchmark: a whole simulated UAV flight through every path, from the bare core to the
HTTP service with its queues (issue #13).

The flight is :func:`hmcc.simulate_flight.simulate_flight`'s default: a penta-view block like
the paper's dataset 3, 750 images, 18 283 pairs, about 720 matches a pair (half of them
outliers), default method (hmcc-plus) unless a row says otherwise. One run, every row on the
same flight:

* **core, 1 process**: ``Flight.verify(i)`` for every pair, on arrays already in memory (the
  algorithm itself, no parsing);
* **core, 2 processes**: the same in two forked processes (pairs handed out 16 at a time);
* **hmcc flight --processes N, JSON file / binary file**: the whole command (``python -m
  hmcc_cli flight FILE --processes N -o OUT``, reading and parsing the file included) on the
  flight written as JSON and as a binary flight file (MessagePack, raw arrays), N = 2 by
  default (``--cli-processes``); its JSON lines are read back for precision and recall, and
  its ``--timings`` line gives the timeline table (when each step of the command ended);
  each line holds the full result, the command's default;
* **hmcc flight, binary file, --result inliers**: the same with the result the core rows keep
  and the HTTP rows ask for (inliers, model and time), like for like with them;
* **hmcc flight, columns file** (and with ``--result inliers``): the binary file with its pairs
  as columns (:mod:`hmcc_schema.flight_columns`: image ids, counts and one array of every
  pair's matches), the form the command reads without Python work a pair;
* **serial share**: for every row that runs children, the CPU seconds outside them (the
  command's own process, as it reports from ``getrusage``; the benchmark's own for the
  forked rows) against those in them, and the speed-up Amdahl's law then predicts for 4, 16
  and 64 processes, ``1 / (s + (1 - s) / N)``;
* **CPU per pair x core 1 process**: a row's CPU seconds, all its processes together, per
  pair, against the core's in one process. On the forked core row it is what running N
  processes at once costs the work itself (shared caches and memory bandwidth, a busy host):
  c there bounds that row's wall time below by ``c / N`` x the core's 1-process time, with
  no serial work at all;
* **cut-over** (``--cutover``): ``hmcc flight`` on the first n pairs, in its own process
  against 2 children, to place ``hmcc_worker.cutover.INPROCESS_MAX_PAIRS``;
* **pair JSON, full model** (how the service read a pair before #13: every number validated by
  pydantic) and **pair JSON, array parser** (the single-pair route today): one JSON body per
  pair with both images' keypoints, ``parse_pair`` + verify; sampled (``--sample`` pairs,
  extrapolated to the flight), 1 and 2 processes;
* **HTTP embedded** (``hmcc serve`` alone, ``HMCC_EMBEDDED_WORKERS=2``) and **HTTP + RQ, 2
  workers** (a private ``redis-server``, ``hmcc serve`` with ``REDIS_URL``, two ``hmcc
  worker``; also with 3 workers, ``--rq-workers``): :meth:`HmccClient.verify_flight` with
  ``params.result = "inliers"``, from the first request to the last result, bodies in
  MessagePack with raw array buffers and the pairs as columns; bytes sent are counted on the
  client's transport and the API process's peak RSS (``VmHWM``) is read from ``/proc`` at the
  end; then **HTTP embedded, pairs as rows** (``columns=False``: each pair an object of the
  body) and **HTTP + RQ, JSON bodies** (``binary=False``: JSON, the contract), each on the
  same service as the row before it;
* **OpenCV MAGSAC++** and **USAC_ACCURATE** (``magsac++``, ``usac-accurate``: one estimator on
  all matches), sampled, 1 and 2 processes;
* **COLMAP two-view geometry** (``pycolmap.estimate_two_view_geometry``, when pycolmap is
  installed), sampled, 1 process.

Precision and recall are against the simulator's truth, pooled over the pairs a row verified.
"Bytes" is what a client sends: per-pair JSON bodies for the first rows (computed for every
pair), the batches' bodies for the HTTP rows. Targets (issues #13 and #30): ``hmcc flight``
with 2 processes at most 0.55 x the core's 1-process time, HTTP + RQ (2 workers) and embedded
at most 0.6 x; the serial share of each at most 3 %; API peak RSS at most 1 GiB; bytes at most
40 % of the batch JSON of before (every pair with the keypoints of its matches, #13's
"today"); the same precision and recall as the core. The HTTP rows' serial share: the CPU
seconds over the timed flight of the client (this process), the API process, Redis and the
RQ workers' own processes (``/proc/PID/stat``), against the compute children's (the
embedded API's or the RQ workers', ended children included); the breakdown table gives each
part. Each HTTP row's service is warmed by an untimed
first flight of ``WARM_PAIRS`` pairs, as a running service is (the core row runs warm too).

The client runs on the same 2-core machine as the service and takes CPU from it. This process
holds the simulated flight to the end; it is frozen once built (``gc.freeze``), as ``hmcc
flight`` freezes the flight it read, so that the collector does not walk it again and again
(before, most of the HTTP rows' client CPU).

Results go to ``<out>/flight.json`` and ``<out>/flight.md``. Usage (from the checkout's root)::

    .venv/bin/python -m benchmarks.bench_flight [--quick] [--sample N] [--out DIR]
        [--scale-only] [--cli-processes 1,2] [--core-processes 1,2] [--cutover]

``--scale-only`` runs the core and ``hmcc flight`` rows only (no sampled, HTTP, OpenCV or
COLMAP rows); ``benchmarks/scale_device.sh`` runs it on a many-core machine.
"""

from __future__ import annotations

import argparse
import functools
import gc
import json
import multiprocessing
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import orjson
from tests.support.procs import (
    Proc,
    compute_children,
    redis_server,
    running,
    service_env,
    start_api,
    start_worker,
    wait_for_workers,
    wait_until,
)

from hmcc.flight import Flight
from hmcc.simulate_flight import FlightOptions, SimulatedFlight, simulate_flight
from hmcc_client import HmccClient
from hmcc_schema import parse_batch, parse_pair
from hmcc_schema.flight_columns import write_flight_columns
from hmcc_schema.flight_file import write_flight_file
from hmcc_schema.models import PairRequest
from hmcc_worker.metrics import process_cpu_s
from hmcc_worker.outcomes import unpack
from hmcc_worker.pool import ComputePool

from .common import DEFAULT_OUT, Table, environment, fmt, jsonable, warm_up_opencv, with_code_hash

QUICK = FlightOptions(strips=3, stations_per_strip=6, keypoints_per_image=1500, pairs=600)
CHUNK_PAIRS = 16
#: Pairs of the untimed first flight each HTTP row sends its freshly started service.
WARM_PAIRS = 500
GIB = 1024**3

# The forked children's view of the run (set before forking).
_FLIGHT: Flight | None = None
_TEXTS: list[bytes] = []


@dataclass
class Row:
    """One path's run: wall seconds for the flight (extrapolated when sampled), inliers found
    by pair index, and what else was measured."""

    path: str
    processes: int
    seconds: float
    pairs: int  # pairs actually run
    found: dict[int, np.ndarray]
    bytes_sent: int | None = None
    api_rss: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    #: CPU seconds outside the compute children and in them (None: not measured).
    cpu_outside: float | None = None
    cpu_children: float | None = None
    #: CPU seconds of a row run in this one process (None: not measured).
    cpu_self: float | None = None


def _cpu(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def serial_share(row: Row) -> float | None:
    if row.cpu_outside is None or row.cpu_children is None:
        return None
    return row.cpu_outside / (row.cpu_outside + row.cpu_children)


def amdahl(s: float, n: int) -> float:
    """The speed-up of ``n`` processes when ``s`` of the work is serial."""
    return 1.0 / (s + (1.0 - s) / n)


# --------------------------------------------------------------------------- the flight


def core_flight(sim: SimulatedFlight, method: str | None = None) -> Flight:
    """The flight as the core takes it (parsed once, untimed)."""
    body = dict(sim.body)
    if method:
        body["method"] = method
    return parse_batch(body, max_pairs=len(body["pairs"]))


def pair_json(sim: SimulatedFlight, i: int) -> bytes:
    """Pair ``i`` as the single-pair route takes it: both images' keypoints inline."""
    pair = sim.body["pairs"][i]
    im1, im2 = sim.body["images"][pair["image1"]], sim.body["images"][pair["image2"]]
    doc = {
        "image1": {"camera": im1["camera"], "pose": im1["pose"]},
        "image2": {"camera": im2["camera"], "pose": im2["pose"]},
        "keypoints1": np.round(im1["keypoints"], 2),
        "keypoints2": np.round(im2["keypoints"], 2),
        "matches": pair["matches"],
        "plane": sim.body["plane"],
    }
    return orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY)


def batch_json_before_bytes(sim: SimulatedFlight, indices: Sequence[int]) -> int:
    """Bytes of the flight as batch JSON before images could carry their keypoints (issue
    #13's "today"): every pair sends the keypoints of its matches (2 decimals), scaled from
    ``indices`` to the flight."""
    images, pairs = sim.body["images"], sim.body["pairs"]
    total = 0
    for i in indices:
        pair = pairs[i]
        m = np.asarray(pair["matches"])
        doc = {
            "id": pair["id"],
            "image1": pair["image1"],
            "image2": pair["image2"],
            "keypoints1": np.round(images[pair["image1"]]["keypoints"][m[:, 0]], 2),
            "keypoints2": np.round(images[pair["image2"]]["keypoints"][m[:, 1]], 2),
            "matches": np.stack([np.arange(len(m))] * 2, axis=1),
        }
        total += len(orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY))
    return total * len(pairs) // len(indices)


def sample_indices(n: int, k: int, seed: int = 0) -> list[int]:
    return sorted(np.random.default_rng(seed).choice(n, min(k, n), replace=False).tolist())


# --------------------------------------------------------------------------- local rows


def _verify_core(i: int) -> tuple[int, np.ndarray]:
    assert _FLIGHT is not None
    return i, _FLIGHT.verify(i).inliers


def _verify_json_model(i: int) -> tuple[int, np.ndarray]:
    text = _TEXTS[i]
    model = PairRequest.model_validate_json(text)  # how the service read a pair before #13
    doc = {
        "image1": model.image1.model_dump(exclude_none=True),
        "image2": model.image2.model_dump(exclude_none=True),
        "keypoints1": np.asarray(model.keypoints1, dtype=np.float64),
        "keypoints2": np.asarray(model.keypoints2, dtype=np.float64),
        "matches": np.asarray(model.matches, dtype=np.int64),
        "plane": None if model.plane is None else model.plane.model_dump(exclude_none=True),
    }
    return i, parse_pair(doc).verify(0).inliers


def _verify_json_fast(i: int) -> tuple[int, np.ndarray]:
    return i, parse_pair(_TEXTS[i]).verify(0).inliers


def run_local(
    path: str,
    fn: Callable[[int], tuple[int, np.ndarray]],
    indices: Sequence[int],
    processes: int,
    n_flight: int,
) -> Row:
    """``fn`` over ``indices`` in this process or in forked children; the time scaled from
    the pairs run to the flight's."""
    t0 = time.perf_counter()
    here, children = _cpu(resource.RUSAGE_SELF), _cpu(resource.RUSAGE_CHILDREN)
    if processes == 1:
        found = dict(map(fn, indices))
    else:
        with multiprocessing.get_context("fork").Pool(processes) as pool:
            found = dict(pool.imap_unordered(fn, indices, chunksize=CHUNK_PAIRS))
    seconds = (time.perf_counter() - t0) * n_flight / len(indices)
    row = Row(path, processes, seconds, len(indices), found)
    if processes > 1:  # the pool's children are reaped when it ends
        row.cpu_outside = _cpu(resource.RUSAGE_SELF) - here
        row.cpu_children = _cpu(resource.RUSAGE_CHILDREN) - children
    else:
        row.cpu_self = _cpu(resource.RUSAGE_SELF) - here
    return row


def cpu_per_pair(row: Row) -> float | None:
    """CPU seconds a pair cost on this row, all processes together (None: not measured)."""
    if row.cpu_self is not None:
        return row.cpu_self / row.pairs
    if row.cpu_outside is None or row.cpu_children is None:
        return None
    return (row.cpu_outside + row.cpu_children) / row.pairs


_CPU_LINE = re.compile(rb"CPU ([0-9.]+) s here, ([0-9.]+) s in child processes")
_TIMELINE = re.compile(rb"timeline \(s from the process's start\): (.*)")
_TIMELINE_CPU = re.compile(rb"CPU here \(s from the process's start\): (.*)")
#: The steps of ``hmcc flight --timings``, in the order the timeline table gives them.
TIMELINE_STEPS = (
    "imports",
    "read",
    "parsed",
    "shared file",
    "children warm",
    "first result",
    "last result",
    "exit",
)


def timeline(stderr: bytes, line: re.Pattern[bytes] = _TIMELINE) -> dict[str, float]:
    """``hmcc flight --timings``'s timeline: step -> seconds from the command's start (wall
    clock, or with ``_TIMELINE_CPU`` the command's own CPU seconds)."""
    match = line.search(stderr)
    if match is None:
        return {}
    steps = (part.rsplit(" ", 1) for part in match[1].decode().split(", "))
    return {step: float(t) for step, t in steps}


#: The ``hmcc flight`` row with ``--result inliers``.
INLIERS = "--result inliers"


def run_cli(path: str, file: Path, processes: int, n: int, *extra: str) -> tuple[Row, float, float]:
    """``hmcc flight FILE --processes N`` as a command, timed whole (start, reading the file,
    children, writing the lines); its own report of the CPU time here and in its children.
    Returns the row and the command's (here, children) CPU seconds."""
    with tempfile.TemporaryDirectory(prefix="bench-flight-") as folder:
        out = Path(folder) / "out.jsonl"
        cmd = [sys.executable, "-m", "hmcc_cli", "flight", str(file)]
        cmd += ["--processes", str(processes), "-o", str(out), "--timings", *extra]
        t0 = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, check=False)
        seconds = time.perf_counter() - t0
        if done.returncode != 0:
            raise RuntimeError(f"{cmd}: {done.stderr.decode()[-2000:]}")
        found = {}
        for line in out.read_bytes().splitlines():
            doc = orjson.loads(line)
            if doc["status"] == "finished":
                found[doc["index"]] = np.asarray(doc["result"]["inliers"], dtype=np.int64)
    match = _CPU_LINE.search(done.stderr)
    assert match is not None, done.stderr
    here, children = float(match[1]), float(match[2])
    row = Row(path, processes, seconds, n, found, cpu_outside=here, cpu_children=children)
    row.extra["timeline_s"] = timeline(done.stderr)
    row.extra["timeline_cpu_s"] = timeline(done.stderr, _TIMELINE_CPU)
    return row, here, children


def cutover(sim: SimulatedFlight, sizes: Sequence[int], processes: int) -> list[dict[str, Any]]:
    """``hmcc flight`` on the first n pairs of the flight (a binary file), verified in its own
    process against ``processes`` children: where the children start to pay."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-cutover-") as folder:
        for n in sizes:
            pairs = sim.body["pairs"][:n]
            names = {p["image1"] for p in pairs} | {p["image2"] for p in pairs}
            images = {k: v for k, v in sim.body["images"].items() if k in names}
            file = Path(folder) / f"flight-{n}.msgpack"
            write_flight_file(file, images, pairs, plane=sim.body["plane"])
            here, _, _ = run_cli("in process", file, processes, n, "--in-process-max", str(n))
            pool, _, _ = run_cli("pool", file, processes, n, "--in-process-max", "0")
            rows.append(
                {
                    "pairs": n,
                    "in_process_s": here.seconds,
                    "pool_s": pool.seconds,
                    "processes": processes,
                    "faster": "in process" if here.seconds < pool.seconds else "pool",
                }
            )
            print(f"  cut-over {n}: in process {here.seconds:.2f} s, pool {pool.seconds:.2f} s")
    return rows


def run_compute_pool(flight: Flight, processes: int) -> Row:
    """The local runner of ``hmcc flight``: spawned children, results as stored JSON."""
    pool = ComputePool(processes)
    try:
        pool.start()
        t0 = time.perf_counter()
        found = {}
        for i, outcome in pool.map_flight(flight):
            _, body = unpack(outcome.pack())
            found[i] = np.asarray(orjson.loads(body)["inliers"], dtype=np.int64)
        seconds = time.perf_counter() - t0
    finally:
        pool.close(wait=True)
    n = len(flight.pairs)
    return Row("hmcc flight --processes", processes, seconds, n, found)


# --------------------------------------------------------------------------- HTTP rows


class CountingTransport(httpx.HTTPTransport):
    """An httpx transport that counts the request bytes it sends (bodies go in pieces, with
    their length)."""

    def __init__(self) -> None:
        super().__init__()
        self.sent = 0

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        self.sent += int(request.headers.get("Content-Length", 0))
        return super().handle_request(request)


def peak_rss(pid: int) -> int:
    """The process's peak resident set (bytes), from /proc."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmHWM for {pid}")


@dataclass
class Service:
    """A running service of the HTTP rows: its URL, its API process, and the processes whose
    CPU time is measured: ``serial`` (outside the compute: the API, Redis, the RQ workers' own
    processes) and ``compute_parents`` (whose children compute: the API in embedded mode, the
    RQ workers)."""

    url: str
    api: Proc
    serial: dict[str, int]
    compute_parents: list[int]


def service_cpu(service: Service) -> dict[str, float]:
    """CPU seconds so far, by part: each serial process's own (``/proc/PID/stat``: all its
    threads), and ``compute``: the compute children's, live (with their own ended children)
    and ended (the parents' waited-for children)."""
    cpu: dict[str, float] = {"client": _cpu(resource.RUSAGE_SELF)}
    for name, pid in service.serial.items():
        own = process_cpu_s(pid)
        cpu[name] = 0.0 if own is None else own[0]
    compute = 0.0
    for pid in service.compute_parents:
        own = process_cpu_s(pid)
        compute += 0.0 if own is None else own[1]
        for child in compute_children(pid):
            mine = process_cpu_s(child)
            compute += 0.0 if mine is None else mine[0] + mine[1]
    cpu["compute"] = compute
    return cpu


def run_http(
    path: str,
    service: Service,
    sim: SimulatedFlight,
    processes: int,
    binary: bool = True,
    columns: bool = True,
) -> Row:
    """The flight through the service with :class:`HmccClient` (warmed first); the CPU seconds
    of the client (this process), the API, Redis and the RQ workers' own processes (outside
    the compute) against the compute children's, over the timed flight."""
    transport = CountingTransport()
    body = sim.body
    failed = 0
    with HmccClient(service.url, timeout=120.0, transport=transport) as client:
        flight = functools.partial(
            client.verify_flight,
            body["images"],
            params={"result": "inliers"},
            plane=body["plane"],
            binary=binary,
            columns=columns,
        )
        # a running service is warm (as the core row runs after a warm-up): a first small
        # flight, untimed and not counted, before the timed one
        for _ in flight(body["pairs"][:WARM_PAIRS]):
            pass
        transport.sent = 0
        before = service_cpu(service)
        t0 = time.perf_counter()
        inliers = {}
        for item in flight(body["pairs"]):
            if item.status == "finished" and item.result is not None:
                inliers[item.index] = item.result.inliers
            else:
                failed += 1
        seconds = time.perf_counter() - t0
        after = service_cpu(service)  # the client's CPU: not the benchmark's arrays below
        found = {i: np.asarray(v, dtype=np.int64) for i, v in inliers.items()}
    n = len(body["pairs"])
    row = Row(path, processes, seconds, n, found, transport.sent, peak_rss(service.api.proc.pid))
    parts = {k: after[k] - before[k] for k in after}
    row.cpu_children = parts["compute"]
    row.cpu_outside = sum(v for k, v in parts.items() if k != "compute")
    row.extra["failed"] = failed
    row.extra["cpu_s"] = parts
    return row


@contextmanager
def embedded_service(processes: int) -> Iterator[Service]:
    api, url = start_api(service_env(HMCC_EMBEDDED_WORKERS=str(processes)))
    with running(api):
        wait_until(lambda: httpx.get(f"{url}/readyz").status_code == 200, 30)
        yield Service(url, api, {"api": api.proc.pid}, [api.proc.pid])


@contextmanager
def rq_service(workers: int) -> Iterator[Service]:
    with redis_server() as redis:
        env = service_env(REDIS_URL=redis.url)
        api, url = start_api(env)
        procs = [start_worker(env, f"flight-{k}") for k in range(workers)]
        with running(*procs, api):
            wait_for_workers(url, workers)
            assert redis.proc is not None
            serial = {"api": api.proc.pid, "redis": redis.proc.pid}
            serial |= {f"worker {k}": w.proc.pid for k, w in enumerate(procs)}
            yield Service(url, api, serial, [w.proc.pid for w in procs])


# --------------------------------------------------------------------------- COLMAP


def colmap_row(sim: SimulatedFlight, indices: Sequence[int]) -> Row | None:
    """pycolmap's two-view geometry (its default options) on the sampled pairs, if installed."""
    try:
        import pycolmap  # type: ignore[import-not-found]
    except ImportError:
        return None
    cam = sim.body["images"][next(iter(sim.body["images"]))]["camera"]
    camera = pycolmap.Camera(
        model="SIMPLE_PINHOLE",
        width=cam["width"],
        height=cam["height"],
        params=[cam["focal"], (cam["width"] - 1) / 2 + 0.5, (cam["height"] - 1) / 2 + 0.5],
    )
    found = {}
    t0 = time.perf_counter()
    for i in indices:
        pair = sim.body["pairs"][i]
        kp1 = sim.body["images"][pair["image1"]]["keypoints"] + 0.5  # COLMAP: pixel centres
        kp2 = sim.body["images"][pair["image2"]]["keypoints"] + 0.5
        m = pair["matches"]
        geometry = pycolmap.estimate_calibrated_two_view_geometry(
            camera, kp1, camera, kp2, m.astype(np.uint32)
        )
        inl = np.asarray(geometry.inlier_matches)
        if len(inl):  # inlier_matches are rows of matches: back to indices into the pair's list
            key = {(int(a), int(b)): k for k, (a, b) in enumerate(m)}
            found[i] = np.sort([key[(int(a), int(b))] for a, b in inl])
        else:
            found[i] = np.zeros(0, dtype=np.int64)
    seconds = (time.perf_counter() - t0) * len(sim.body["pairs"]) / len(indices)
    return Row("COLMAP two-view geometry", 1, seconds, len(indices), found)


# --------------------------------------------------------------------------- report


def quality(row: Row, truth: dict[str, np.ndarray], ids: list[str]) -> tuple[float, float]:
    kept = hit = true = 0
    for i, inliers in row.found.items():
        t = truth[ids[i]]
        kept += len(inliers)
        hit += len(np.intersect1d(inliers, t))
        true += len(t)
    for i in set(range(len(ids))) - set(row.found) if row.pairs == len(ids) else ():
        true += len(truth[ids[i]])  # a pair that failed found nothing
    return (hit / kept if kept else 0.0), (hit / true if true else 0.0)


def report(
    rows: list[Row],
    sim: SimulatedFlight,
    json_bytes: int,
    before_bytes: int,
    args: argparse.Namespace,
) -> dict[str, Any]:
    ids = [p["id"] for p in sim.body["pairs"]]
    n = len(ids)
    core = next(r for r in rows if r.path == "core" and r.processes == 1)
    table = Table(
        "A whole flight, every path",
        [
            "path",
            "procs",
            "time s",
            "pairs/s",
            "x core-1",
            "pairs run",
            "MiB sent",
            "API peak RSS MiB",
            "precision",
            "recall",
            "serial %",
            "CPU / pair x core 1",
            "Amdahl x4",
            "x16",
            "x64",
        ],
        [],
        left=1,
    )
    records = []
    core_cpu = cpu_per_pair(core)
    for r in rows:
        precision, recall = quality(r, sim.truth, ids)
        share = serial_share(r)
        cpu = cpu_per_pair(r)
        predicted = {} if share is None else {f"x{k}": amdahl(share, k) for k in (4, 16, 64)}
        record = {
            "path": r.path,
            "processes": r.processes,
            "seconds": r.seconds,
            "pairs_per_s": n / r.seconds,
            "vs_core_1": r.seconds / core.seconds,
            "pairs_run": r.pairs,
            "sampled": r.pairs < n,
            "bytes_sent": r.bytes_sent,
            "api_peak_rss": r.api_rss,
            "precision": precision,
            "recall": recall,
            "cpu_outside_s": r.cpu_outside,
            "cpu_children_s": r.cpu_children,
            "serial_share": share,
            "amdahl_speedup": predicted or None,
            "cpu_per_pair_vs_core_1": None if cpu is None or not core_cpu else cpu / core_cpu,
            **r.extra,
        }
        records.append(record)
        table.rows.append(
            [
                r.path,
                str(r.processes),
                fmt(r.seconds, 1),
                fmt(n / r.seconds, 0),
                fmt(r.seconds / core.seconds, 2),
                f"{r.pairs}" + ("" if r.pairs == n else " (sampled)"),
                "" if r.bytes_sent is None else fmt(r.bytes_sent / 2**20, 0),
                "" if r.api_rss is None else fmt(r.api_rss / 2**20, 0),
                fmt(precision, 4),
                fmt(recall, 4),
                "" if share is None else fmt(100 * share, 1),
                "" if cpu is None or not core_cpu else fmt(cpu / core_cpu, 2),
                *(fmt(predicted[f"x{k}"], 1) if predicted else "" for k in (4, 16, 64)),
            ]
        )
    by = {(rec["path"], rec["processes"]): rec for rec in records}
    core_rec = by[("core", 1)]
    targets = []
    for path in (
        "hmcc flight, JSON file",
        "hmcc flight, binary file",
        f"hmcc flight, binary file, {INLIERS}",
        "hmcc flight, columns file",
        f"hmcc flight, columns file, {INLIERS}",
    ):
        rec = by.get((path, 2))
        if rec is None:
            continue
        targets += [
            {
                "target": f"{path}, 2 processes: serial share <= 3 % of the CPU time",
                "value": rec["serial_share"],
                "ok": rec["serial_share"] <= 0.03,
            },
            {
                "target": f"{path}, 2 processes: whole command <= 0.55 x core 1 process",
                "value": rec["vs_core_1"],
                "ok": rec["vs_core_1"] <= 0.55,
            },
            {
                "target": f"{path}: precision and recall equal to the core's",
                "value": [rec["precision"], rec["recall"]],
                "ok": abs(rec["precision"] - core_rec["precision"]) <= 1e-9
                and abs(rec["recall"] - core_rec["recall"]) <= 1e-9,
            },
        ]
    for path in ("HTTP + RQ", "HTTP embedded"):
        rec = by.get((path, 2))
        if rec is None:
            continue
        targets += [
            {
                "target": f"{path}, 2 processes: serial share (API, client, Redis, RQ workers' "
                "own processes) <= 3 % of the CPU time",
                "value": rec["serial_share"],
                "ok": rec["serial_share"] <= 0.03,
            },
            {
                "target": f"{path}, 2 processes: time <= 0.6 x core 1 process",
                "value": rec["vs_core_1"],
                "ok": rec["vs_core_1"] <= 0.6,
            },
            {
                "target": f"{path}: API peak RSS <= 1 GiB",
                "value": rec["api_peak_rss"] / GIB,
                "ok": rec["api_peak_rss"] <= GIB,
            },
            {
                "target": f"{path}: bytes sent <= 40 % of the batch JSON before (keypoints "
                "with every pair)",
                "value": rec["bytes_sent"] / before_bytes,
                "ok": rec["bytes_sent"] <= 0.4 * before_bytes,
            },
            {
                "target": f"{path}: precision and recall within 0.002 of the core",
                "value": [rec["precision"], rec["recall"]],
                "ok": abs(rec["precision"] - core_rec["precision"]) <= 0.002
                and abs(rec["recall"] - core_rec["recall"]) <= 0.002,
            },
        ]
    return {"table": table, "records": records, "targets": targets}


def write(result: dict[str, Any], out: Path, header: list[str]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    table: Table = result.pop("table")
    (out / "flight.json").write_text(
        json.dumps(jsonable(with_code_hash(result, __file__)), indent=2) + "\n"
    )
    lines = [
        "# Flight benchmark (`python -m benchmarks.bench_flight`)",
        "",
        *header,
        "",
        table.markdown(),
        "",
        "| target | value | met |",
        "|---|---|---|",
    ]
    for t in result["targets"]:
        v = t["value"]
        value = ", ".join(fmt(x, 4) for x in v) if isinstance(v, list) else fmt(v, 2)
        lines.append(f"| {t['target']} | {value} | {'yes' if t['ok'] else 'NO'} |")
    timed = [r for r in result["records"] if r.get("timeline_s")]
    if timed:
        lines += [
            "",
            "**Timeline** of the `hmcc flight` rows (`--timings`): when each step ended, in "
            "seconds from the command's start; children warm: each child has run a first "
            "short task (they start, in the background, once the file is read: while it is parsed)",
            "",
            "| path | procs | " + " | ".join(TIMELINE_STEPS) + " |",
            "|:---|---:|" + "---:|" * len(TIMELINE_STEPS),
        ]
        for r in timed:
            steps = r["timeline_s"]
            cells = [fmt(steps[k], 2) if k in steps else "" for k in TIMELINE_STEPS]
            lines.append(f"| {r['path']} | {r['processes']} | " + " | ".join(cells) + " |")
    timed_cpu = [r for r in result["records"] if r.get("timeline_cpu_s")]
    if timed_cpu:
        lines += [
            "",
            "**Where the command's own CPU goes** (`--timings`): its process's CPU seconds "
            "(all threads, not its children) when each step ended; the serial share",
            "",
            "| path | procs | " + " | ".join(TIMELINE_STEPS) + " |",
            "|:---|---:|" + "---:|" * len(TIMELINE_STEPS),
        ]
        for r in timed_cpu:
            steps = r["timeline_cpu_s"]
            cells = [fmt(steps[k], 2) if k in steps else "" for k in TIMELINE_STEPS]
            lines.append(f"| {r['path']} | {r['processes']} | " + " | ".join(cells) + " |")
    parted = [r for r in result["records"] if r.get("cpu_s")]
    if parted:
        lines += [
            "",
            "**The service rows' CPU seconds by process** over the timed flight: outside the "
            "compute (client, API, Redis, the RQ workers' own processes) and in it",
            "",
            "| path | procs | client | API | Redis | RQ workers | compute | serial % |",
            "|:---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in parted:
            cpu = r["cpu_s"]
            workers = sum(v for k, v in cpu.items() if k.startswith("worker"))
            cells = [
                fmt(cpu["client"], 2),
                fmt(cpu["api"], 2),
                fmt(cpu["redis"], 2) if "redis" in cpu else "",
                fmt(workers, 2) if "redis" in cpu else "",
                fmt(cpu["compute"], 2),
                fmt(100 * r["serial_share"], 1),
            ]
            lines.append(f"| {r['path']} | {r['processes']} | " + " | ".join(cells) + " |")
    cut = result.get("cutover")
    if cut:
        lines += [
            "",
            f"**Cut-over**: `hmcc flight` on the first n pairs (binary file, whole command), "
            f"in its own process against {cut[0]['processes']} children",
            "",
            "| pairs | in process s | pool s | faster |",
            "|---:|---:|---:|:---|",
        ]
        lines += [
            f"| {c['pairs']} | {c['in_process_s']:.2f} | {c['pool_s']:.2f} | {c['faster']} |"
            for c in cut
        ]
    (out / "flight.md").write_text("\n".join(lines) + "\n")
    print(table.text())
    for t in result["targets"]:
        print(f"{'ok ' if t['ok'] else 'NO '} {t['target']}: {t['value']}")


# --------------------------------------------------------------------------- main


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="a small flight (600 pairs)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--sample", type=int, default=1500, help="pairs the slow rows run")
    p.add_argument("--no-http", action="store_true", help="skip the service rows")
    p.add_argument(
        "--rq-workers",
        type=lambda v: [int(x) for x in v.split(",")],
        default=[2, 3],
        help="worker counts of the HTTP + RQ rows (default 2,3; the targets use 2)",
    )
    p.add_argument("--scale-only", action="store_true", help="only the core and hmcc flight rows")
    ints = lambda v: [int(x) for x in v.split(",") if x]  # noqa: E731
    p.add_argument("--core-processes", type=ints, default=[1, 2], help="default 1,2")
    p.add_argument("--cli-processes", type=ints, default=[2], help="default 2")
    p.add_argument(
        "--http-processes",
        type=ints,
        default=[],
        help="embedded children and RQ workers of extra service rows, run with --scale-only too",
    )
    p.add_argument(
        "--magsac-processes",
        type=ints,
        default=[],
        help="process counts of OpenCV MAGSAC++ rows on the sample (--scale-only too)",
    )
    p.add_argument("--cutover", type=ints, default=None, help="pair counts of the cut-over table")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    global _FLIGHT, _TEXTS
    args = parse_args(argv)
    options = QUICK if args.quick else FlightOptions()
    t0 = time.perf_counter()
    sim = simulate_flight(options, args.seed)
    n = len(sim.body["pairs"])
    print(
        f"flight: {len(sim.body['images'])} images, {n} pairs, {sim.matches} matches "
        f"(simulated in {time.perf_counter() - t0:.1f} s)"
    )
    warm_up_opencv()
    _TEXTS = [pair_json(sim, i) for i in range(n)]
    json_bytes = sum(map(len, _TEXTS))
    before_bytes = batch_json_before_bytes(sim, sample_indices(n, 2000, seed=1))
    everything = list(range(n))
    sample = sample_indices(n, args.sample)
    rows: list[Row] = []

    def add(row: Row | None) -> None:
        if row is not None:
            rows.append(row)
            print(f"  {row.path} ({row.processes}): {row.seconds:.1f} s", flush=True)

    _FLIGHT = core_flight(sim)
    # The flight as simulated, its texts and arrays are kept to the end: frozen, as ``hmcc
    # flight`` freezes the flight it read, so that the collections set off by the rows do not
    # walk them again and again (the HTTP rows' client, this process, spent most of its CPU so)
    gc.freeze()
    for procs in sorted(set(args.core_processes) | {1}):
        add(run_local("core", _verify_core, everything, procs, n))
    with tempfile.TemporaryDirectory(prefix="bench-flight-files-") as folder:
        files = {
            "JSON file": Path(folder) / "flight.json",
            "binary file": Path(folder) / "flight.msgpack",
            "columns file": Path(folder) / "columns.msgpack",
        }
        files["JSON file"].write_bytes(orjson.dumps(sim.body, option=orjson.OPT_SERIALIZE_NUMPY))
        body = dict(sim.body)
        images, pairs = body.pop("images"), body.pop("pairs")
        write_flight_file(files["binary file"], images, pairs, **body)
        write_flight_columns(files["columns file"], images, pairs, **body)
        sizes = {k: f.stat().st_size for k, f in files.items()}
        for procs in args.cli_processes:
            for kind, file in files.items():
                # on the children however small the flight (--quick): the rows measure them
                row, _, _ = run_cli(f"hmcc flight, {kind}", file, procs, n, "--in-process-max", "0")
                add(row)
            # the result the core rows keep and the HTTP rows ask for (inliers, model, time)
            for kind in ("binary file", "columns file"):
                path, file = f"hmcc flight, {kind}, {INLIERS}", files[kind]
                extra = ("--in-process-max", "0", "--result", "inliers")
                add(run_cli(path, file, procs, n, *extra)[0])
    cut = cutover(sim, args.cutover, 2) if args.cutover else []
    if not args.scale_only:
        for path, fn in (
            ("pair JSON, full model", _verify_json_model),
            ("pair JSON, array parser", _verify_json_fast),
        ):
            for procs in (1, 2):
                add(replace(run_local(path, fn, sample, procs, n), bytes_sent=json_bytes))
    for procs in args.http_processes:  # the scaling rows of the service (--scale-only too)
        try:  # on a lent machine: the rows that ran are written, whatever the service did
            with embedded_service(procs) as service:
                add(run_http("HTTP embedded", service, sim, procs))
            with rq_service(procs) as service:
                add(run_http("HTTP + RQ", service, sim, procs))
        except Exception as exc:  # noqa: BLE001
            print(f"  the service rows with {procs} processes failed: {exc!r}", flush=True)
    if not args.no_http and not args.scale_only:
        with embedded_service(2) as service:
            add(run_http("HTTP embedded", service, sim, 2))
            # what pairs as columns buy: the same with each pair an object of the body
            add(run_http("HTTP embedded, pairs as rows", service, sim, 2, columns=False))
        for workers in args.rq_workers:
            with rq_service(workers) as service:
                add(run_http("HTTP + RQ", service, sim, workers))
                if workers == 2:  # what MessagePack buys: the same with JSON bodies
                    add(run_http("HTTP + RQ, JSON bodies", service, sim, workers, binary=False))
    if args.magsac_processes:  # the baseline's scaling rows (--scale-only too)
        _FLIGHT = core_flight(sim, "magsac++")
        for procs in args.magsac_processes:
            add(run_local("OpenCV magsac++", _verify_core, sample, procs, n))
    if not args.scale_only:
        for method in ("magsac++", "usac-accurate"):
            _FLIGHT = core_flight(sim, method)
            for procs in (1, 2):
                add(replace(run_local(f"OpenCV {method}", _verify_core, sample, procs, n)))
        add(colmap_row(sim, sample[: max(1, args.sample // 10)]))

    env = environment()
    header = [
        f"Flight: {len(sim.body['images'])} images, {n} pairs, {sim.matches} matches "
        f"({sim.matches / n:.0f} a pair, {options.outlier_ratio:.0%} outliers), seed {args.seed}; "
        f"per-pair JSON would be {json_bytes / 2**20:.0f} MiB, batch JSON with the keypoints of "
        f"every pair (before images carried them) {before_bytes / 2**20:.0f} MiB.",
        f"Machine: {env.get('cpu_count')} cores, {env.get('platform')}; "
        f"commit {env.get('git_commit')}.",
        "Sampled rows ran the pairs shown and are scaled to the flight's pair count.",
        f"Flight files: JSON {sizes['JSON file'] / 2**20:.0f} MiB, binary (MessagePack, raw "
        f"arrays) {sizes['binary file'] / 2**20:.0f} MiB, binary with the pairs as columns "
        f"{sizes['columns file'] / 2**20:.0f} MiB. `hmcc flight` rows: the whole "
        "command, timed from its start to its exit; serial % = CPU outside the compute "
        "children / all CPU (the command's process against its children; for the forked core "
        "rows, the benchmark's process against its pool's); Amdahl xN = 1 / (s + (1 - s) / N).",
    ]
    result = report(rows, sim, json_bytes, before_bytes, args)
    result.update(
        environment=env,
        flight={
            "images": len(sim.body["images"]),
            "pairs": n,
            "matches": sim.matches,
            "json_bytes": json_bytes,
            "batch_json_before_bytes": before_bytes,
            "options": options.__dict__,
            "seed": args.seed,
            "file_bytes": sizes,
        },
        cutover=cut,
    )
    write(result, args.out if not args.quick else args.out / "quick", header)
    return 0 if all(t["ok"] for t in result["targets"]) else 1


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    raise SystemExit(main())
