"""Hostile probes against the live page (issue 50): crowds of slow or idle connections and
requests without one Host header (docs/live.md).

Everything runs over 127.0.0.1, every loop bounded by a count or a deadline.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import time

import pytest
from test_bridge_safety import _wait
from test_live_web import _get, _raw, _upgrade, served, smoke_team  # noqa: F401

from icco_torchrl.live.guard import LOG_EVERY
from icco_torchrl.live.web import MAX_CLIENTS, MAX_IDLE_PER_IP, SPARE_CONNECTIONS


# ---------------------------------------------------------------------- crowds of connections
def _closed(socks: list[socket.socket], wait: float = 2.0) -> set[socket.socket]:
    """The sockets of ``socks`` the server closed (EOF within ``wait`` seconds)."""
    readable, _, _ = select.select(socks, [], [], wait)
    closed = set()
    for sock in readable:
        sock.setblocking(False)
        with contextlib.suppress(BlockingIOError, ConnectionError):
            if sock.recv(1) == b"":
                closed.add(sock)
    return closed


def _crowd_of_connections(port: int, n: int, sources: int = 1) -> list[socket.socket]:
    """``n`` connections that never finish a request: every other one idle, the others slow
    (half a request head, never ended), from 127.0.0.1 (``sources`` 1) or spread over
    127.0.0.2 ... 127.0.0.(sources + 1)."""
    crowd = []
    for k in range(n):
        source = "127.0.0.1" if sources == 1 else f"127.0.0.{2 + k % sources}"
        sock = socket.create_connection(
            ("127.0.0.1", port), timeout=2.0, source_address=(source, 0)
        )
        if k % 2:
            sock.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n".encode())
        crowd.append(sock)
    return crowd


@pytest.mark.parametrize("sources", [1, 5], ids=["from one IP", "from five IPs"])
def test_a_crowd_of_slow_or_idle_connections_does_not_lock_a_new_tab_out(served, sources):  # noqa: F811
    """319 slow or idle connections (the server keeps 256 tabs + 64 others), from the tab's own
    IP or from five others: a new tab still loads the page on a kept-alive connection and opens
    its socket; the oldest waiting connections make room."""
    server, url = served(smoke_team())
    port = int(url.rsplit(":", 1)[1])
    crowd = _crowd_of_connections(port, MAX_CLIENTS + SPARE_CONNECTIONS - 1, sources)
    page = None
    try:
        assert _wait(lambda: server._open + server.stats["evicted"] == len(crowd))
        page = socket.create_connection(("127.0.0.1", port), timeout=5.0)  # as a browser: kept
        page.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
        head, end = b"", time.monotonic() + 5.0
        while b"\r\n\r\n" not in head and time.monotonic() < end:
            head += page.recv(65_536)
        assert head.startswith(b"HTTP/1.1 200"), head[:80]
        status, _, _ = _upgrade(port)  # the tab's socket, one connection more
        assert status == 101
        assert _get(port)[0] == 200
        assert server.stats["evicted"] >= 1 and server._open <= MAX_CLIENTS + SPARE_CONNECTIONS
        closed = _closed(crowd)
        assert closed and closed <= set(crowd[: len(crowd) - MAX_IDLE_PER_IP + 8])  # the oldest
    finally:
        for sock in [*crowd, *([page] if page else [])]:
            sock.close()


def test_a_connection_that_never_finishes_its_request_is_closed_after_the_idle_timeout(served):  # noqa: F811
    server, url = served(smoke_team(), idle_timeout=0.5)
    port = int(url.rsplit(":", 1)[1])
    crowd = _crowd_of_connections(port, 4)
    try:
        start, closed = time.monotonic(), 0
        for sock in crowd:
            sock.settimeout(5.0)
            with contextlib.suppress(ConnectionError):
                closed += sock.recv(1) == b""
        assert closed == 4 and time.monotonic() - start < 3.0
        assert _get(port)[0] == 200
    finally:
        for sock in crowd:
            sock.close()


# ---------------------------------------------------------------------- malformed HTTP
@pytest.mark.parametrize("hosts", [0, 2], ids=["no Host", "two Hosts"])
def test_a_request_without_one_host_is_a_one_line_400_and_no_traceback(served, caplog, hosts):  # noqa: F811
    caplog.set_level(logging.INFO)
    server, url = served(smoke_team())
    port = int(url.rsplit(":", 1)[1])
    lines = ["GET / HTTP/1.1", *[f"Host: 127.0.0.1:{port}"] * hosts, "Connection: close"]
    start = time.monotonic()
    for _ in range(200):
        status, _, body = _raw(port, lines)
        assert status == 400 and body.strip() and body.strip().count("\n") == 0, body
    seconds = time.monotonic() - start
    records = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert not [r for r in records if r.exc_info or "Traceback" in r.getMessage()]
    assert 1 <= len(records) <= seconds / LOG_EVERY + 2, [r.getMessage() for r in records][:3]
    assert all(len(r.getMessage()) <= 300 for r in records)
    assert sum(len(r.getMessage()) for r in records) < 5_000  # ~150 KB of tracebacks before
    assert server.stats["malformed"] == 200 and _get(port)[0] == 200
