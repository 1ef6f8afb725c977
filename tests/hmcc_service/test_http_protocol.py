"""Request heads ``hmcc serve`` refuses (a 1 MB URL, 1 MB of headers, not HTTP at all), over a
socket: the client sends all of it without a reset, reads an answer in the API's error
envelope, then the end of the connection; the server goes on answering."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from hmcc_service.http_protocol import MAX_HEAD_BYTES
from tests.support.procs import service_env, start_api
from tests.support.raw_http import connect, read_answer

pytestmark = pytest.mark.procs

MB = 1024 * 1024
HOST_END = b"Host: hmcc.test\r\n\r\n"
HEALTHZ = b"GET /healthz HTTP/1.1\r\nHost: hmcc.test\r\n"


@pytest.fixture(scope="module")
def url() -> Iterator[str]:
    api, base = start_api(service_env())
    try:
        yield base
    finally:
        api.stop()


@pytest.mark.parametrize(
    ("request_bytes", "status", "code"),
    [
        (b"GET /v1/verifications/" + b"a" * MB + b" HTTP/1.1\r\n" + HOST_END, 414, "uri_too_long"),
        (HEALTHZ + b"X-Big: " + b"b" * MB + b"\r\n\r\n", 431, "headers_too_large"),
        (HEALTHZ + b"X-Many: y\r\n" * (MB // 11) + b"\r\n", 431, "headers_too_large"),
        (b"\x16\x03\x01 not http at all\r\n\r\n", 400, "bad_request"),
    ],
    ids=["1MB-url", "1MB-header", "many-headers", "not-http"],
)
def test_a_refused_request_head_gets_an_answer_not_a_reset(
    url: str, request_bytes: bytes, status: int, code: str
) -> None:
    with connect(url) as sock:
        sock.sendall(request_bytes)  # all of it: the server reads what it refuses
        answer = read_answer(sock)
        assert sock.recv(1) == b"", "the server closes (FIN), it does not reset"
    assert answer.status == status, answer
    error = answer.json()["error"]
    assert error["code"] == code
    if status != 400:
        assert str(MAX_HEAD_BYTES) in error["message"]
    assert httpx.get(f"{url}/healthz").status_code == 200
