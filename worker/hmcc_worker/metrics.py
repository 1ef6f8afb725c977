"""Job metrics that outlive the process that ran the job.

Workers run on other machines than the API, so per-stage durations and failure counts are
aggregated as flat counters (one hash in Redis, or a dict in embedded mode) and turned into
Prometheus histograms by the API's ``/metrics`` (see ``hmcc_service.metrics``).

Counter fields: ``stage|<stage>|<le>`` (observations <= le seconds, non-cumulative bucket),
``stage_sum|<stage>``, ``outcome|<finished|failed>``, ``failure|<reason>``.
"""

from __future__ import annotations

import os
import resource
import threading
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .protocol import METRICS_KEY

if TYPE_CHECKING:
    from .outcomes import PairOutcome

__all__ = [
    "STAGE_BUCKETS_S",
    "JobMetricsSnapshot",
    "MemoryJobMetrics",
    "RedisJobMetrics",
    "children_cpu_s",
    "increments",
    "process_cpu_s",
]

#: Histogram bucket upper bounds, seconds (the last bucket, +Inf, is implicit).
STAGE_BUCKETS_S: tuple[float, ...] = (
    0.0005,
    0.001,
    0.002,
    0.005,
    0.01,
    0.02,
    0.05,
    0.1,
    0.2,
    0.5,
    1.0,
    2.0,
    5.0,
    10.0,
    30.0,
    60.0,
)
_LE = [*(repr(b) for b in STAGE_BUCKETS_S), "+Inf"]
_BOUNDS = np.asarray(STAGE_BUCKETS_S)


@dataclass
class JobMetricsSnapshot:
    """``stages[name] = (cumulative counts per bucket of STAGE_BUCKETS_S + [+Inf], sum_s)``."""

    stages: dict[str, tuple[list[float], float]] = field(default_factory=dict)
    outcomes: dict[str, float] = field(default_factory=dict)
    failures: dict[str, float] = field(default_factory=dict)


def increments(outcomes: Iterable[PairOutcome], job_s: float | None = None) -> dict[str, float]:
    """The counters' increments for ``outcomes`` and a job of ``job_s`` seconds; each stage's
    observations bucketed at once (a chunk's 256 pairs of 8 stages one by one took 1.7 ms of
    the process that records them, the API's in embedded mode)."""
    inc: dict[str, float] = defaultdict(float)
    by_stage: dict[str, list[float]] = defaultdict(list)
    if job_s is not None:
        by_stage["job"].append(job_s * 1e3)
    for outcome in outcomes:
        inc[f"outcome|{outcome.status.value}"] += 1
        for stage, ms in outcome.timings_ms.items():
            by_stage[stage].append(ms)
    for stage, times_ms in by_stage.items():
        seconds = np.asarray(times_ms, dtype=np.float64) / 1e3
        seconds = seconds[np.isfinite(seconds)]
        if not seconds.size:
            continue
        counts = np.bincount(np.searchsorted(_BOUNDS, seconds), minlength=len(_LE))
        for k in np.flatnonzero(counts):
            inc[f"stage|{stage}|{_LE[k]}"] += float(counts[k])
        inc[f"stage_sum|{stage}"] += float(seconds.sum())
    return inc


def _snapshot(counters: Mapping[str, float]) -> JobMetricsSnapshot:
    snap = JobMetricsSnapshot()
    buckets: dict[str, list[float]] = defaultdict(lambda: [0.0] * len(_LE))
    sums: dict[str, float] = defaultdict(float)
    for name, value in counters.items():
        kind, _, rest = name.partition("|")
        if kind == "stage":
            stage, _, le = rest.rpartition("|")
            if le in _LE:
                buckets[stage][_LE.index(le)] += value
        elif kind == "stage_sum":
            sums[rest] += value
        elif kind == "outcome":
            snap.outcomes[rest] = value
        elif kind == "failure":
            snap.failures[rest] = value
    for stage, counts in buckets.items():
        cumulative = [sum(counts[: i + 1]) for i in range(len(counts))]
        snap.stages[stage] = (cumulative, sums[stage])
    return snap


class MemoryJobMetrics:
    """In-process counters (embedded mode)."""

    def __init__(self) -> None:
        self._counters: dict[str, float] = defaultdict(float)
        self._lock = threading.Lock()

    def record(self, outcomes: Iterable[PairOutcome], job_s: float | None = None) -> None:
        """Count the pairs of one job by outcome, their stages' times and the job's time."""
        self.add(increments(outcomes, job_s))

    def add(self, inc: Mapping[str, float], job_s: float | None = None) -> None:
        """Add a job's :func:`increments`, made where its pairs were verified, and count the
        job's time."""
        job = increments((), job_s) if job_s is not None else {}
        with self._lock:
            for k, v in (*inc.items(), *job.items()):
                self._counters[k] += v

    def record_failure(self, reason: str) -> None:
        with self._lock:
            self._counters[f"failure|{reason}"] += 1

    def snapshot(self) -> JobMetricsSnapshot:
        with self._lock:
            return _snapshot(dict(self._counters))


class RedisJobMetrics:
    """The same counters in one Redis hash, shared by every worker and API process."""

    def __init__(self, connection: Any) -> None:
        self._redis = connection

    def record(
        self, outcomes: Iterable[PairOutcome], job_s: float | None = None, pipeline: Any = None
    ) -> None:
        """As :meth:`MemoryJobMetrics.record`; with ``pipeline``, its commands are added to
        that pipeline (executed by the caller, with the job's other writes) rather than sent
        at once."""
        inc = increments(outcomes, job_s)
        if pipeline is not None:
            for k, v in inc.items():
                pipeline.hincrbyfloat(METRICS_KEY, k, v)
            return
        with self._redis.pipeline(transaction=False) as pipe:
            for k, v in inc.items():
                pipe.hincrbyfloat(METRICS_KEY, k, v)
            pipe.execute()

    def record_failure(self, reason: str) -> None:
        self._redis.hincrbyfloat(METRICS_KEY, f"failure|{reason}", 1)

    def snapshot(self) -> JobMetricsSnapshot:
        raw = self._redis.hgetall(METRICS_KEY)
        return _snapshot({_text(k): float(v) for k, v in raw.items()})


def _text(value: bytes | str) -> str:
    return value.decode() if isinstance(value, bytes) else value


def process_cpu_s(pid: int | None = None) -> tuple[float, float] | None:
    """CPU seconds (user + system) of process ``pid`` (None: this one), all its threads, and
    of its children that ended and were waited for, from ``/proc/PID/stat``; None where there
    is no such process (or no ``/proc``)."""
    try:
        stat = Path(f"/proc/{'self' if pid is None else pid}/stat").read_text()
        fields = stat.rsplit(")", 1)[1].split()
        ticks = [int(f) for f in fields[11:15]]  # utime, stime, cutime, cstime
    except (OSError, ValueError, IndexError):
        return None
    hz = os.sysconf("SC_CLK_TCK")
    return (ticks[0] + ticks[1]) / hz, (ticks[2] + ticks[3]) / hz


def children_cpu_s(pids: Iterable[int]) -> float:
    """CPU seconds of this process's children: those that ended and were waited for
    (``getrusage``), and the live ``pids`` (with their own ended children). The compute pool's
    share of the work; the rest of the process's is the serial part."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    total = usage.ru_utime + usage.ru_stime
    for pid in pids:
        cpu = process_cpu_s(pid)
        if cpu is not None:
            total += cpu[0] + cpu[1]
    return total
