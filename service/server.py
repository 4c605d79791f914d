"""The uvicorn server options of ``gpnarx serve``: read timeouts, a connection limit, the drain window.

uvicorn bounds the idle time between two requests of a connection (``timeout_keep_alive``) but
not the time a client takes to send a request's headers, so a client sending one header line
every few seconds holds its connection for ever. ``GuardedH11Protocol`` (uvicorn's h11 protocol)
adds:

- a header deadline: a connection that has not sent a complete request head within
  ``settings.header_timeout`` seconds of opening (or of the end of the previous answer) is answered
  408 (a problem detail, ``Connection: close``) and closed;
- a connection limit: a connection opened while ``settings.max_connections`` are open is answered
  503 with ``Retry-After`` at once, before anything is read, and closed.

The body deadline (``settings.body_timeout``: 408 when the body has not arrived in time) is kept
by ``service.middleware.GuardMiddleware``; a request head still incomplete after
``settings.max_header_bytes`` bytes is answered 400 and closed (h11's incomplete-event limit).
"""
from __future__ import annotations

import json

from uvicorn.protocols.http.h11_impl import H11Protocol

from .problems import PROBLEM_MEDIA_TYPE, ProblemError
from .settings import Settings


def _raw_problem(p: ProblemError) -> bytes:
    """A complete HTTP/1.1 answer holding problem ``p``, closing the connection."""
    body = json.dumps(p.to_dict()).encode()
    head = [f"HTTP/1.1 {p.status} {p.title}", f"content-type: {PROBLEM_MEDIA_TYPE}",
            f"content-length: {len(body)}", "connection: close",
            *(f"{k}: {v}" for k, v in p.headers.items())]
    return ("\r\n".join(head) + "\r\n\r\n").encode("latin-1") + body


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a header deadline and a connection limit (``protocol_for``)."""

    header_timeout: float = 10.0  # [s]; 0: none
    max_connections: int = 0  # 0: none
    retry_after: int = 2  # [s]

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._header_timer = None
        if self.max_connections and len(self.connections) > self.max_connections:
            transport.write(_raw_problem(ProblemError(
                503, f"the server holds its limit of {self.max_connections} open connections "
                     f"(GPNARX_MAX_CONNECTIONS); retry after {self.retry_after} s",
                headers={"Retry-After": str(self.retry_after)}, limit=self.max_connections)))
            transport.close()
            return
        self._arm()

    def _waiting_for_head(self) -> bool:
        return self.cycle is None or self.cycle.response_complete

    def _arm(self) -> None:
        if self.header_timeout > 0 and self._header_timer is None:
            self._header_timer = self.loop.call_later(self.header_timeout, self._head_expired)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def data_received(self, data: bytes) -> None:
        before = self.cycle
        super().data_received(data)
        if self.cycle is not before and not self._waiting_for_head():
            self._disarm()  # a complete request head: the app (and the body deadline) takes over
        elif self._waiting_for_head():
            self._arm()  # (part of) the next request head: it must be complete in time

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._disarm()  # idle from here: uvicorn's keep-alive timeout applies until the next byte

    def connection_lost(self, exc) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _head_expired(self) -> None:
        self._header_timer = None
        if self._waiting_for_head() and not self.transport.is_closing():
            self.transport.write(_raw_problem(ProblemError(
                408, f"the request head was not received within {self.header_timeout:g} s (GPNARX_HEADER_TIMEOUT)",
                limit=self.header_timeout)))
            self.transport.close()


def protocol_for(settings: Settings) -> type[GuardedH11Protocol]:
    """A ``GuardedH11Protocol`` class carrying ``settings``' header deadline and connection limit."""
    return type("GuardedH11Protocol", (GuardedH11Protocol,), {
        "header_timeout": float(settings.header_timeout), "max_connections": int(settings.max_connections),
        "retry_after": int(settings.retry_after)})


def uvicorn_options(settings: Settings) -> dict:
    """Keyword arguments of ``uvicorn.run`` / ``uvicorn.Config`` for ``settings``."""
    return {"http": protocol_for(settings), "timeout_keep_alive": settings.keep_alive_timeout,
            "h11_max_incomplete_event_size": settings.max_header_bytes,
            "timeout_graceful_shutdown": settings.drain_seconds}
