"""The API end to end over real HTTP, in both queue modes: embedded (``hmcc serve`` alone)
and RQ (``hmcc serve`` + ``hmcc worker`` on a private redis-server). Both must give the same
answers, and the same inliers as verifying in-process."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import orjson
import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_pair
from hmcc_worker.outcomes import FAULT_CRASH_PAIR_ID, FAULT_SLOW_PAIR_ID, FAULT_SLOW_S
from tests.support.answers import MSGPACK, as_json, both, raw_arrays
from tests.support.procs import redis_server, service_env, start_api, start_worker, wait_until

pytestmark = pytest.mark.procs


def _pair(seed: int = 1, n_inliers: int = 150) -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=n_inliers, outlier_ratio=0.5), seed)
    pair.pop("ground_truth")
    return pair


CRASH_ID = "boom"  # a pair with this id kills the process verifying it (fault injection)


@pytest.fixture(scope="module", params=["embedded", "rq"])
def url(request: pytest.FixtureRequest) -> Iterator[str]:
    settings = {"HMCC_BATCH_CHUNK_PAIRS": "4", FAULT_CRASH_PAIR_ID: CRASH_ID}
    if request.param == "embedded":
        api, base = start_api(service_env(**settings))
        try:
            yield base
        finally:
            api.stop()
        return
    with redis_server() as redis:
        env = service_env(REDIS_URL=redis.url, **settings)
        api, base = start_api(env)
        worker = start_worker(env)
        try:
            assert wait_until(lambda: httpx.get(f"{base}/readyz").status_code == 200, 30), (
                worker.log()
            )
            yield base
        finally:
            worker.stop()
            api.stop()


def test_a_pair_with_wait_answers_200_with_the_in_process_result(url: str) -> None:
    pair = _pair()
    r = httpx.post(f"{url}/v1/verifications?wait=30", json=pair, timeout=40)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["status"] == "finished"
    assert r.headers["Location"] == f"/v1/verifications/{body['job_id']}"
    expected = parse_pair(pair).verify(0).to_dict()
    assert body["result"]["inliers"] == expected["inliers"]
    assert body["result"]["model"]["type"] == "fundamental"
    timings = body["result"]["timings_ms"]  # the core's: each stage and their total
    stages = [s["name"] for s in body["result"]["stages"]]
    assert set(timings) == {*stages, "total"}
    assert timings["total"] == pytest.approx(sum(timings[s] for s in stages))
    service = body["timings_ms"]  # the job's: waiting, running, both
    for key in ("queue_wait", "run", "turnaround"):
        assert service[key] >= 0, key
        assert service[key] == round(service[key], 3), (key, service[key])  # no float noise
    assert service["turnaround"] >= service["queue_wait"]
    assert service["run"] >= timings["total"]
    assert body["submitted_at"] <= body["started_at"] <= body["finished_at"]
    assert body["error"] is None


def test_submit_then_long_poll(url: str) -> None:
    r = httpx.post(f"{url}/v1/verifications", json=_pair(seed=2))
    assert r.status_code == 202
    job = r.json()
    assert job["status"] in ("queued", "started", "finished")
    assert job["result"] is None or job["status"] == "finished"
    got = httpx.get(f"{url}{r.headers['Location']}?wait=30", timeout=40)
    assert got.status_code == 200
    assert got.json()["status"] == "finished"
    assert got.json()["job_id"] == job["job_id"]


def test_unknown_job_is_404_and_a_finished_job_cannot_be_cancelled(url: str) -> None:
    r = httpx.get(f"{url}/v1/verifications/0123456789abcdef")
    assert r.status_code == 404
    assert r.json()["error"]["code"] == "not_found"
    done = httpx.post(f"{url}/v1/verifications?wait=30", json=_pair(), timeout=40).json()
    r = httpx.delete(f"{url}/v1/verifications/{done['job_id']}")
    assert r.status_code == 409
    assert r.json()["error"]["code"] == "not_cancelable"


def test_input_only_the_core_can_refuse_fails_the_job_with_the_field(url: str) -> None:
    pair = _pair()
    pair["matches"] = pair["matches"][:5]  # valid JSON, but F needs 7 matches
    body = httpx.post(f"{url}/v1/verifications?wait=30", json=pair, timeout=40).json()
    assert body["status"] == "failed"
    assert body["error"]["code"] == "invalid_input"
    assert body["error"]["issues"][0]["field"] == "matches"
    assert body["result"] is None


def _batch(n: int) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    pairs = [_pair(seed=10 + k, n_inliers=60) for k in range(n)]
    first = pairs[0]
    images = {"A": first["image1"], "B": first["image2"]}
    batch = {
        "images": images,
        "plane": first["plane"],
        "pairs": [
            {
                "id": f"p{k}",
                "image1": "A",
                "image2": "B",
                "keypoints1": p["keypoints1"],
                "keypoints2": p["keypoints2"],
                "matches": p["matches"],
            }
            for k, p in enumerate(pairs)
        ],
    }
    batch["pairs"][3]["matches"] = batch["pairs"][3]["matches"][:3]  # refused by the core
    singles = [dict(p, image1=images["A"], image2=images["B"], plane=first["plane"]) for p in pairs]
    return batch, singles


def test_a_batch_runs_in_chunks_and_pages_its_results(url: str) -> None:
    batch, singles = _batch(10)
    r = httpx.post(f"{url}/v1/batches", json=batch, timeout=30)
    assert r.status_code == 202, r.text
    accepted = r.json()
    assert accepted["total"] == 10
    assert accepted["jobs"] == 3  # HMCC_BATCH_CHUNK_PAIRS=4
    location = r.headers["Location"]

    def finished() -> bool:
        return bool(httpx.get(f"{url}{location}?limit=0").json()["status"] == "finished")

    assert wait_until(finished, 30)
    first = httpx.get(f"{url}{location}?offset=0&limit=6").json()
    assert (first["finished"], first["failed"], first["queued"]) == (9, 1, 0)
    assert [i["index"] for i in first["results"]] == list(range(6))
    assert first["next_offset"] == 6
    # every pair ended: a page that stops before the first waiting one is the whole page
    assert httpx.get(f"{url}{location}?offset=0&limit=6&ended=true").json() == first
    rest = httpx.get(f"{url}{location}?offset=6&limit=6").json()
    assert [i["index"] for i in rest["results"]] == [6, 7, 8, 9]
    assert rest["next_offset"] is None
    items = first["results"] + rest["results"]
    assert [i["id"] for i in items] == [f"p{k}" for k in range(10)]
    failed = items[3]
    assert failed["status"] == "failed"
    assert failed["error"]["code"] == "invalid_input"
    for k, item in enumerate(items):
        if k == 3:
            continue
        assert item["status"] == "finished"
        assert item["result"]["inliers"] == parse_pair(singles[k]).verify(0).inliers.tolist()


def test_a_result_page_in_messagepack_is_the_json_page_with_raw_arrays(url: str) -> None:
    """``Accept: application/vnd.hmcc+msgpack``: the same page, field for field, each
    finished result's inliers a raw little-endian buffer of the JSON's numbers; a failed
    pair's error and a page's progress as in JSON."""
    batch, _ = _batch(10)
    r = httpx.post(f"{url}/v1/batches", json=batch, timeout=30)
    assert r.status_code == 202, r.text
    location = r.headers["Location"]
    assert wait_until(
        lambda: httpx.get(f"{url}{location}?limit=0").json()["status"] == "finished", 30
    )
    for query in ("?offset=0&limit=6", "?offset=6&limit=6", "?limit=0", "?offset=50"):
        plain, packed = both(url, location + query)
        assert as_json(packed) == plain  # every field, in JSON's terms
        assert list(packed) == list(plain)  # in the same order
    plain, packed = both(url, location + "?limit=10")
    finished = [k for k, i in enumerate(plain["results"]) if i["status"] == "finished"]
    assert len(finished) == 9 and plain["results"][3]["error"]["code"] == "invalid_input"
    for k in finished:
        inliers = packed["results"][k]["result"]["inliers"]
        assert isinstance(inliers["data"], bytes) and inliers["dtype"] == "<i4"
        (array,) = raw_arrays(inliers)
        assert array.tolist() == plain["results"][k]["result"]["inliers"]
    assert packed["results"][3]["result"] is None
    assert packed["results"][3]["error"] == plain["results"][3]["error"]


def test_a_job_in_messagepack_is_the_json_job_with_raw_arrays(url: str) -> None:
    pair = _pair(seed=5)
    r = httpx.post(
        f"{url}/v1/verifications?wait=30", json=pair, headers={"Accept": MSGPACK}, timeout=40
    )
    assert r.status_code == 200 and r.headers["content-type"] == MSGPACK, r.content[:200]
    import msgpack

    submitted = msgpack.unpackb(r.content)
    assert submitted["status"] == "finished"
    plain, packed = both(url, r.headers["Location"])
    assert as_json(packed) == plain == as_json(submitted)
    (inliers,) = raw_arrays(packed["result"])
    assert inliers.tolist() == parse_pair(pair).verify(0).inliers.tolist()


def test_an_accept_the_api_cannot_serve_is_answered_in_json(url: str) -> None:
    """Today's behaviour kept: the API answers JSON to an Accept it cannot serve (no 406),
    to MessagePack refused (q=0) or ranked below JSON, and its errors are JSON whatever the
    Accept."""
    batch, _ = _batch(4)
    location = httpx.post(f"{url}/v1/batches", json=batch, timeout=30).headers["Location"]
    for accept in (
        "text/html",
        "application/xml, */*;q=0.1",
        f"{MSGPACK};q=0, application/json",
        f"application/json, {MSGPACK};q=0.5",
        f"{MSGPACK};q=zero",
        "application/vnd.hmcc+msgpackx",
    ):
        r = httpx.get(f"{url}{location}", headers={"Accept": accept}, timeout=30)
        assert r.status_code == 200, (accept, r.text)
        assert r.headers["content-type"] == "application/json", accept
        assert r.json()["batch_id"] == location.rsplit("/", 1)[1]
    for accept in (MSGPACK, f"application/json;q=0.5, {MSGPACK}", f"*/*, {MSGPACK}"):
        r = httpx.get(f"{url}{location}", headers={"Accept": accept}, timeout=30)
        assert r.headers["content-type"] == MSGPACK, accept
    missing = httpx.get(f"{url}/v1/batches/nope", headers={"Accept": MSGPACK})
    assert missing.status_code == 404 and missing.json()["error"]["code"] == "not_found"


def test_unknown_batch_is_404(url: str) -> None:
    r = httpx.get(f"{url}/v1/batches/nope")
    assert r.status_code == 404
    assert r.json()["error"]["code"] == "not_found"


def test_health_readiness_and_metrics(url: str) -> None:
    assert httpx.get(f"{url}/healthz").json()["status"] == "ok"
    ready = httpx.get(f"{url}/readyz")
    assert ready.status_code == 200
    assert ready.json()["ready"] is True
    assert ready.json()["workers"] >= 1
    httpx.post(f"{url}/v1/verifications?wait=30", json=_pair(), timeout=40)
    text = httpx.get(f"{url}/metrics").text
    assert "hmcc_queue_up 1.0" in text
    assert "hmcc_queue_depth" in text
    assert 'hmcc_job_stage_seconds_count{stage="compute"}' in text
    assert 'hmcc_job_stage_seconds_count{stage="consistency"}' in text  # the default method
    assert 'hmcc_pairs_total{outcome="finished"}' in text
    assert 'hmcc_http_requests_total{method="POST",route="/v1/verifications",status="200"}' in text
    # the serial share's two halves: the API process's CPU, and (embedded) its children's
    cpu = {
        line.split()[0]: float(line.split()[1])
        for line in text.splitlines()
        if line.startswith(("hmcc_api_cpu_seconds_total", "hmcc_compute_cpu_seconds_total"))
    }
    assert cpu["hmcc_api_cpu_seconds_total"] > 0
    if ready.json()["backend"] == "embedded":
        assert cpu["hmcc_compute_cpu_seconds_total"] > 0  # warm-up and a verified pair
    else:
        assert "hmcc_compute_cpu_seconds_total" not in cpu  # the workers compute


# -- queue limits: own set-ups -----------------------------------------------------------------


def test_embedded_backpressure_and_cancel() -> None:
    # Every pair takes 8 s (fault injection), so the first one keeps the one worker busy
    # however fast the machine (a "slow" RANSAC pair had become fast enough to race it).
    # No drain at the end: the API stops at once instead of waiting for that pair.
    env = service_env(
        HMCC_EMBEDDED_WORKERS="1",
        HMCC_MAX_QUEUE_DEPTH="1",
        HMCC_RETRY_AFTER_S="7",
        HMCC_SHUTDOWN_DRAIN_S="0",
        **{FAULT_SLOW_PAIR_ID: "*", FAULT_SLOW_S: "8"},
    )
    api, url = start_api(env)
    try:
        _limits(url)
    finally:
        api.stop()


def test_rq_backpressure_cancel_and_readiness_without_workers() -> None:
    with redis_server() as redis:
        env = service_env(REDIS_URL=redis.url, HMCC_MAX_QUEUE_DEPTH="1", HMCC_RETRY_AFTER_S="7")
        api, url = start_api(env)
        try:
            ready = httpx.get(f"{url}/readyz")
            assert ready.status_code == 503
            assert ready.json()["workers"] == 0
            assert ready.json()["redis"] == "ok"
            _limits(url, worker_env=env)
        finally:
            api.stop()


def test_an_ended_page_stops_before_the_first_pair_still_waiting() -> None:
    """``?ended=true``: none of a batch's pairs ran (RQ without workers): an empty page, its
    progress and ``limit`` as asked; without it, the waiting pairs' items."""
    with redis_server() as redis:
        api, url = start_api(service_env(REDIS_URL=redis.url, HMCC_BATCH_CHUNK_PAIRS="4"))
        try:
            batch, _ = _batch(10)
            r = httpx.post(f"{url}/v1/batches", json=batch, timeout=30)
            assert r.status_code == 202, r.text
            location = r.headers["Location"]
            waiting = httpx.get(f"{url}{location}?offset=2&limit=5").json()
            assert [i["status"] for i in waiting["results"]] == ["queued"] * 5
            ended = httpx.get(f"{url}{location}?offset=2&limit=5&ended=true").json()
            assert ended == {**waiting, "results": [], "next_offset": None}
        finally:
            api.stop()


def _limits(url: str, worker_env: dict[str, str] | None = None) -> None:
    """Occupy the one worker (embedded) or have none (RQ): one job queued fills the queue
    (depth 1); the next gets 429 + Retry-After; the queued one can be cancelled."""
    if worker_env is None:
        busy = httpx.post(f"{url}/v1/verifications", json=_pair()).json()
        assert wait_until(
            lambda: (
                httpx.get(f"{url}/v1/verifications/{busy['job_id']}").json()["status"] == "started"
            ),
            20,
        )
    queued = httpx.post(f"{url}/v1/verifications", json=_pair())
    assert queued.status_code == 202
    job_id = queued.json()["job_id"]
    full = httpx.post(f"{url}/v1/verifications", json=_pair())
    assert full.status_code == 429, full.text
    assert full.json()["error"]["code"] == "queue_full"
    assert full.headers["Retry-After"] == "7"
    r = httpx.delete(f"{url}/v1/verifications/{job_id}")
    assert r.status_code == 200, r.text
    assert r.json()["status"] == "canceled"
    assert httpx.get(f"{url}/v1/verifications/{job_id}").json()["status"] == "canceled"
    t0 = time.monotonic()
    again = httpx.post(f"{url}/v1/verifications", json=_pair())
    assert again.status_code == 202, "a cancelled job no longer counts against the limit"
    assert time.monotonic() - t0 < 5


# -- no request can take the service down ------------------------------------------------------


def _random_pair(n_keypoints: int, n_matches: int) -> dict[str, Any]:
    """Valid, in-limit input that segfaulted OpenCV's USAC_ACCURATE (reached from hmcc-plus's
    fallback, the default one until stop 23, a choice since) and with it the whole process:
    uniformly random matches."""
    rng = np.random.default_rng(0)
    camera = {"width": 2000, "height": 1125, "focal": 1170.2}

    def image(x: float) -> dict[str, Any]:
        position = {"x": x, "y": 0.0, "z": 100.0}
        return {
            "camera": camera,
            "pose": {"position": position, "attitude": {"yaw": 0, "pitch": 0, "roll": 0}},
        }

    def keypoints() -> list[list[float]]:
        return np.round(
            np.column_stack([rng.uniform(0, 1999, n_keypoints), rng.uniform(0, 1124, n_keypoints)]),
            2,
        ).tolist()

    return {
        "image1": image(0.0),
        "image2": image(20.0),
        "keypoints1": keypoints(),
        "keypoints2": keypoints(),
        "matches": rng.integers(0, n_keypoints, (n_matches, 2)).tolist(),
    }


def test_the_pair_that_crashed_opencv_is_verified(url: str) -> None:
    big = _random_pair(5_000, 100_000)  # 100 000 matches: the limit
    big["params"] = {"plus": {"fallback": "usac-accurate"}}
    r = httpx.post(f"{url}/v1/verifications?wait=60", json=big, timeout=90)
    body = r.json()
    assert body["status"] == "finished", body
    stats = body["result"]["statistics"]
    assert stats["matches"] == 100_000 and stats["fallback"]["used"]
    fallback = next(s for s in body["result"]["stages"] if s["name"] == "fallback")
    assert fallback["stats"]["subsample"] == {"matches": 100_000, "used": 40_000}
    del big["params"]  # the default fallback, MAGSAC++, takes all 100 000 at once
    default = httpx.post(f"{url}/v1/verifications?wait=60", json=big, timeout=90).json()
    assert default["status"] == "finished", default
    assert default["result"]["statistics"]["fallback"]["used"]
    assert (
        httpx.post(f"{url}/v1/verifications?wait=30", json=_pair(), timeout=40).json()["status"]
        == "finished"
    )


def test_a_pair_that_kills_its_process_costs_that_pair_only(url: str) -> None:
    workers = httpx.get(f"{url}/readyz").json()["workers"]
    batch, _ = _batch(6)
    batch["pairs"][3]["matches"] = batch["pairs"][4]["matches"]  # valid again
    batch["pairs"][2]["id"] = CRASH_ID
    r = httpx.post(f"{url}/v1/batches", json=batch, timeout=30)
    assert r.status_code == 202, r.text
    location = r.headers["Location"]
    done = httpx.get(f"{url}{location}?wait=60&limit=10", timeout=70).json()
    while done["status"] != "finished":
        done = httpx.get(f"{url}{location}?wait=60&limit=10", timeout=70).json()
    statuses = [i["status"] for i in done["results"]]
    assert statuses == ["finished", "finished", "failed", "finished", "finished", "finished"]
    error = done["results"][2]["error"]
    assert error["code"] == "worker_crashed" and "SIGSEGV" in error["message"]
    # Nothing else is lost: the API answers, the same workers take the next job.
    again = httpx.post(f"{url}/v1/verifications?wait=30", json=_pair(), timeout=40).json()
    assert again["status"] == "finished"
    ready = httpx.get(f"{url}/readyz").json()
    assert ready["ready"] and ready["workers"] == workers


@pytest.mark.parametrize("mode", ["embedded", "rq"])
def test_a_single_pair_that_kills_its_process_fails_and_the_service_stays(mode: str) -> None:
    """Every pair kills the process verifying it (fault injection: a single pair has no id):
    each is failed ``worker_crashed`` once (RQ: not retried onto the next worker), the API
    answers the next request, and the same number of workers is there after as before."""
    settings = {FAULT_CRASH_PAIR_ID: "*", "HMCC_WORKER_GRACE_S": "1"}
    with contextlib.ExitStack() as stack:
        if mode == "rq":
            redis = stack.enter_context(redis_server())
            settings["REDIS_URL"] = redis.url
        env = service_env(**settings)
        api, url = start_api(env)
        stack.callback(api.stop)
        if mode == "rq":
            worker = start_worker(env)
            stack.callback(worker.stop)
        assert wait_until(lambda: httpx.get(f"{url}/readyz").status_code == 200, 60)
        workers = httpx.get(f"{url}/readyz").json()["workers"]
        for _ in range(2):
            r = httpx.post(f"{url}/v1/verifications?wait=30", json=_pair(), timeout=40)
            body = r.json()
            assert body["status"] == "failed", body
            assert body["error"]["code"] == "worker_crashed", body
            assert "SIGSEGV" in body["error"]["message"]
        assert wait_until(lambda: httpx.get(f"{url}/readyz").json()["workers"] == workers, 10)
        if mode == "rq":
            assert worker.proc.poll() is None, "the worker process itself survives"


def test_a_messagepack_batch_gives_the_json_results(url: str) -> None:
    """The same batch as MessagePack with raw array buffers (and images carrying their
    keypoints once): the same results as the JSON one."""
    import msgpack

    pairs = [_pair(seed=30 + k, n_inliers=60) for k in range(3)]
    images = {
        "A": {**pairs[0]["image1"], "keypoints": pairs[0]["keypoints1"]},
        "B": {**pairs[0]["image2"], "keypoints": pairs[0]["keypoints2"]},
    }
    as_json = {
        "images": images,
        "plane": pairs[0]["plane"],
        "pairs": [{"id": "shared", "image1": "A", "image2": "B", "matches": pairs[0]["matches"]}]
        + [
            {
                "id": f"own{k}",
                "image1": "A",
                "image2": "B",
                "keypoints1": p["keypoints1"],
                "keypoints2": p["keypoints2"],
                "matches": p["matches"],
            }
            for k, p in enumerate(pairs[1:])
        ],
        "params": {"result": "inliers"},
    }

    def buffer(value: list[list[float]], dtype: str) -> dict[str, Any]:
        array = np.asarray(value, dtype=dtype)
        return {"dtype": dtype, "shape": list(array.shape), "data": array.tobytes()}

    binary = {
        **as_json,
        "images": {
            n: {**im, "keypoints": buffer(im["keypoints"], "<f8")} for n, im in images.items()
        },
        "pairs": [
            {
                **p,
                **{
                    k: buffer(p[k], "<i4" if k == "matches" else "<f4")
                    for k in ("matches", "keypoints1", "keypoints2")
                    if k in p
                },
            }
            for p in as_json["pairs"]
        ],
    }
    results = []
    for content, kind in (
        (orjson.dumps(as_json), "application/json"),
        (msgpack.packb(binary), "application/vnd.hmcc+msgpack"),
    ):
        r = httpx.post(f"{url}/v1/batches", content=content, headers={"Content-Type": kind})
        assert r.status_code == 202, r.text
        page = httpx.get(f"{url}{r.headers['Location']}?wait=30&limit=10", timeout=40).json()
        while page["status"] != "finished":
            page = httpx.get(f"{url}{r.headers['Location']}?wait=30&limit=10", timeout=40).json()
        results.append([(i["id"], i["result"]["inliers"]) for i in page["results"]])
        assert set(page["results"][0]["result"]) == {"method", "inliers", "model", "timings_ms"}
    # float32 keypoints (the second and third pairs) may move a borderline match; the first
    # pair's keypoints are float64 in both bodies.
    assert results[0][0] == results[1][0]
    for (id_json, a), (id_bin, b) in zip(results[0][1:], results[1][1:], strict=True):
        assert id_json == id_bin and len(set(a) ^ set(b)) <= 2


def test_a_batch_with_its_pairs_as_columns_gives_the_results_of_its_rows(url: str) -> None:
    """The same batch as MessagePack with its pairs as columns and as rows: split into the same
    jobs (``HMCC_BATCH_CHUNK_PAIRS=4``), the same pages, each pair's inliers the core's; a pair
    the core refuses fails in its place in both."""
    from hmcc_schema import parse_batch
    from hmcc_schema.flight_columns import encode_flight_columns
    from hmcc_schema.flight_file import encode_flight
    from tests.support.flights import small_flight

    doc = small_flight(10)
    doc.pop("truth")
    doc["pairs"][6]["matches"] = doc["pairs"][6]["matches"][:3]  # refused by the core
    extra = {"plane": doc["plane"], "params": {"result": "inliers"}}
    core = parse_batch({**doc, **extra}, 100)
    pages = []
    for encode in (encode_flight_columns, encode_flight):
        content = encode(doc["images"], doc["pairs"], **extra)
        r = httpx.post(f"{url}/v1/batches", content=content, headers={"Content-Type": MSGPACK})
        assert r.status_code == 202, r.text
        assert (r.json()["total"], r.json()["jobs"]) == (10, 3)
        location = f"{url}{r.headers['Location']}?wait=30&limit=100"
        page = httpx.get(location, timeout=40).json()
        while page["status"] != "finished":
            page = httpx.get(location, timeout=40).json()
        pages.append([{k: v for k, v in i.items() if k != "result"} for i in page["results"]])
        for k, item in enumerate(page["results"]):
            if k == 6:
                assert item["error"]["code"] == "invalid_input"
                continue
            assert item["id"] == f"p{k}" and item["status"] == "finished"
            assert item["result"]["inliers"] == core.verify(k).inliers.tolist()
    assert pages[0] == pages[1]
