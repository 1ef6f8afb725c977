"""No stalled client can block the service: bodies are read under deadlines, the body budget
is held by bytes that arrived (not by what a head declares), a SIGTERM'd API neither waits on
stalled uploads nor accepts work it will not run, and the HTTP edge answers what it refuses
with the right status. Real ``hmcc serve`` processes on loopback, sockets driven by hand,
every wait bounded."""

from __future__ import annotations

import json
import re
import select
import signal
import socket
import subprocess
import time
from collections.abc import Iterator

import httpx
import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_service.http_protocol import MAX_HEAD_BYTES
from tests.support.procs import Proc, service_env, start_api, wait_until
from tests.support.raw_http import connect, read_answer, send_head

pytestmark = pytest.mark.procs

MB = 1024 * 1024
#: What a stalled upload declares: the largest body the API takes by default.
DECLARED = 64 * MB
#: The deadlines of the ``api`` fixture: a body's first bytes within GRACE_S of its head.
GRACE_S = 3.0


def _pair(size: int = 0) -> bytes:
    """A valid pair as JSON, padded with whitespace to ``size`` bytes (when larger)."""
    pair = simulate_pair(SimulationOptions(n_inliers=40), seed=1)
    pair.pop("ground_truth")
    raw = json.dumps(pair).encode()
    return raw + b" " * max(0, size - len(raw))


def _stalled_upload(url: str) -> socket.socket:
    """A POST that declares 64 MB, sends one byte of it and waits."""
    sock = connect(url, timeout_s=30)
    send_head(
        sock,
        "POST",
        "/v1/verifications",
        Content_Type="application/json",
        Content_Length=str(DECLARED),
    )
    sock.sendall(b"{")
    return sock


def _exits_within(proc: Proc, timeout_s: float) -> bool:
    try:
        proc.proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        return False
    return True


def _readable(sock: socket.socket) -> bool:
    return bool(select.select([sock], [], [], 0)[0])


def _post(url: str, body: bytes, **headers: str) -> httpx.Response:
    return httpx.post(
        f"{url}/v1/verifications",
        content=body,
        headers={"Content-Type": "application/json", **headers},
        timeout=10,
        trust_env=False,
    )


def _requests_counted(url: str, route: str, status: str) -> float:
    """``hmcc_http_requests_total`` of POSTs to ``route`` answered ``status``."""
    text = httpx.get(f"{url}/metrics", timeout=10, trust_env=False).text
    pattern = (
        r'hmcc_http_requests_total\{method="POST",route="'
        + re.escape(route)
        + r'",status="'
        + status
        + r'"\} ([0-9.e+]+)'
    )
    found = re.search(pattern, text)
    return float(found.group(1)) if found else 0.0


@pytest.fixture(scope="module")
def api() -> Iterator[tuple[Proc, str]]:
    env = service_env(HMCC_BODY_GRACE_S=str(GRACE_S), HMCC_BODY_MIN_BYTES_PER_S="1024")
    proc, url = start_api(env)
    try:
        yield proc, url
    finally:
        proc.stop()


# -- bodies under deadlines, a budget idle connections cannot hold ------------------------------


def test_two_stalled_uploads_block_no_post_and_are_cut_after_the_deadline(
    api: tuple[Proc, str],
) -> None:
    """Two uploads declaring 64 MB each (the whole 128 MB budget) send one byte and wait:
    valid POSTs are still accepted at once, and the stalled ones get 408 after the grace."""
    _, url = api
    body = _pair()
    t0 = time.monotonic()
    stalled = [_stalled_upload(url), _stalled_upload(url)]
    try:
        time.sleep(0.3)  # both heads read, their requests in the app
        for _ in range(3):
            t = time.monotonic()
            answer = _post(url, body)
            assert answer.status_code == 202, answer.text
            assert time.monotonic() - t < 2.0
        assert not any(map(_readable, stalled)), "a stalled upload was answered before its deadline"
        for sock in stalled:
            answer = read_answer(sock)
            elapsed = time.monotonic() - t0
            assert answer.status == 408, answer
            assert answer.json()["error"]["code"] == "request_timeout"
            assert GRACE_S <= elapsed < GRACE_S + 5, elapsed
            assert sock.recv(1) == b"", "the connection is closed after the 408"
    finally:
        for sock in stalled:
            sock.close()


def test_a_body_sent_slowly_but_steadily_is_not_cut(api: tuple[Proc, str]) -> None:
    """A body that keeps arriving faster than HMCC_BODY_MIN_BYTES_PER_S (here 1 kB/s) is read
    to the end, even when it takes longer than the grace."""
    _, url = api
    body = _pair()
    step = 2048
    with connect(url, timeout_s=30) as sock:
        send_head(
            sock,
            "POST",
            "/v1/verifications",
            Content_Type="application/json",
            Content_Length=str(len(body)),
        )
        sock.sendall(body[:step])
        start = step
        t0 = time.monotonic()
        while start < len(body):
            time.sleep(min(0.5, (GRACE_S + 1) / (len(body) / step)))
            sock.sendall(body[start : start + step])
            start += step
        assert time.monotonic() - t0 > GRACE_S
        answer = read_answer(sock)
    assert answer.status == 202, answer


# -- shutdown -----------------------------------------------------------------------------------


def test_sigterm_exits_quickly_with_two_stalled_uploads_open() -> None:
    """SIGTERM with two stalled uploads open (default deadlines): they are answered 503
    ``shutting_down`` at once, and the API exits in under 5 s."""
    proc, url = start_api(service_env())
    stalled: list[socket.socket] = []
    try:
        stalled = [_stalled_upload(url), _stalled_upload(url)]
        time.sleep(0.3)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        for sock in stalled:
            answer = read_answer(sock)
            assert answer.status == 503, answer
            assert answer.json()["error"]["code"] == "shutting_down"
            assert "retry-after" in answer.headers
        assert _exits_within(proc, 10), proc.log()
        assert time.monotonic() - t0 < 5.0, proc.log()
    finally:
        for sock in stalled:
            sock.close()
        proc.stop()


def test_a_post_after_sigterm_is_refused_and_what_was_accepted_finishes() -> None:
    """Embedded mode, a job still running (HMCC_FAULT_SLOW_S) at SIGTERM: a POST that comes
    after gets 503 + Retry-After, never 202; the job accepted before finishes and is read
    while the API drains; then the API exits."""
    env = service_env(
        HMCC_EMBEDDED_WORKERS="1",
        HMCC_FAULT_SLOW_PAIR_ID="*",
        HMCC_FAULT_SLOW_S="3",
        HMCC_RETRY_AFTER_S="7",
    )
    proc, url = start_api(env)
    try:
        body = _pair()
        accepted = _post(url, body)
        assert accepted.status_code == 202, accepted.text
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.1)
        refused = _post(url, body)
        assert refused.status_code == 503, refused.text
        assert refused.headers["retry-after"] == "7"
        assert refused.json()["error"]["code"] == "shutting_down"
        ready = httpx.get(f"{url}/readyz", timeout=10, trust_env=False)
        assert ready.status_code == 503
        done = httpx.get(
            f"{url}{accepted.headers['location']}?wait=10", timeout=20, trust_env=False
        )
        assert done.json()["status"] == "finished", done.text
        assert wait_until(lambda: proc.proc.poll() is not None, 15), proc.log()
    finally:
        proc.stop()


@pytest.mark.parametrize(("drain_s", "signals"), [(2, 1), (30, 2)], ids=["drain", "twice"])
def test_the_drain_is_bounded_and_a_second_signal_ends_it(drain_s: int, signals: int) -> None:
    """A job that would run 30 s at SIGTERM: the API exits HMCC_SHUTDOWN_DRAIN_S after the
    signal (then its compute pool stops the busy child, up to about 3 s more), not after the
    job; with a second SIGTERM, without waiting for the drain."""
    env = service_env(
        HMCC_EMBEDDED_WORKERS="1",
        HMCC_FAULT_SLOW_PAIR_ID="*",
        HMCC_FAULT_SLOW_S="30",
        HMCC_SHUTDOWN_DRAIN_S=str(drain_s),
    )
    proc, url = start_api(env)
    try:
        assert _post(url, _pair()).status_code == 202
        t0 = time.monotonic()
        for _ in range(signals):
            proc.send_signal(signal.SIGTERM)
            time.sleep(0.3)
        assert _exits_within(proc, 15), proc.log()
        elapsed = time.monotonic() - t0
        if signals == 1:
            assert drain_s <= elapsed < drain_s + 5, elapsed
        else:
            assert elapsed < 6, elapsed
    finally:
        proc.stop()


# -- the HTTP edge ------------------------------------------------------------------------------


def test_a_client_that_disconnects_mid_upload_is_logged_once_at_info_as_499(
    api: tuple[Proc, str],
) -> None:
    """A client that sends part of its body and closes: one INFO line, counted as 499, no
    ERROR and no 500."""
    proc, url = api
    before = _requests_counted(url, "/v1/verifications", "499")
    with connect(url) as sock:
        send_head(
            sock,
            "POST",
            "/v1/verifications",
            Content_Type="application/json",
            Content_Length="100000",
        )
        sock.sendall(b"{" * 1000)
        time.sleep(0.2)
    assert wait_until(
        lambda: _requests_counted(url, "/v1/verifications", "499") == before + 1, 10
    ), httpx.get(f"{url}/metrics", trust_env=False).text
    lines = [json.loads(line) for line in proc.log().splitlines() if line.startswith("{")]
    disconnects = [r for r in lines if "disconnect" in str(r.get("message", r.get("msg", "")))]
    assert len(disconnects) == 1, disconnects
    assert disconnects[0].get("level", disconnects[0].get("levelname")) == "INFO"
    assert not [r for r in lines if r.get("level", r.get("levelname")) == "ERROR"], lines
    assert _requests_counted(url, "/v1/verifications", "500") == 0


def test_a_content_length_that_is_not_a_number_is_400(api: tuple[Proc, str]) -> None:
    """``Content-Length: abc`` and a 200 kB body after it: 400 naming Content-Length (not 414,
    as when the refusal was read from the body h11 had left in its buffer)."""
    _, url = api
    with connect(url) as sock:
        send_head(
            sock,
            "POST",
            "/v1/verifications",
            Content_Type="application/json",
            Content_Length="abc",
        )
        sock.sendall(b" " * (200 * 1024))
        answer = read_answer(sock)
    assert answer.status == 400, answer
    error = answer.json()["error"]
    assert error["code"] == "bad_request"
    assert "Content-Length" in error["message"]


def test_a_compressed_body_is_415_naming_the_encoding(api: tuple[Proc, str]) -> None:
    """``Content-Encoding: gzip``: 415 naming it, not 422 "invalid JSON"."""
    _, url = api
    answer = _post(url, b"\x1f\x8b\x08\x00", **{"Content-Encoding": "gzip"})
    assert answer.status_code == 415, answer.text
    error = answer.json()["error"]
    assert error["code"] == "unsupported_media_type"
    assert "gzip" in error["message"]


def test_a_70kb_header_sent_in_one_segment_is_431(api: tuple[Proc, str]) -> None:
    """A head over the 16 KB limit that arrives whole (h11's own limit holds only for an
    incomplete head) is refused like one that arrives in pieces."""
    _, url = api
    head = b"GET /healthz HTTP/1.1\r\nHost: hmcc.test\r\nX-Big: " + b"b" * 70_000 + b"\r\n\r\n"
    with connect(url) as sock:
        sock.sendall(head)
        answer = read_answer(sock)
    assert answer.status == 431, answer
    error = answer.json()["error"]
    assert error["code"] == "headers_too_large"
    assert str(MAX_HEAD_BYTES) in error["message"]
    assert httpx.get(f"{url}/healthz", trust_env=False).status_code == 200


def test_a_head_just_under_the_limit_is_read(api: tuple[Proc, str]) -> None:
    """The limit is the head's size, not the size of what arrived with it: a request whose
    head fits is read even when its body comes in the same segment."""
    _, url = api
    body = _pair(64 * 1024)
    head = (
        b"POST /v1/verifications HTTP/1.1\r\nHost: hmcc.test\r\n"
        b"Content-Type: application/json\r\n"
        + f"Content-Length: {len(body)}\r\n".encode()
        + b"X-Pad: "
        + b"p" * (MAX_HEAD_BYTES - 400)
        + b"\r\n\r\n"
    )
    assert len(head) < MAX_HEAD_BYTES < len(head + body)
    with connect(url) as sock:
        sock.sendall(head + body)  # one write: the head and its body arrive together
        answer = read_answer(sock)
    assert answer.status == 202, answer


# -- the body budget under load -----------------------------------------------------------------


@pytest.fixture(scope="module")
def small_budget() -> Iterator[str]:
    env = service_env(
        HMCC_MAX_BODY_BYTES=str(MB),
        HMCC_BODY_BUDGET_BYTES=str(MB),
        HMCC_BODY_WAIT_S="1",
        HMCC_RETRY_AFTER_S="7",
    )
    proc, url = start_api(env)
    try:
        yield url
    finally:
        proc.stop()


def test_bytes_beyond_the_budget_wait_then_503_counted_under_the_route(
    small_budget: str,
) -> None:
    """A 1 MB budget: one body holds 700 kB of it, half sent; a second body's bytes beyond the
    300 kB left wait HMCC_BODY_WAIT_S, then 503 ``server_busy`` + Retry-After (counted under
    its route); the first finishes and is accepted."""
    url = small_budget
    size = 900_000
    body = _pair(size)
    before = _requests_counted(url, "/v1/verifications", "503")
    first, second = connect(url), connect(url)
    try:
        for sock in (first, second):
            send_head(
                sock,
                "POST",
                "/v1/verifications",
                Content_Type="application/json",
                Content_Length=str(size),
            )
        first.sendall(body[:700_000])
        time.sleep(0.3)
        second.sendall(body[:400_000])
        answer = read_answer(second)
        assert answer.status == 503, answer
        assert answer.json()["error"]["code"] == "server_busy"
        assert answer.headers["retry-after"] == "7"
        first.sendall(body[700_000:])
        answer = read_answer(first)
        assert answer.status == 202, answer
    finally:
        first.close()
        second.close()
    assert _requests_counted(url, "/v1/verifications", "503") == before + 1
