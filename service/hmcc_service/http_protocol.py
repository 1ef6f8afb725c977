"""The HTTP/1.1 protocol ``hmcc serve`` runs: uvicorn's (h11), with an answer the client can
read to a request whose head it refuses.

A request line and headers may hold :data:`MAX_HEAD_BYTES` together. h11 enforces that only
while a head is incomplete (its ``max_incomplete_event_size``): a longer head that arrives in
one segment would be read, so :class:`HttpProtocol` measures each head itself, however its
bytes come. uvicorn answers a head h11 refuses with a bare 400 and closes the connection at
once; the rest of the request is then unread, so the kernel resets the connection, and a client
still sending (a 1 MB URL) sees the reset, not the answer. :class:`HttpProtocol` answers in the
API's error envelope instead, 414 ``uri_too_long`` for a request line over the limit, 431
``headers_too_large`` for headers over it, 400 ``bad_request`` otherwise (naming
Content-Length when that is what is wrong), and then closes the way nginx's lingering close
does: it stops sending (FIN), reads and drops whatever the client still sends, and closes when
the client does, or after :data:`LINGER_S`. Nothing it drops is kept.
"""

from __future__ import annotations

import json
import re
from http import HTTPStatus

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from hmcc_worker.protocol import ErrorCode

__all__ = ["LINGER_S", "MAX_HEAD_BYTES", "HttpProtocol"]

#: Request line plus headers, bytes, at most (h11's default, set explicitly by ``hmcc serve``).
MAX_HEAD_BYTES = 16 * 1024
#: Seconds a refused connection is drained at most before it is closed.
LINGER_S = 10.0

_END_OF_HEAD = re.compile(rb"\n\r?\n")


class HttpProtocol(H11Protocol):
    """uvicorn's h11 protocol with a readable answer to a refused request head (see the module
    docstring). Pass it as uvicorn's ``http``, with ``h11_max_incomplete_event_size``."""

    _draining = False
    _head = b""

    def data_received(self, data: bytes) -> None:
        if not self._draining:
            super().data_received(data)

    def handle_events(self) -> None:
        """h11's limit holds only while a head is incomplete: a longer head that arrives in
        one piece would be read. Each head is measured here, however its bytes came."""
        if self.conn.their_state is h11.IDLE:
            buffered, _ = self.conn.trailing_data
            end = _END_OF_HEAD.search(buffered)
            # kept for send_400_response: h11 drops the head from its buffer as it parses it
            self._head = buffered[: end.end()] if end else buffered
            if len(self._head) > self._limit():
                self.send_400_response("request head too large")
                return
        super().handle_events()

    def _limit(self) -> int:
        return self.config.h11_max_incomplete_event_size or MAX_HEAD_BYTES

    def send_400_response(self, msg: str) -> None:
        """Called by uvicorn when h11 refuses the request head (and by :meth:`handle_events`)."""
        status, code, message = _refusal(self._head, self._limit())
        self.logger.warning("refused a request head: %d %s", status, message)
        body = json.dumps({"error": {"code": code, "message": message}}).encode()
        headers = [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ]
        for event in (
            h11.Response(status_code=status, headers=headers, reason=HTTPStatus(status).phrase),
            h11.Data(data=body),
            h11.EndOfMessage(),
        ):
            self.transport.write(self.conn.send(event))
        self._draining = True
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.loop.call_later(LINGER_S, self.transport.close)


_CONTENT_LENGTH = re.compile(rb"^content-length[ \t]*:[ \t]*(.*?)[ \t]*\r?$", re.I | re.M)


def _refusal(head: bytes, limit: int) -> tuple[int, str, str]:
    """Status, code and message of a refused request ``head`` (all of it, or what came)."""
    if len(head) > limit:
        line = head.find(b"\n")
        if line < 0 or line > limit:
            return (
                414,
                ErrorCode.uri_too_long,
                f"the request line (method and URL) is longer than {limit} bytes",
            )
        message = f"the request's headers are longer than {limit} bytes"
        return 431, ErrorCode.headers_too_large, message
    lengths = _CONTENT_LENGTH.findall(head)
    if any(not value.isdigit() for value in lengths) or len(set(lengths)) > 1:
        return 400, ErrorCode.bad_request, "Content-Length is not a number of bytes"
    return 400, ErrorCode.bad_request, "not a valid HTTP/1.1 request"
