"""HTTP/1.1 by hand over a socket, for tests that decide what is sent when: a head and part of
a body, then the answer read before the rest is sent (which no HTTP client library allows)."""

from __future__ import annotations

import json
import socket
from dataclasses import dataclass
from http.client import HTTPResponse
from typing import Any

__all__ = ["Answer", "connect", "read_answer", "send_head"]


@dataclass(frozen=True)
class Answer:
    status: int
    headers: dict[str, str]
    body: bytes

    def json(self) -> Any:
        return json.loads(self.body)


def connect(url: str, timeout_s: float = 60.0) -> socket.socket:
    """A connection to ``http://host:port`` (a blocking socket with a generous timeout)."""
    host, port = url.removeprefix("http://").rstrip("/").rsplit(":", 1)
    return socket.create_connection((host, int(port)), timeout=timeout_s)


def send_head(sock: socket.socket, method: str, target: str | bytes, **headers: str) -> None:
    """The request line and headers (``Content_Type`` -> ``Content-Type``), nothing more."""
    if isinstance(target, str):
        target = target.encode()
    lines = [method.encode() + b" " + target + b" HTTP/1.1", b"Host: hmcc.test"]
    lines += [f"{k.replace('_', '-')}: {v}".encode() for k, v in headers.items()]
    sock.sendall(b"\r\n".join(lines) + b"\r\n\r\n")


def read_answer(sock: socket.socket) -> Answer:
    """The response the server sends on ``sock`` (status, lower-case headers, body)."""
    response = HTTPResponse(sock)
    response.begin()
    try:
        body = response.read()
    finally:
        response.close()
    return Answer(response.status, {k.lower(): v for k, v in response.getheaders()}, body)
