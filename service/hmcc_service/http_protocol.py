"""The HTTP/1.1 protocol ``hmcc serve`` runs: uvicorn's (h11), with an answer the client can
read to a request whose head it refuses.

h11 reads a request line and headers of at most :data:`MAX_HEAD_BYTES` together; past that, or
for a head that is not HTTP, uvicorn answers a bare 400 and closes the connection at once. The
rest of the request is then unread, so the kernel resets the connection, and a client still
sending (a 1 MB URL) sees the reset, not the answer. :class:`HttpProtocol` answers in the API's
error envelope instead, 414 ``uri_too_long`` for a request line over the limit, 431
``headers_too_large`` for headers over it, 400 ``bad_request`` otherwise, and then closes the
way nginx's lingering close does: it stops sending (FIN), reads and drops whatever the client
still sends, and closes when the client does, or after :data:`LINGER_S`. Nothing it drops is
kept.
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

    def data_received(self, data: bytes) -> None:
        if not self._draining:
            super().data_received(data)

    def send_400_response(self, msg: str) -> None:
        """Called by uvicorn when h11 refuses the request head."""
        head, _ = self.conn.trailing_data
        limit = self.config.h11_max_incomplete_event_size or MAX_HEAD_BYTES
        line = head.find(b"\n")
        if len(head) > limit and not _END_OF_HEAD.search(head):
            if line < 0 or line > limit:
                status, code = 414, ErrorCode.uri_too_long
                message = f"the request line (method and URL) is longer than {limit} bytes"
            else:
                status, code = 431, ErrorCode.headers_too_large
                message = f"the request's headers are longer than {limit} bytes"
        else:
            status, code, message = 400, ErrorCode.bad_request, "not a valid HTTP/1.1 request"
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
