"""A small typed client of the hmcc-match HTTP API, for front ends (on httpx).

::

    with HmccClient("http://127.0.0.1:8000", api_key=None) as hmcc:
        job = hmcc.verify(pair)              # submit with ?wait, then long-poll; a Job
        if job.status == "finished":
            inliers = job.result.inliers
        for item in hmcc.verify_flight(images, pairs, method="hmcc-ransac"):
            ...                              # each pair's BatchItem once it has ended
        chosen = hmcc.choose_pairs(images, flying_height=120)  # the pairs worth matching

Answers are frozen dataclasses (:mod:`hmcc_client.models`): :class:`Job`, :class:`Batch`,
:class:`BatchItem`, :class:`Limits`, :class:`Pairs`. Answers that carry results (jobs and
batch pages) are asked for in MessagePack (``Accept: application/vnd.hmcc+msgpack``), each
result's ``inliers`` (and ``matches``) raw arrays rather than lists of numbers; a result's
``inliers`` is an int64 numpy array (read from JSON too, where a server answers JSON). A job
that ran and failed (e.g. ``invalid_input`` found by the worker) is a :class:`Job` with
``status == "failed"`` and ``error``; an HTTP error answer (4xx/5xx) raises
:class:`HmccError`. Waiting methods return the job/batch as it is when their timeout ends
(check ``done``).

Retries: with ``retries=N`` a request answered 429 (queue full) or 503 (queue unreachable) is
sent again up to N times, after the answer's ``Retry-After`` seconds (at most
``max_retry_wait_s``; 1 s when the header is missing). The default is 0: errors surface at
once. A retried POST may queue the same work twice (verification is deterministic, so this
only costs compute). :meth:`HmccClient.verify_flight` always retries 429 and 503 (within its
``timeout``).

:class:`AsyncHmccClient` has the same methods as coroutines (``batch_results`` and
``verify_flight`` are async iterators).
"""

from __future__ import annotations

import asyncio
import re
import time
from collections import deque
from collections.abc import (
    AsyncIterator,
    Awaitable,
    Callable,
    Iterable,
    Iterator,
    Mapping,
    Sequence,
)
from dataclasses import dataclass, replace
from types import TracebackType
from typing import Any, Self, TypeVar, cast
from urllib.parse import quote

import httpx
import msgpack

from .bodies import (
    BODY_PIECE_BYTES,
    JSON,
    MSGPACK,
    BatchBody,
    Pair,
    batch_body,
    flight_bodies,
    pair_body,
    pairs_body,
)
from .models import MAX_WAIT_S, Batch, BatchItem, ErrorBody, Issue, Job, Limits, Pairs

try:  # a faster JSON reader where it is installed (result pages are most of what comes back)
    from orjson import loads as _loads
except ImportError:  # the client alone needs no more than the standard library's
    from json import loads as _loads  # type: ignore[assignment]

__all__ = ["AsyncHmccClient", "HmccClient", "HmccError"]

_RETRY_STATUSES = frozenset({429, 503})
#: Results in MessagePack where the server has them so (jobs, batch pages), else JSON.
_ACCEPT = f"{MSGPACK}, {JSON};q=0.9"
_BATCH_PAIR = re.compile(r"\bpairs\[(\d+)\]")

_Answer = TypeVar("_Answer", Job, Batch, BatchItem, Limits, Pairs)


class HmccError(Exception):
    """An error answer of the API: HTTP ``status``, ``code`` (``invalid_input``,
    ``not_found``, ``queue_full``, ...), ``message``, the field ``issues`` of a 422 and
    ``retry_after`` (seconds, from the Retry-After header of a 429/503; else None)."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        issues: list[Issue] | None = None,
        retry_after: float | None = None,
    ) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message = status, code, message
        self.issues = issues or []
        self.retry_after = retry_after


def _parse(kind: type[_Answer], doc: Any) -> _Answer:
    """``doc`` (a decoded answer) as ``kind``; ValueError when it is not one (e.g. a proxy's
    page answered 200)."""
    try:
        return kind.from_json(doc)
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise ValueError(f"the answer is not a {kind.__name__}: {e!r}") from e


def _retry_after(response: httpx.Response) -> float | None:
    """Retry-After in seconds (the delta-seconds form; an HTTP date is not used here)."""
    value = response.headers.get("Retry-After")
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None


def _error(response: httpx.Response) -> HmccError:
    """The :class:`HmccError` of an error answer (also one that is not the API's JSON, e.g.
    from a proxy)."""
    retry = _retry_after(response)
    try:
        body = ErrorBody.from_json(response.json()["error"])
    except (ValueError, KeyError, TypeError, AttributeError):
        text = response.text.strip()[:200] or response.reason_phrase
        return HmccError(response.status_code, "http_error", text, None, retry)
    return HmccError(response.status_code, body.code, body.message, body.issues, retry)


def _decoded(response: httpx.Response) -> Any:
    """A successful answer's document, read as its ``Content-Type`` says (MessagePack or
    JSON)."""
    kind = response.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind == MSGPACK:
        return msgpack.unpackb(response.content)
    return _loads(response.content)


def _body_headers(content: Sequence[bytes] | None, content_type: str) -> dict[str, str] | None:
    if content is None:
        return None
    return {"Content-Type": content_type, "Content-Length": str(sum(map(len, content)))}


def _pieces(content: Sequence[bytes]) -> Iterator[bytes]:
    """The body's pieces as they are sent: a piece larger than :data:`BODY_PIECE_BYTES` in
    slices of that size (each copied once, see there)."""
    for piece in content:
        if len(piece) <= BODY_PIECE_BYTES:
            yield piece
            continue
        for start in range(0, len(piece), BODY_PIECE_BYTES):
            yield piece[start : start + BODY_PIECE_BYTES]


async def _async_pieces(content: Sequence[bytes]) -> AsyncIterator[bytes]:
    for piece in _pieces(content):
        yield piece


def _seg(value: str) -> str:
    """An id as one path segment (``/`` and friends escaped)."""
    return quote(value, safe="")


def _clamp_wait(wait: float) -> float:
    return min(max(0.0, float(wait)), MAX_WAIT_S)


@dataclass
class _Flying:
    """A batch of a flight being verified: its id, the flight's indices of its pairs, and how
    many of them were yielded."""

    batch_id: str
    indices: list[int]
    cursor: int = 0

    def ended(self, results: list[Any]) -> Iterator[BatchItem]:
        """The items of a page's ``results`` (read from the cursor on, as decoded) that ended,
        in order up to the first still queued or started, renumbered into the flight; the
        cursor moves past them. Only those are read into :class:`BatchItem`: the page's items
        after them are asked for again by the next poll."""
        for doc in results:
            if isinstance(doc, dict) and doc.get("status") in ("queued", "started"):
                return
            item = _parse(BatchItem, doc)
            self.cursor += 1
            yield BatchItem(self.indices[item.index], item.id, item.status, item.result, item.error)

    @property
    def done(self) -> bool:
        return self.cursor == len(self.indices)


def _page_results(doc: Any) -> list[Any]:
    """The decoded ``results`` of a batch page of a flight, the rest of the page checked as a
    :class:`Batch` (ValueError when it is not one); its items are read by
    :meth:`_Flying.ended`, as far as they ended."""
    if not isinstance(doc, dict) or not isinstance(doc.get("results"), list):
        raise ValueError(f"the answer is not a Batch: {doc!r:.200}")
    _parse(Batch, doc | {"results": []})
    return cast(list[Any], doc["results"])


def _in_flight_terms(error: HmccError, body: BatchBody) -> None:
    """Make ``error`` name the flight's pairs: the server names the batch's (``pairs[k]``),
    the caller knows the flight's."""

    def flight_index(m: re.Match[str]) -> str:
        k = int(m[1])
        return f"pairs[{body.indices[k]}]" if k < len(body.indices) else m[0]

    error.issues = [
        replace(issue, field=_BATCH_PAIR.sub(flight_index, issue.field)) for issue in error.issues
    ]
    error.message = _BATCH_PAIR.sub(flight_index, error.message)


def _flight_extra(
    method: str | None,
    params: Mapping[str, Any] | None,
    plane: Mapping[str, Any] | None,
    matching: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    given = (("method", method), ("params", params), ("plane", plane), ("matching", matching))
    return {k: v for k, v in given if v is not None}


class _Base:
    """What both clients share: headers, timeouts, retry policy."""

    def __init__(
        self,
        base_url: str,
        api_key: str | None,
        timeout: float,
        retries: int,
        max_retry_wait_s: float,
    ) -> None:
        if retries < 0:
            raise ValueError("retries must be >= 0")
        self.base_url = base_url.rstrip("/")
        self.timeout = float(timeout)
        self.retries = int(retries)
        self.max_retry_wait_s = float(max_retry_wait_s)
        self._headers = {"Accept": _ACCEPT}
        if api_key:
            self._headers["X-API-Key"] = api_key

    def _timeout(self, wait: float) -> httpx.Timeout:
        """``timeout`` for connecting and writing; reading also gets the long poll's ``wait``."""
        return httpx.Timeout(self.timeout, read=self.timeout + wait)

    def _delay(self, error: HmccError, attempt: int, retries: int | None = None) -> float | None:
        """Seconds to sleep before retry ``attempt`` (1-based), or None: raise."""
        limit = self.retries if retries is None else retries
        if error.status not in _RETRY_STATUSES or attempt > limit:
            return None
        delay = 1.0 if error.retry_after is None else error.retry_after
        return min(delay, self.max_retry_wait_s)

    def _flight_delay(self, error: HmccError, deadline: float | None) -> float:
        """Seconds to sleep before a flight's request is sent again after ``error``; raises
        ``error`` unless it is a 429 or 503, TimeoutError past the deadline."""
        if error.status not in _RETRY_STATUSES:
            raise error
        delay = min(1.0 if error.retry_after is None else error.retry_after, self.max_retry_wait_s)
        if deadline is not None and time.monotonic() + delay > deadline:
            raise TimeoutError("the flight did not finish in time") from error
        return delay

    @staticmethod
    def _poll_wait(deadline: float | None) -> float:
        """The long poll's ``wait`` on a flight's oldest batch: the time left, at most 60 s."""
        left = MAX_WAIT_S if deadline is None else deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the flight did not finish in time")
        return _clamp_wait(left)

    @staticmethod
    def _params(wait: float = 0.0, **extra: Any) -> dict[str, Any]:
        params = {k: v for k, v in extra.items() if v is not None}
        if wait > 0:
            params["wait"] = f"{wait:g}"
        return params


class HmccClient(_Base):
    """Synchronous client; use as a context manager (or call :meth:`close`).

    ``timeout``: seconds for connecting, sending and (beyond any ``?wait``) reading one
    request. ``retries``/``max_retry_wait_s``: see the module docstring. ``transport``: an
    httpx transport instead of the network (tests).
    """

    def __init__(
        self,
        base_url: str,
        api_key: str | None = None,
        timeout: float = 30.0,
        *,
        retries: int = 0,
        max_retry_wait_s: float = 30.0,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        super().__init__(base_url, api_key, timeout, retries, max_retry_wait_s)
        self._http = httpx.Client(
            base_url=self.base_url, headers=self._headers, transport=transport
        )

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _request(
        self,
        method: str,
        path: str,
        *,
        wait: float = 0.0,
        content: bytes | Sequence[bytes] | None = None,
        content_type: str = JSON,
        retries: int | None = None,
        **params: Any,
    ) -> Any:
        """One API call (retried on 429/503 as configured, or ``retries`` times); the decoded
        answer (:func:`_decoded`)."""
        pieces = (content,) if isinstance(content, bytes) else content
        headers = _body_headers(pieces, content_type)
        attempt = 0
        while True:
            response = self._http.request(
                method,
                path,
                params=self._params(wait, **params),
                content=None if pieces is None else _pieces(pieces),
                headers=headers,
                timeout=self._timeout(wait),
            )
            if response.is_success:
                return _decoded(response)
            error = _error(response)
            attempt += 1
            delay = self._delay(error, attempt, retries)
            if delay is None:
                raise error
            time.sleep(delay)

    def limits(self) -> Limits:
        """What one request may hold (``GET /v1/limits``)."""
        return _parse(Limits, self._request("GET", "/v1/limits"))

    def choose_pairs(
        self,
        images: Mapping[str, Mapping[str, Any]],
        *,
        ground_z: float | None = None,
        flying_height: float | None = None,
        params: Mapping[str, Any] | None = None,
    ) -> Pairs:
        """The pairs worth matching among ``images`` (id -> ``{camera, pose}``; keypoints are
        not sent), chosen by footprint overlap (``POST /v1/pairs``, answered at once). The
        ground: ``ground_z`` (metres, the positions' height scale) or ``flying_height``
        (metres below each camera), exactly one. ``params``: ``min_overlap`` (default 0.5),
        ``max_per_image``, ``min_partners``, ``footprint``."""
        body = pairs_body(images, ground_z, flying_height, params)
        return _parse(Pairs, self._request("POST", "/v1/pairs", content=body))

    # -- single pairs -----------------------------------------------------------------------

    def submit(self, pair: Pair, wait: float = 0.0) -> Job:
        """Queue one pair; with ``wait`` (s, at most 60) the answer waits for the job."""
        data = self._request(
            "POST", "/v1/verifications", wait=_clamp_wait(wait), content=pair_body(pair)
        )
        return _parse(Job, data)

    def get(self, job_id: str, wait: float = 0.0) -> Job:
        """The job; with ``wait`` (s, at most 60) once it ends or ``wait`` passes."""
        path = f"/v1/verifications/{_seg(job_id)}"
        return _parse(Job, self._request("GET", path, wait=_clamp_wait(wait)))

    def wait(self, job_id: str, timeout: float) -> Job:
        """Long-poll (60 s at a time) until the job ends or ``timeout`` seconds pass."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.get(job_id, wait=deadline - time.monotonic())
            if job.done or time.monotonic() >= deadline:
                return job

    def verify(self, pair: Pair, timeout: float = 60.0) -> Job:
        """Submit one pair and wait up to ``timeout`` seconds for its result."""
        deadline = time.monotonic() + timeout
        job = self.submit(pair, wait=timeout)
        if job.done or time.monotonic() >= deadline:
            return job
        return self.wait(job.job_id, deadline - time.monotonic())

    def cancel(self, job_id: str) -> Job:
        """Cancel a queued job (409 ``not_cancelable`` once it has started)."""
        return _parse(Job, self._request("DELETE", f"/v1/verifications/{_seg(job_id)}"))

    # -- batches ----------------------------------------------------------------------------

    def submit_batch(
        self,
        images: Mapping[str, Any],
        pairs: Sequence[Mapping[str, Any]],
        method: str | None = None,
        params: Mapping[str, Any] | None = None,
        plane: Mapping[str, Any] | None = None,
        matching: Mapping[str, Any] | None = None,
    ) -> Batch:
        """Queue a batch: ``images`` {id: {camera, pose, keypoints?, descriptors?}}, ``pairs``
        [{id?, image1, image2, keypoints1?, keypoints2?, matches}] (or ``match: True`` instead
        of matches); method/params/plane apply to every pair, ``matching`` (the matcher's
        options) to the pairs that ask for matching. JSON."""
        body = batch_body(images, pairs, method, params, plane, matching)
        return _parse(Batch, self._request("POST", "/v1/batches", content=body))

    def get_batch(self, batch_id: str, offset: int = 0, limit: int = 100) -> Batch:
        """Progress and the results of pairs ``offset .. offset + limit - 1`` (limit <= 1000;
        0: progress only)."""
        path = f"/v1/batches/{_seg(batch_id)}"
        return _parse(Batch, self._request("GET", path, offset=offset, limit=limit))

    def wait_batch(self, batch_id: str, timeout: float, poll_s: float = 1.0) -> Batch:
        """Poll progress (no results) until the batch is finished or ``timeout`` seconds
        pass; polls start at 50 ms and grow to ``poll_s``."""
        deadline = time.monotonic() + timeout
        interval = 0.05
        while True:
            batch = self.get_batch(batch_id, limit=0)
            remaining = deadline - time.monotonic()
            if batch.done or remaining <= 0:
                return batch
            time.sleep(min(interval, remaining))
            interval = min(interval * 2, poll_s)

    def batch_results(self, batch_id: str, page_size: int = 1000) -> Iterator[BatchItem]:
        """Every pair's item in index order, one page (``page_size`` <= 1000) at a time, read
        in MessagePack (each result's ``inliers`` an int64 numpy array)."""
        offset: int | None = 0
        while offset is not None:
            page = self.get_batch(batch_id, offset, page_size)
            yield from page.results
            offset = page.next_offset

    # -- whole flights ----------------------------------------------------------------------

    def verify_flight(
        self,
        images: Mapping[str, Mapping[str, Any]],
        pairs: Iterable[Mapping[str, Any]],
        *,
        method: str | None = None,
        params: Mapping[str, Any] | None = None,
        plane: Mapping[str, Any] | None = None,
        matching: Mapping[str, Any] | None = None,
        progress: Callable[[int, int], None] | None = None,
        binary: bool = True,
        columns: bool = True,
        batches_in_flight: int = 3,
        max_batch_pairs: int = 10_000,
        timeout: float | None = None,
    ) -> Iterator[BatchItem]:
        """Verify every pair of a flight; yields each pair's item once it has ended, its
        ``index`` the pair's position in ``pairs`` (batches are read oldest first, each in
        order: a pair that ends before those ahead of it waits for them).

        ``images``: id -> ``{camera, pose, keypoints, descriptors?}`` (arrays as lists or
        ndarrays, sent once per batch); ``pairs``: ``{id?, image1, image2, matches}``, or
        ``{id?, image1, image2, match: True}`` to have the images' descriptors matched (guided
        by the rough poses, options in ``matching``; ``plane`` then gives the ground's height:
        ``{"ground_z": ...}``), any iterable (read as the batches go); a matched pair's result
        holds its ``matches``, ``inliers`` indexing them, and ``matching`` (the matcher's
        figures); ``inliers`` and ``matches`` are int64 numpy arrays (result pages are read in
        MessagePack, the arrays raw). Pairs are split into batches under the server's limits
        (``GET /v1/limits``, not guessed), at most ``batches_in_flight`` at once, as
        MessagePack with raw array buffers (``binary``) or JSON; in MessagePack, a batch whose
        pairs are all ``{id?, image1, image2, matches}`` has them as columns (``columns``: one
        array each, which the server reads at once). A 429 or 503 is retried after
        its ``Retry-After``; ``timeout`` bounds the whole flight (``TimeoutError``). An error
        answer to a batch raises :class:`HmccError`, its fields naming the flight's pairs.
        ``progress(finished, submitted)`` is called as pairs are submitted and finish.
        """
        limits = self.limits()
        bodies = flight_bodies(
            images,
            pairs,
            max_pairs=min(limits.max_batch_pairs, max_batch_pairs),
            max_bytes=limits.max_body_bytes,
            binary=binary,
            columns=columns,
            extra=_flight_extra(method, params, plane, matching),
        )
        deadline = None if timeout is None else time.monotonic() + timeout
        flying: deque[_Flying] = deque()
        finished = submitted = 0

        def advance() -> Iterator[BatchItem]:
            """One long poll on the oldest batch: what ended of it; drop it once done."""
            nonlocal finished
            oldest = flying[0]
            for item in oldest.ended(self._flight_page(oldest, deadline)):
                finished += 1
                yield item
            if oldest.done:
                flying.popleft()
            if progress is not None:
                progress(finished, submitted)

        for body in bodies:
            while len(flying) >= batches_in_flight:
                yield from advance()
            flying.append(self._submit_flight_batch(body, deadline))
            submitted += len(body.indices)
            if progress is not None:
                progress(finished, submitted)
        while flying:
            yield from advance()

    def _submit_flight_batch(self, body: BatchBody, deadline: float | None) -> _Flying:
        def post() -> Any:
            return self._request(
                "POST",
                "/v1/batches",
                content=body.pieces,
                content_type=body.media_type,
                retries=0,
            )

        try:
            data = self._retrying(deadline, post)
        except HmccError as e:
            _in_flight_terms(e, body)
            raise
        return _Flying(_parse(Batch, data).batch_id, body.indices)

    def _flight_page(self, flying: _Flying, deadline: float | None) -> list[Any]:
        """The page of ``flying`` from its cursor on, after one long poll (at most the time
        left): its results as decoded (:func:`_page_results`). ``ended``: the page stops
        before its first pair still waiting (a server without it sends them too, unread)."""
        wait = self._poll_wait(deadline)
        path = f"/v1/batches/{_seg(flying.batch_id)}"
        data = self._retrying(
            deadline,
            lambda: self._request(
                "GET", path, wait=wait, offset=flying.cursor, limit=1000, ended="true", retries=0
            ),
        )
        return _page_results(data)

    def _retrying(self, deadline: float | None, call: Callable[[], Any]) -> Any:
        """``call()``, again after ``Retry-After`` while the answer is 429 or 503."""
        while True:
            try:
                return call()
            except HmccError as e:
                time.sleep(self._flight_delay(e, deadline))


class AsyncHmccClient(_Base):
    """The same client for asyncio; ``async with`` (or ``await aclose()``)."""

    def __init__(
        self,
        base_url: str,
        api_key: str | None = None,
        timeout: float = 30.0,
        *,
        retries: int = 0,
        max_retry_wait_s: float = 30.0,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        super().__init__(base_url, api_key, timeout, retries, max_retry_wait_s)
        self._http = httpx.AsyncClient(
            base_url=self.base_url, headers=self._headers, transport=transport
        )

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _request(
        self,
        method: str,
        path: str,
        *,
        wait: float = 0.0,
        content: bytes | Sequence[bytes] | None = None,
        content_type: str = JSON,
        retries: int | None = None,
        **params: Any,
    ) -> Any:
        pieces = (content,) if isinstance(content, bytes) else content
        headers = _body_headers(pieces, content_type)
        attempt = 0
        while True:
            response = await self._http.request(
                method,
                path,
                params=self._params(wait, **params),
                content=None if pieces is None else _async_pieces(pieces),
                headers=headers,
                timeout=self._timeout(wait),
            )
            if response.is_success:
                return _decoded(response)
            error = _error(response)
            attempt += 1
            delay = self._delay(error, attempt, retries)
            if delay is None:
                raise error
            await asyncio.sleep(delay)

    async def limits(self) -> Limits:
        return _parse(Limits, await self._request("GET", "/v1/limits"))

    async def choose_pairs(
        self,
        images: Mapping[str, Mapping[str, Any]],
        *,
        ground_z: float | None = None,
        flying_height: float | None = None,
        params: Mapping[str, Any] | None = None,
    ) -> Pairs:
        """:meth:`HmccClient.choose_pairs`."""
        body = pairs_body(images, ground_z, flying_height, params)
        return _parse(Pairs, await self._request("POST", "/v1/pairs", content=body))

    async def submit(self, pair: Pair, wait: float = 0.0) -> Job:
        data = await self._request(
            "POST", "/v1/verifications", wait=_clamp_wait(wait), content=pair_body(pair)
        )
        return _parse(Job, data)

    async def get(self, job_id: str, wait: float = 0.0) -> Job:
        path = f"/v1/verifications/{_seg(job_id)}"
        return _parse(Job, await self._request("GET", path, wait=_clamp_wait(wait)))

    async def wait(self, job_id: str, timeout: float) -> Job:
        deadline = time.monotonic() + timeout
        while True:
            job = await self.get(job_id, wait=deadline - time.monotonic())
            if job.done or time.monotonic() >= deadline:
                return job

    async def verify(self, pair: Pair, timeout: float = 60.0) -> Job:
        deadline = time.monotonic() + timeout
        job = await self.submit(pair, wait=timeout)
        if job.done or time.monotonic() >= deadline:
            return job
        return await self.wait(job.job_id, deadline - time.monotonic())

    async def cancel(self, job_id: str) -> Job:
        path = f"/v1/verifications/{_seg(job_id)}"
        return _parse(Job, await self._request("DELETE", path))

    async def submit_batch(
        self,
        images: Mapping[str, Any],
        pairs: Sequence[Mapping[str, Any]],
        method: str | None = None,
        params: Mapping[str, Any] | None = None,
        plane: Mapping[str, Any] | None = None,
        matching: Mapping[str, Any] | None = None,
    ) -> Batch:
        body = batch_body(images, pairs, method, params, plane, matching)
        return _parse(Batch, await self._request("POST", "/v1/batches", content=body))

    async def get_batch(self, batch_id: str, offset: int = 0, limit: int = 100) -> Batch:
        path = f"/v1/batches/{_seg(batch_id)}"
        return _parse(Batch, await self._request("GET", path, offset=offset, limit=limit))

    async def wait_batch(self, batch_id: str, timeout: float, poll_s: float = 1.0) -> Batch:
        deadline = time.monotonic() + timeout
        interval = 0.05
        while True:
            batch = await self.get_batch(batch_id, limit=0)
            remaining = deadline - time.monotonic()
            if batch.done or remaining <= 0:
                return batch
            await asyncio.sleep(min(interval, remaining))
            interval = min(interval * 2, poll_s)

    async def batch_results(self, batch_id: str, page_size: int = 1000) -> AsyncIterator[BatchItem]:
        """:meth:`HmccClient.batch_results`."""
        offset: int | None = 0
        while offset is not None:
            page = await self.get_batch(batch_id, offset, page_size)
            for item in page.results:
                yield item
            offset = page.next_offset

    async def verify_flight(
        self,
        images: Mapping[str, Mapping[str, Any]],
        pairs: Iterable[Mapping[str, Any]],
        *,
        method: str | None = None,
        params: Mapping[str, Any] | None = None,
        plane: Mapping[str, Any] | None = None,
        matching: Mapping[str, Any] | None = None,
        progress: Callable[[int, int], None] | None = None,
        binary: bool = True,
        columns: bool = True,
        batches_in_flight: int = 3,
        max_batch_pairs: int = 10_000,
        timeout: float | None = None,
    ) -> AsyncIterator[BatchItem]:
        """:meth:`HmccClient.verify_flight` as an async iterator (bodies are encoded in the
        event loop's thread, a batch at a time)."""
        limits = await self.limits()
        bodies = flight_bodies(
            images,
            pairs,
            max_pairs=min(limits.max_batch_pairs, max_batch_pairs),
            max_bytes=limits.max_body_bytes,
            binary=binary,
            columns=columns,
            extra=_flight_extra(method, params, plane, matching),
        )
        deadline = None if timeout is None else time.monotonic() + timeout
        flying: deque[_Flying] = deque()
        finished = submitted = 0

        async def advance() -> list[BatchItem]:
            nonlocal finished
            oldest = flying[0]
            ended = list(oldest.ended(await self._flight_page(oldest, deadline)))
            finished += len(ended)
            if oldest.done:
                flying.popleft()
            if progress is not None:
                progress(finished, submitted)
            return ended

        for body in bodies:
            while len(flying) >= batches_in_flight:
                for item in await advance():
                    yield item
            flying.append(await self._submit_flight_batch(body, deadline))
            submitted += len(body.indices)
            if progress is not None:
                progress(finished, submitted)
        while flying:
            for item in await advance():
                yield item

    async def _submit_flight_batch(self, body: BatchBody, deadline: float | None) -> _Flying:
        def post() -> Awaitable[Any]:
            return self._request(
                "POST",
                "/v1/batches",
                content=body.pieces,
                content_type=body.media_type,
                retries=0,
            )

        try:
            data = await self._retrying(deadline, post)
        except HmccError as e:
            _in_flight_terms(e, body)
            raise
        return _Flying(_parse(Batch, data).batch_id, body.indices)

    async def _flight_page(self, flying: _Flying, deadline: float | None) -> list[Any]:
        wait = self._poll_wait(deadline)
        path = f"/v1/batches/{_seg(flying.batch_id)}"
        data = await self._retrying(
            deadline,
            lambda: self._request(
                "GET", path, wait=wait, offset=flying.cursor, limit=1000, ended="true", retries=0
            ),
        )
        return _page_results(data)

    async def _retrying(self, deadline: float | None, call: Callable[[], Awaitable[Any]]) -> Any:
        while True:
            try:
                return await call()
            except HmccError as e:
                await asyncio.sleep(self._flight_delay(e, deadline))
