"""The /v1 gate against a real ``hmcc serve``, over sockets driven by hand: what it refuses is
answered while the client is still sending its body, so the body was never read (the API key,
the content type), and the body budget holds the bytes that arrived, not the lengths declared."""

from __future__ import annotations

import json
import select
from collections.abc import Iterator

import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from tests.support.procs import service_env, start_api
from tests.support.raw_http import connect, read_answer, send_head

pytestmark = pytest.mark.procs

KEY = "s3cret"
MB = 1024 * 1024
#: Each body's size (two fit in the budget, a third would not).
SHARE = 400_000


@pytest.fixture(scope="module")
def url() -> Iterator[str]:
    env = service_env(
        HMCC_API_KEY=KEY,
        HMCC_MAX_BODY_BYTES=str(MB),
        HMCC_BODY_BUDGET_BYTES=str(MB),
        HMCC_BODY_WAIT_S="1",
        HMCC_RETRY_AFTER_S="7",
    )
    api, base = start_api(env)
    try:
        yield base
    finally:
        api.stop()


def _chunk(data: bytes) -> bytes:
    return f"{len(data):x}\r\n".encode() + data + b"\r\n"


@pytest.mark.parametrize(
    ("headers", "status", "code"),
    [
        ({"Content_Type": "application/json"}, 401, "unauthorized"),
        ({"Content_Type": "application/json", "X_API_Key": "wrong"}, 401, "unauthorized"),
        ({"Content_Type": "text/plain", "X_API_Key": KEY}, 415, "unsupported_media_type"),
    ],
    ids=["no-key", "wrong-key", "wrong-content-type"],
)
def test_a_refused_body_is_answered_before_it_is_sent(
    url: str, headers: dict[str, str], status: int, code: str
) -> None:
    """A chunked POST (the length unknown, so nothing refuses it up front) sends its head and
    a first 64 KB chunk of what would be 63 MB, and waits: the refusal comes while the body is
    unfinished, so the API answered without reading it."""
    with connect(url) as sock:
        send_head(sock, "POST", "/v1/verifications", Transfer_Encoding="chunked", **headers)
        sock.sendall(_chunk(b"x" * 65536))
        answer = read_answer(sock)
    assert answer.status == status, answer
    assert answer.json()["error"]["code"] == code
    if status == 401:
        assert answer.headers["www-authenticate"] == "X-API-Key"


def _padded_pair(size: int) -> bytes:
    """A valid pair as JSON, padded with whitespace to ``size`` bytes."""
    pair = simulate_pair(SimulationOptions(n_inliers=40), seed=1)
    pair.pop("ground_truth")
    raw = json.dumps(pair).encode()
    assert len(raw) < size
    return raw + b" " * (size - len(raw))


def test_a_declared_length_holds_nothing_of_the_budget_until_its_bytes_come(url: str) -> None:
    """Four 400 KB bodies at once against a 1 MB budget, each half sent: the budget holds the
    bytes that arrived (4 kB), not the lengths declared (1.6 MB), so none is refused or kept
    waiting, and all four finish and are accepted. (Bytes beyond the budget: see
    tests/reliability/test_uploads.py.)"""
    body = _padded_pair(SHARE)
    socks = [connect(url) for _ in range(4)]
    try:
        for sock in socks:
            send_head(
                sock,
                "POST",
                "/v1/verifications",
                Content_Type="application/json",
                Content_Length=str(len(body)),
                X_API_Key=KEY,
            )
            sock.sendall(body[:1000])
        readable, _, _ = select.select(socks, [], [], 1.5)
        assert not readable, "a body was answered before it was sent"
        for sock in socks:
            sock.sendall(body[1000:])
            answer = read_answer(sock)
            assert answer.status in (200, 202), answer
    finally:
        for sock in socks:
            sock.close()
