"""hmcc_client against a real ``hmcc serve`` (embedded queue) over TCP, plus the retry
policy and headers against a mock transport."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from typing import Any

import httpx
import msgpack
import numpy as np
import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_client import (
    MSGPACK,
    AsyncHmccClient,
    Batch,
    BatchItem,
    HmccClient,
    HmccError,
    Job,
    bodies,
)
from hmcc_client import client as client_module
from tests.hmcc_service.test_pairs import grid_images
from tests.support.procs import running, service_env, start_api

pytestmark = pytest.mark.procs


def _pair(seed: int, n_inliers: int = 80) -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=n_inliers, outlier_ratio=0.3), seed)
    pair.pop("ground_truth")
    return pair


@pytest.fixture(scope="module")
def server() -> Iterator[str]:
    api, url = start_api(service_env())
    with running(api):
        yield url


@pytest.fixture
def client(server: str) -> Iterator[HmccClient]:
    with HmccClient(server, timeout=10) as c:
        yield c


def test_verify_returns_finished_job_with_result(client: HmccClient) -> None:
    pair = _pair(1)
    job = client.verify(pair, timeout=30)
    assert isinstance(job, Job)
    assert job.status == "finished" and job.done
    assert job.error is None and job.result is not None
    stats = job.result.statistics
    assert stats["matches"] == len(pair["matches"])
    assert len(job.result.inliers) == stats["inliers"] > 40
    inliers = job.result.inliers
    assert inliers.dtype == np.int64 and inliers.ndim == 1
    assert (np.diff(inliers) > 0).all()  # ascending, each once
    assert job.result.timings_ms["total"] > 0  # the stages' sum
    assert job.timings_ms.run is not None and job.timings_ms.run >= job.result.timings_ms["total"]


def test_submit_then_wait_and_get(client: HmccClient) -> None:
    submitted = client.submit(json.dumps(_pair(2)))  # pre-encoded JSON is sent as is
    assert submitted.status in ("queued", "started", "finished")
    waited = client.wait(submitted.job_id, timeout=30)
    assert waited.status == "finished" and waited.job_id == submitted.job_id
    again = client.get(submitted.job_id)
    assert again.result is not None and waited.result is not None
    assert np.array_equal(again.result.inliers, waited.result.inliers)


def test_invalid_pair_raises_with_field_issues(client: HmccClient) -> None:
    pair = _pair(3)
    pair["matches"][2] = [len(pair["keypoints1"]) + 5, 0]
    pair["image1"]["camera"]["width"] = -1
    with pytest.raises(HmccError) as info:
        client.verify(pair)
    e = info.value
    assert (e.status, e.code) == (422, "invalid_input")
    reasons = {i.field: i.reason for i in e.issues}
    assert "greater than 0" in reasons["image1.camera.width"]
    assert "matches[2][0]" in reasons["matches"] and "out of range" in reasons["matches"]
    assert "image1.camera.width" in e.message
    assert e.retry_after is None


def test_choose_pairs_over_http_sync_and_async(server: str) -> None:
    """``POST /v1/pairs`` through a real server: the pairs of neighbours along each strip,
    the same from both clients; keypoints an image carries are not sent; bad input raises
    the 422 naming the field."""
    images = grid_images(along=49.0)
    images["s0-0"] = {**images["s0-0"], "keypoints": [[1.0, 2.0]]}  # a batch's image, as is
    with HmccClient(server, timeout=10) as hmcc:
        chosen = hmcc.choose_pairs(images, ground_z=0.0)
        wider = hmcc.choose_pairs(images, flying_height=100.0, params={"min_partners": 3})
        with pytest.raises(HmccError) as info:
            hmcc.choose_pairs(images, params={"min_overlap": 0.5})
    assert {(p.image1, p.image2) for p in chosen.pairs} == {
        (f"s{s}-{i}", f"s{s}-{i + 1}") for s in range(3) for i in range(4)
    }
    assert all(p.overlap == pytest.approx(0.51) for p in chosen.pairs)
    assert chosen.images == 15 and chosen.ground == {"ground_z": 0.0}
    assert chosen.params["min_overlap"] == 0.5 and chosen.timings_ms["total"] > 0
    assert set(chosen.pairs) < set(wider.pairs) and wider.params["min_partners"] == 3
    assert (info.value.status, info.value.code) == (422, "invalid_input")
    assert info.value.issues[0].field == "ground_z"

    async def from_async() -> Any:
        async with AsyncHmccClient(server, timeout=10) as hmcc:
            return await hmcc.choose_pairs(images, ground_z=0.0)

    assert asyncio.run(from_async()).pairs == chosen.pairs


def test_unknown_ids_raise_404(client: HmccClient) -> None:
    for call in (
        lambda: client.get("no-such-job"),
        lambda: client.get_batch("no-such-batch"),
        lambda: client.cancel("no-such-job"),
    ):
        with pytest.raises(HmccError) as info:
            call()
        assert (info.value.status, info.value.code) == (404, "not_found")


def test_cancel_finished_job_is_409(client: HmccClient) -> None:
    job = client.verify(_pair(4), timeout=30)
    with pytest.raises(HmccError) as info:
        client.cancel(job.job_id)
    assert (info.value.status, info.value.code) == (409, "not_cancelable")


def test_batch_round_trip_pages_in_order(client: HmccClient) -> None:
    images: dict[str, Any] = {}
    pairs = []
    for k in range(5):
        p = _pair(10 + k, n_inliers=50)
        images[f"a{k}"], images[f"b{k}"] = p["image1"], p["image2"]
        pairs.append(
            {
                "id": f"pair-{k}",
                "image1": f"a{k}",
                "image2": f"b{k}",
                "keypoints1": p["keypoints1"],
                "keypoints2": p["keypoints2"],
                "matches": p["matches"],
            }
        )
    pairs[3]["image2"] = "a3"  # same image twice: a valid request, but verification may differ
    batch = client.submit_batch(images, pairs, method="hmcc-ransac", plane={"z": "auto"})
    assert isinstance(batch, Batch) and batch.total == 5 and batch.results == []
    done = client.wait_batch(batch.batch_id, timeout=30)
    assert done.done and done.finished + done.failed == 5 and done.queued == done.started == 0
    items = list(client.batch_results(batch.batch_id, page_size=2))  # 3 pages
    assert [i.index for i in items] == list(range(5))
    assert [i.id for i in items] == [f"pair-{k}" for k in range(5)]
    for k in (0, 1, 2, 4):
        assert items[k].status == "finished" and items[k].result is not None
        inliers = items[k].result.inliers  # type: ignore[union-attr]
        assert isinstance(inliers, np.ndarray) and inliers.dtype == np.int64 and inliers.size

    async def read() -> list[BatchItem]:
        async with AsyncHmccClient(client.base_url, timeout=10) as c:
            return [i async for i in c.batch_results(batch.batch_id, page_size=3)]

    assert asyncio.run(read()) == items  # the same results, arrays compared by value

    # the page as JSON and as MessagePack, read by the client's models: equal arrays
    path = f"{client.base_url}/v1/batches/{batch.batch_id}"
    as_json = httpx.get(path, headers={"Accept": "application/json"})
    binary = httpx.get(path, headers={"Accept": MSGPACK})
    assert binary.headers["content-type"] == MSGPACK
    from_json = Batch.from_json(as_json.json())
    from_binary = Batch.from_json(msgpack.unpackb(binary.content))
    assert from_binary == from_json
    for a, b in zip(from_json.results, from_binary.results, strict=True):
        if a.result is not None:
            assert b.result is not None and np.array_equal(a.result.inliers, b.result.inliers)
            assert (
                a.result.to_dict()
                == b.result.to_dict()
                == as_json.json()["results"][a.index]["result"]
            )


def test_batch_with_unknown_image_raises(client: HmccClient) -> None:
    p = _pair(20)
    pair = {
        "image1": "a",
        "image2": "zzz",
        "keypoints1": p["keypoints1"],
        "keypoints2": p["keypoints2"],
        "matches": p["matches"],
    }
    with pytest.raises(HmccError) as info:
        client.submit_batch({"a": p["image1"]}, [pair])
    assert info.value.status == 422
    assert [i.field for i in info.value.issues] == ["pairs[0].image2"]


def test_async_client_verify_and_batch(server: str) -> None:
    p = _pair(30)

    async def run() -> tuple[Job, list[str]]:
        async with AsyncHmccClient(server, timeout=10) as c:
            job = await c.verify(p, timeout=30)
            pair = {
                "image1": "a",
                "image2": "b",
                "keypoints1": p["keypoints1"],
                "keypoints2": p["keypoints2"],
                "matches": p["matches"],
            }
            batch = await c.submit_batch({"a": p["image1"], "b": p["image2"]}, [pair, pair])
            await c.wait_batch(batch.batch_id, timeout=30)
            items = c.batch_results(batch.batch_id, page_size=1)
            statuses: list[str] = [i.status async for i in items]
            return job, statuses

    job, statuses = asyncio.run(run())
    assert job.status == "finished"
    assert statuses == ["finished", "finished"]


# -- retry policy and headers (mock transport) ---------------------------------------------


def _queue_full(retry_after: str | None = "0") -> httpx.Response:
    headers = {} if retry_after is None else {"Retry-After": retry_after}
    return httpx.Response(
        429, headers=headers, json={"error": {"code": "queue_full", "message": "full"}}
    )


def _job_json() -> dict[str, Any]:
    return {"job_id": "j1", "status": "queued", "submitted_at": "2024-01-01T00:00:00Z"}


def test_retries_honour_retry_after_up_to_the_bound() -> None:
    seen: list[httpx.Request] = []
    answers = [_queue_full("0"), _queue_full("0"), httpx.Response(202, json=_job_json())]

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return answers[len(seen) - 1]

    with HmccClient(
        "http://hmcc.test", api_key="k3y", retries=2, transport=httpx.MockTransport(handler)
    ) as c:
        job = c.submit({"x": 1})
    assert job.job_id == "j1" and not job.done
    assert len(seen) == 3
    assert all(r.headers["X-API-Key"] == "k3y" for r in seen)
    assert seen[0].headers["Content-Type"] == "application/json"
    assert json.loads(seen[0].content) == {"x": 1}


def test_no_retry_by_default_and_error_carries_retry_after() -> None:
    calls = 0

    def handler(request: httpx.Request) -> httpx.Response:
        nonlocal calls
        calls += 1
        return _queue_full("7")

    with HmccClient("http://hmcc.test", transport=httpx.MockTransport(handler)) as c:
        with pytest.raises(HmccError) as info:
            c.submit({})
    assert calls == 1
    e = info.value
    assert (e.status, e.code, e.retry_after) == (429, "queue_full", 7.0)
    assert "X-API-Key" not in c._headers


def test_retries_exhausted_raise_and_other_errors_are_not_retried() -> None:
    calls: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request.method)
        if request.method == "POST":
            return _queue_full("0")
        return httpx.Response(502, text="<html>bad gateway</html>")

    with HmccClient("http://hmcc.test", retries=1, transport=httpx.MockTransport(handler)) as c:
        with pytest.raises(HmccError) as info:
            c.submit({})
        assert info.value.status == 429 and calls == ["POST", "POST"]
        with pytest.raises(HmccError) as info:
            c.get("x")
        assert (info.value.status, info.value.code) == (502, "http_error")
        assert "bad gateway" in info.value.message
        assert calls == ["POST", "POST", "GET"]


def test_wait_long_polls_with_bounded_wait() -> None:
    waits: list[str | None] = []
    paths: list[bytes] = []

    def handler(request: httpx.Request) -> httpx.Response:
        waits.append(request.url.params.get("wait"))
        paths.append(request.url.raw_path)
        status = "finished" if len(waits) == 2 else "started"
        return httpx.Response(200, json={**_job_json(), "status": status})

    with HmccClient("http://hmcc.test", transport=httpx.MockTransport(handler)) as c:
        job = c.wait("a/b", timeout=500)
    assert job.status == "finished"
    assert waits[0] == "60" and len(waits) == 2
    assert paths[0] == b"/v1/verifications/a%2Fb?wait=60"  # the id is one path segment


# -- whole flights ---------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False], ids=["msgpack", "json"])
def test_verify_flight_yields_every_pair_once_with_its_flight_index(
    client: HmccClient, binary: bool
) -> None:
    from hmcc_schema import parse_batch
    from tests.support.flights import small_flight

    flight = small_flight(7)
    truth = flight.pop("truth")
    seen: list[tuple[int, int]] = []
    items = list(
        client.verify_flight(
            flight["images"],
            iter(flight["pairs"]),
            plane=flight["plane"],
            params={"result": "inliers"},
            binary=binary,
            max_batch_pairs=3,
            batches_in_flight=2,
            progress=lambda done, submitted: seen.append((done, submitted)),
        )
    )
    assert sorted(i.index for i in items) == list(range(7))
    assert all(i.status == "finished" and i.result is not None for i in items)
    local = parse_batch(flight, max_pairs=100)
    for item in items:
        assert item.id == f"p{item.index}" and item.result is not None
        assert np.array_equal(item.result.inliers, local.verify(item.index).inliers)
        assert set(item.result.inliers) & set(truth[item.id])
    assert seen[-1] == (7, 7) and all(d <= s for d, s in seen)


def test_async_verify_flight_matches_the_sync_one(client: HmccClient, server: str) -> None:
    from tests.support.flights import small_flight

    flight = small_flight(5, seed=40)
    kwargs: dict[str, Any] = {"plane": flight["plane"], "max_batch_pairs": 2}
    expected = {
        i.index: i.result.to_dict()["inliers"]
        for i in client.verify_flight(flight["images"], flight["pairs"], **kwargs)
        if i.result is not None
    }

    async def run() -> dict[int, list[int]]:
        async with AsyncHmccClient(server, timeout=10) as c:
            items = c.verify_flight(
                flight["images"], flight["pairs"], batches_in_flight=2, timeout=60, **kwargs
            )
            return {i.index: i.result.inliers.tolist() async for i in items if i.result is not None}

    assert sorted(expected) == list(range(5))
    assert asyncio.run(run()) == expected


@pytest.mark.parametrize("binary", [True, False], ids=["msgpack", "json"])
def test_a_flight_sent_in_small_pieces_reaches_the_server_whole(
    server: str, binary: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Bodies packed and sent in pieces (a JSON body, one piece, sliced as it is sent) of a
    few kilobytes, sync and async: every pair is verified as from the flight itself."""
    from hmcc_schema import parse_batch
    from tests.support.flights import small_flight

    monkeypatch.setattr(bodies, "BODY_PIECE_BYTES", 2048)
    monkeypatch.setattr(client_module, "BODY_PIECE_BYTES", 2048)
    flight = small_flight(6, seed=41)
    flight.pop("truth")
    local = parse_batch(flight, max_pairs=100)
    expected = {k: local.verify(k).inliers.tolist() for k in range(6)}
    kwargs: dict[str, Any] = {"plane": flight["plane"], "binary": binary, "max_batch_pairs": 4}
    with HmccClient(server, timeout=10) as c:
        items = c.verify_flight(flight["images"], flight["pairs"], **kwargs)
        got = {i.index: i.result.inliers.tolist() for i in items if i.result is not None}
    assert got == expected

    async def run() -> dict[int, list[int]]:
        async with AsyncHmccClient(server, timeout=10) as c:
            items = c.verify_flight(flight["images"], flight["pairs"], timeout=60, **kwargs)
            return {i.index: i.result.inliers.tolist() async for i in items if i.result is not None}

    assert asyncio.run(run()) == expected


def test_a_body_goes_with_its_length_in_pieces_of_at_most_the_piece_size(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(client_module, "BODY_PIECE_BYTES", 1000)
    sent: list[tuple[httpx.Headers, list[bytes]]] = []

    class Recording(httpx.BaseTransport):  # MockTransport reads the body whole first
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            assert isinstance(request.stream, httpx.SyncByteStream)
            sent.append((request.headers, list(request.stream)))
            return httpx.Response(202, json={"error": None})

    pieces = (b"a" * 2500, b"b" * 10, b"c" * 1000)
    with HmccClient("http://hmcc.test", transport=Recording()) as c:
        c._request("POST", "/v1/batches", content=pieces)
        c._request("POST", "/v1/batches", content=b"".join(pieces))
    for headers, chunks in sent:
        assert headers["Content-Length"] == "3510" and "Transfer-Encoding" not in headers
        assert b"".join(chunks) == b"".join(pieces)
        assert max(map(len, chunks)) <= 1000 and len(chunks) >= 4


def test_verify_flight_names_the_flights_pair_in_a_refusal(client: HmccClient) -> None:
    """The server names a pair by its place in its batch; the client by its place in the
    flight."""
    from tests.support.flights import small_flight

    flight = small_flight(3)
    flight["pairs"][2]["image2"] = "nowhere"
    with pytest.raises(HmccError) as e:
        list(
            client.verify_flight(
                flight["images"], flight["pairs"], plane=flight["plane"], max_batch_pairs=1
            )
        )
    assert e.value.status == 422
    assert [i.field for i in e.value.issues] == ["pairs[2].image2"]
    assert "pairs[2].image2" in e.value.message and "pairs[0]" not in e.value.message


class _StatusLog(httpx.HTTPTransport):
    """A transport that keeps every answer's status."""

    def __init__(self) -> None:
        super().__init__()
        self.statuses: list[int] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        response = super().handle_request(request)
        self.statuses.append(response.status_code)
        return response


def test_verify_flight_waits_out_a_full_queue() -> None:
    """With room for one job at a time and each pair taking 0.5 s, the batches after the
    first get 429 at first: the client retries after Retry-After instead of failing."""
    from hmcc_worker.outcomes import FAULT_SLOW_PAIR_ID, FAULT_SLOW_S
    from tests.support.flights import small_flight

    env = service_env(
        HMCC_MAX_QUEUE_DEPTH="1",
        HMCC_RETRY_AFTER_S="1",
        HMCC_BATCH_CHUNK_PAIRS="1",
        HMCC_EMBEDDED_WORKERS="1",
        **{FAULT_SLOW_PAIR_ID: "*", FAULT_SLOW_S: "0.5"},
    )
    api, url = start_api(env)
    flight = small_flight(4)
    log = _StatusLog()
    with running(api), HmccClient(url, timeout=10, transport=log) as c:
        items = list(
            c.verify_flight(
                flight["images"],
                flight["pairs"],
                plane=flight["plane"],
                max_batch_pairs=1,
                batches_in_flight=3,
                timeout=60,
            )
        )
    assert sorted(i.index for i in items) == [0, 1, 2, 3]
    assert all(i.status == "finished" for i in items)
    assert 429 in log.statuses, log.statuses


def _flight_service(pages: list[list[dict[str, Any]]]) -> httpx.MockTransport:
    """A service that accepts one batch of three pairs and answers its polls with ``pages``'
    results in turn (JSON), each page from the offset asked for."""
    limits = {
        "max_body_bytes": 1 << 26,
        "max_batch_pairs": 100,
        "max_batch_images": 100,
        "max_keypoints": 100_000,
        "max_matches": 100_000,
        "batch_chunk_pairs": 256,
        "max_wait_s": 60.0,
        "max_queue_depth": 100,
        "methods": ["hmcc-plus"],
    }
    counts = dict.fromkeys(("queued", "started", "finished", "failed", "canceled", "expired"), 0)
    head = {"batch_id": "b1", "submitted_at": "2024-01-01T00:00:00Z", "total": 3, "jobs": 2}

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/limits":
            return httpx.Response(200, json=limits)
        if request.method == "POST":
            view = {**head, **counts, "status": "queued", "queued": 3, "offset": 0, "limit": 0}
            return httpx.Response(202, json={**view, "next_offset": None, "results": []})
        offset = int(request.url.params["offset"])
        assert request.url.params["ended"] == "true"  # only what ended (this one sends more)
        results = pages.pop(0)
        page = {**head, **counts, "status": "running", "finished": 2, "started": 1}
        page |= {"offset": offset, "limit": 1000, "next_offset": None, "results": results}
        return httpx.Response(200, json=page)

    return httpx.MockTransport(handler)


def _ended(index: int, inliers: list[int]) -> dict[str, Any]:
    result = {"method": "hmcc-plus", "inliers": inliers, "model": {}, "timings_ms": {}}
    return {"index": index, "id": f"p{index}", "status": "finished", "result": result}


def test_verify_flight_reads_a_page_up_to_its_first_pair_still_running() -> None:
    """A pair that ended behind one still running is read again by the next poll, not lost
    or yielded twice; the items after the running one are not read at all (here not even
    valid ones)."""
    pending = {"index": 1, "id": "p1", "status": "started", "result": None, "error": None}
    pages = [
        [_ended(0, [0, 2]), pending, {"index": 2, "junk": True}],
        [_ended(1, [1]), _ended(2, [0, 1])],
    ]
    flight = [{"id": f"p{i}", "image1": "a", "image2": "b", "matches": [[0, 0]]} for i in range(3)]
    with HmccClient("http://hmcc.test", transport=_flight_service(pages)) as c:
        items = list(c.verify_flight({}, flight, binary=False))
    assert [(i.index, i.id, i.status) for i in items] == [
        (0, "p0", "finished"),
        (1, "p1", "finished"),
        (2, "p2", "finished"),
    ]
    assert [i.result.inliers.tolist() for i in items if i.result is not None] == [
        [0, 2],
        [1],
        [0, 1],
    ]


@pytest.mark.parametrize(
    "page", [[{"index": 0, "junk": True}], "not a list"], ids=["item", "results"]
)
def test_verify_flight_refuses_a_page_that_is_not_a_batch(page: Any) -> None:
    with HmccClient("http://hmcc.test", transport=_flight_service([page])) as c:
        with pytest.raises(ValueError, match="not a (Batch|BatchItem)"):
            list(c.verify_flight({}, [{"image1": "a", "image2": "b", "matches": [[0, 0]]}]))
