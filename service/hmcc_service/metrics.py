"""Prometheus metrics of ``/metrics``: HTTP requests and CPU time (this API process, and its
compute children in embedded mode), queue depth and job durations per stage and failures (all
workers: read from the queue backend at scrape time).

The CPU counters give the serial share of a running service: the API's CPU seconds against
its children's (embedded), or against the workers' (RQ: their own process metrics), over the
same interval. The API's share caps what more workers can add (Amdahl's law)."""

from __future__ import annotations

import time
from collections.abc import Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from hmcc_worker.metrics import STAGE_BUCKETS_S, process_cpu_s

from .queue import JobQueue, QueueUnavailable

__all__ = ["API_CPU", "COMPUTE_CPU", "HttpMetrics", "Metrics"]

#: CPU seconds of this API process (all its threads), and of its compute children.
API_CPU = "hmcc_api_cpu_seconds"
COMPUTE_CPU = "hmcc_compute_cpu_seconds"


class _CpuCollector(Collector):
    def __init__(self, queue: JobQueue) -> None:
        self._queue = queue

    def collect(self) -> Iterator[CounterMetricFamily]:
        own = process_cpu_s()
        if own is not None:
            api = CounterMetricFamily(
                API_CPU, "CPU seconds of this API process (all its threads, not its children)"
            )
            api.add_metric([], own[0])
            yield api
        children = self._queue.compute_cpu_s()
        if children is not None:
            compute = CounterMetricFamily(
                COMPUTE_CPU,
                "CPU seconds of this API process's compute children (embedded mode), "
                "ended ones included",
            )
            compute.add_metric([], children)
            yield compute


class _JobCollector(Collector):
    def __init__(self, queue: JobQueue) -> None:
        self._queue = queue

    def collect(self) -> Iterator[GaugeMetricFamily | HistogramMetricFamily | CounterMetricFamily]:
        up = GaugeMetricFamily("hmcc_queue_up", "1 if the queue backend answered this scrape")
        depth = GaugeMetricFamily("hmcc_queue_depth", "Jobs waiting in the queue")
        try:
            depth.add_metric([], self._queue.depth_sync())
            snap = self._queue.job_metrics()
        except QueueUnavailable:
            up.add_metric([], 0)
            yield up
            return
        up.add_metric([], 1)
        yield up
        yield depth
        stages = HistogramMetricFamily(
            "hmcc_job_stage_seconds",
            "Time per stage of verified pairs (compute = all stages, job = with parsing)",
            labels=["stage"],
        )
        les = [*(repr(b) for b in STAGE_BUCKETS_S), "+Inf"]
        for stage, (cumulative, total) in sorted(snap.stages.items()):
            stages.add_metric([stage], list(zip(les, cumulative, strict=True)), total)
        yield stages
        outcomes = CounterMetricFamily(
            "hmcc_pairs",
            "Pairs processed by outcome (failed = input the core refused)",
            labels=["outcome"],
        )
        for outcome, count in sorted(snap.outcomes.items()):
            outcomes.add_metric([outcome], count)
        yield outcomes
        failures = CounterMetricFamily(
            "hmcc_job_failures",
            "Failed job attempts by reason (AbandonedJobError = worker died, "
            "JobTimeoutException, or the exception type)",
            labels=["reason"],
        )
        for reason, count in sorted(snap.failures.items()):
            failures.add_metric([reason], count)
        yield failures


class Metrics:
    """The registry of one app (tests create many apps; each has its own)."""

    def __init__(self, queue: JobQueue) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "hmcc_http_requests",
            "HTTP requests by route template, method and status",
            ["route", "method", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "hmcc_http_request_seconds",
            "HTTP request latency by route template",
            ["route"],
            buckets=(0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10, 30, 60),
            registry=self.registry,
        )
        self.registry.register(_JobCollector(queue))
        self.registry.register(_CpuCollector(queue))


class HttpMetrics:
    """ASGI middleware counting requests by route template (not raw path: bounded labels)."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        status = 500

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            self.metrics.requests.labels(template, scope["method"], str(status)).inc()
            self.metrics.latency.labels(template).observe(time.perf_counter() - t0)
