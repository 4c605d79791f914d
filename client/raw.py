"""One HTTP/1.1 POST on a raw socket, for floods of large bodies (the fault tests and probes).

``raw_post`` sends the body straight from a ``memoryview`` on a fresh connection, so the caller's
side copies nothing: the memory a flood costs is the server's alone, which httpx (that encodes and
buffers each request) would blur. It reads only the status line. Nothing in the product uses it;
``tests/test_faults.py`` and ``tools/fault_probes.py`` do.
"""
from __future__ import annotations

import socket


def raw_post(port: int, path: str, body: bytes, headers: dict[str, str] | None = None,
             host: str = "127.0.0.1", timeout: float = 60.0) -> int:
    """POST ``body`` (``Content-Type: application/json``) to ``http://host:port/path`` on a new connection.

    ``headers``: extra request headers (e.g. ``{"X-API-Key": ...}``); ``timeout``: seconds for the
    connection and each socket operation. Returns the answer's status code, or 0 when the server
    closed the connection before a status line came (a send cut short by the server is not an error:
    the server may answer before reading the whole body).
    """
    extra = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
    head = (f"POST {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\n{extra}"
            f"Content-Length: {len(body)}\r\n\r\n")
    with socket.create_connection((host, port), timeout=timeout) as s:
        s.sendall(head.encode())
        try:
            s.sendall(memoryview(body))
        except OSError:
            pass
        status = s.recv(64)
    return int(status.split()[1]) if status.startswith(b"HTTP/1.1 ") else 0
