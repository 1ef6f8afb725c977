"""Service settings, read once from ``HMCC_*`` environment variables (documented in the README).

Nonsense fails at start-up (pydantic-settings validates), not on the first request.
"""

from __future__ import annotations

from functools import lru_cache

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["Settings", "get_settings"]


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="HMCC_", extra="ignore", frozen=True)

    #: Queue backend. Unset: jobs run in-process (embedded). ``redis://host:6379/0``: RQ workers.
    redis_url: str | None = Field(default=None, validation_alias="REDIS_URL")
    #: RQ queue name (workers listen on the same name).
    queue_name: str = "hmcc"
    #: Child processes that verify pairs in embedded mode (one per core is the usual choice).
    embedded_workers: int = Field(default=2, ge=1, le=64)
    #: Embedded mode: results kept in memory at most (megabytes, each ended job counted with
    #: its bookkeeping, ``embedded.KEPT_JOB_BYTES``); the oldest go first.
    result_memory_mb: int = Field(default=256, ge=1)

    #: Seconds a chunk of pairs (and then each of its pairs) may take before its process is
    #: killed and the pairs still running fail with ``timeout``.
    job_timeout_s: int = Field(default=60, ge=1, le=3600)
    #: A running job's worker renews it every max(1, min(2, grace)) s; a job not renewed for
    #: this many seconds more counts as abandoned (worker died) and is retried once, then failed.
    worker_grace_s: int = Field(default=10, ge=1, le=600)
    #: Seconds a finished job's result is kept (a batch's: as long as the batch), and a failed
    #: job's error. At least 10 s.
    result_ttl_s: int = Field(default=3600, ge=10)
    failure_ttl_s: int = Field(default=86400, ge=10)

    #: Queued jobs above which submissions get 429 + Retry-After.
    max_queue_depth: int = Field(default=1000, ge=1)
    #: Seconds suggested in Retry-After.
    retry_after_s: int = Field(default=5, ge=1, le=3600)
    #: Request bodies larger than this get 413 (bytes).
    max_body_bytes: int = Field(default=64 * 1024 * 1024, ge=1024)
    #: Bytes of request bodies held (read, and then parsed) at once, across requests. Each
    #: request holds the bytes of its body that have arrived, until it is answered; bytes that
    #: do not fit wait for room (at most ``body_wait_s``, then 503 + Retry-After). Bounds the
    #: API's memory whatever the number of clients, and idle connections hold nothing.
    body_budget_bytes: int = Field(default=128 * 1024 * 1024, ge=1024)
    body_wait_s: float = Field(default=30.0, gt=0, le=600)
    #: Deadlines of a body (408 and the connection closed when missed): it must arrive in
    #: full within ``body_timeout_s`` of the request's head, and at ``body_min_bytes_per_s``
    #: at least after the first ``body_grace_s``: by ``body_grace_s + n / body_min_bytes_per_s``
    #: seconds after the head, more than ``n`` bytes of it. Time spent waiting for the budget
    #: does not count.
    body_timeout_s: float = Field(default=300.0, gt=0, le=3600)
    body_grace_s: float = Field(default=10.0, gt=0, le=600)
    body_min_bytes_per_s: int = Field(default=16 * 1024, ge=1)

    #: On SIGTERM the API refuses new work at once (503 + Retry-After; ``/readyz`` 503) and
    #: keeps answering reads until the jobs it accepted have ended, at most
    #: ``shutdown_drain_s`` (embedded mode; RQ jobs live in Redis), then closes: requests
    #: still open then get ``shutdown_timeout_s`` more to end before they are cut.
    shutdown_drain_s: float = Field(default=20.0, ge=0, le=3600)
    shutdown_timeout_s: int = Field(default=3, ge=0, le=600)

    #: Batches: pairs per job at most, and matches per job at most (a job stops at either;
    #: a batch is also split into at least 8 jobs, and at least one a worker, of 16 pairs or
    #: more, see routes/batches.py). Unset: :meth:`chunk_limits`' defaults.
    batch_chunk_pairs: int | None = Field(default=None, ge=1, le=10_000)
    batch_chunk_matches: int | None = Field(default=None, ge=1)
    #: Pairs in one batch at most.
    max_batch_pairs: int = Field(default=10_000, ge=1)

    #: When set, every /v1 route requires this value in the ``X-API-Key`` header.
    api_key: SecretStr | None = None
    #: Origins allowed by CORS; empty (the default) sends no CORS headers at all.
    cors_origins: list[str] = []

    #: Bind address and port of ``hmcc serve``.
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=1, le=65535)
    #: ``INFO``, ``DEBUG``, ...; logs are one JSON object per line on stderr.
    log_level: str = "INFO"

    def chunk_limits(self) -> tuple[int, int]:
        """A batch job's pairs and matches at most: as set, else 1024 and 1 000 000 with RQ,
        where a job costs bookkeeping outside the compute (in its worker, in Redis and in the
        API) that larger jobs amortise, and 256 and 256 000 embedded, where a job costs little
        and smaller jobs end more evenly."""
        rq = self.redis_url is not None
        return (
            self.batch_chunk_pairs or (1024 if rq else 256),
            self.batch_chunk_matches or (1_000_000 if rq else 256_000),
        )


@lru_cache
def get_settings() -> Settings:
    return Settings()
