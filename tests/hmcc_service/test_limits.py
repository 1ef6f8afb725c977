"""The /v1 gate against a real ``hmcc serve``, over sockets driven by hand: what it refuses is
answered while the client is still sending its body, so the body was never read (the API key,
the content type), and bodies beyond the budget wait, then get 503 ``server_busy``."""

from __future__ import annotations

import json
import select
import socket
from collections.abc import Iterator

import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from tests.support.procs import service_env, start_api
from tests.support.raw_http import connect, read_answer, send_head

pytestmark = pytest.mark.procs

KEY = "s3cret"
MB = 1024 * 1024
#: Each body's share of the budget (two fit in it, a third does not).
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


def test_bodies_beyond_the_budget_wait_then_get_503(url: str) -> None:
    """Four 400 KB bodies at once against a 1 MB budget: two are admitted and read (each
    waits here, half sent), the other two wait HMCC_BODY_WAIT_S for a share, then get 503
    ``server_busy`` + Retry-After, without a byte of theirs read. The two admitted finish and
    are accepted."""
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
        answered: list[socket.socket] = []
        while len(answered) < 2:
            readable, _, _ = select.select([s for s in socks if s not in answered], [], [], 60)
            assert readable, f"{len(answered)} answered within 60 s, expected 2"
            answered += readable
        assert len(answered) == 2, "only the bodies beyond the budget are refused"
        for sock in answered:
            answer = read_answer(sock)
            assert answer.status == 503, answer
            assert answer.json()["error"]["code"] == "server_busy"
            assert answer.headers["retry-after"] == "7"
        for sock in socks:
            if sock not in answered:
                sock.sendall(body[1000:])
                answer = read_answer(sock)
                assert answer.status in (200, 202), answer
    finally:
        for sock in socks:
            sock.close()
