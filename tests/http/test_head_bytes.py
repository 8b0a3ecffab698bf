"""What counts toward a head's byte bounds (`timeouts.MAX_HEAD_BYTES`, `MAX_HEADS_HELD`): the bytes of the unfinished
head alone, however a connection's pipelined requests fall into reads. Drives `ReadTimeoutProtocol` read by read
(no socket: a real server's reads are the kernel's to split, tests/http/test_read_timeouts.py sends them)."""

from __future__ import annotations

import asyncio
import random
from typing import Any

import pytest
import uvicorn
from uvicorn.server import ServerState

from jointlimits.service.http import timeouts


async def _app(scope: Any, receive: Any, send: Any) -> None:  # never called: no request is started
    raise AssertionError


class _Transport(asyncio.Transport):
    def __init__(self) -> None:
        super().__init__()
        self.closed = False

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return ("127.0.0.1", 1) if name in ("peername", "sockname") else default

    def is_closing(self) -> bool:
        return self.closed

    def close(self) -> None:
        self.closed = True

    def write(self, data: Any) -> None:
        pass

    def pause_reading(self) -> None:
        pass

    def resume_reading(self) -> None:
        pass


def _requests(rng: random.Random, chunked: bool) -> tuple[bytes, list[tuple[int, int]], list[tuple[int, int]]]:
    """Up to 12 pipelined requests (GETs and POSTs with a Content-Length or, if `chunked`, sometimes a chunked body;
    bodies up to 100 kB that may hold CRLF CRLF; sometimes CRLFs between requests), where each head begins and ends
    in the stream, and where each chunked body does."""
    stream, heads, chunked_bodies = b"", [], []
    for _ in range(rng.randint(1, 12)):
        stream += b"\r\n" * rng.choice((0, 0, 0, 1, 3))  # llhttp skips them before a request
        body = rng.choice((b"", b"\r\n\r\nGET / HTTP/1.1\r\n\r\n" * rng.randint(1, 5000), b"x" * rng.randint(1, 10**5)))
        framing = b"Content-Length: %d" % len(body)
        if body and chunked and rng.random() < 0.5:
            size = rng.randint(300, 5000)
            body = b"".join(b"%x\r\n%s\r\n" % (len(body[i : i + size]), body[i : i + size])
                            for i in range(0, len(body), size)) + b"0\r\n\r\n"
            framing = b"Transfer-Encoding: chunked"
        pad = b"a" * rng.randint(0, 20_000)
        head = b"POST /v1/evaluate HTTP/1.1\r\nHost: h\r\nX-Pad: %s\r\n%s\r\n\r\n" % (pad, framing)
        if not body and rng.random() < 0.5:
            head = b"GET /healthz HTTP/1.1\r\nHost: h\r\n\r\n"
        heads.append((len(stream), len(stream) + len(head)))
        if framing.startswith(b"Transfer"):
            chunked_bodies.append((len(stream) + len(head), len(stream) + len(head) + len(body)))
        stream += head + body
    return stream, heads, chunked_bodies


def _kept(head: bytes) -> int:
    line, *headers = head.split(b"\r\n")[:-2]
    return len(line.split(b" ")[1]) + sum(len(h) - 2 for h in headers)  # "name: value": the name and the value


@pytest.mark.parametrize("chunked", [False, True], ids=["content_length", "chunked"])
@pytest.mark.parametrize("seed", range(40))
def test_only_the_unfinished_heads_bytes_count_whatever_the_reads(seed, chunked, monkeypatch):
    """After each read, the bytes counted for the connection's head are exactly those of its unfinished head received
    so far: not the bodies or the heads before it in the same read (they were: an honest pipelining client got 431),
    and not fewer (a head's blank line split over two reads ends it where it ends). After a chunked body in the read
    where the head began, never fewer, and more by at most the bytes of that read before the head."""
    rng = random.Random(seed)
    monkeypatch.setattr(timeouts.ReadTimeoutProtocol, "heads_held", 0)
    loop = asyncio.new_event_loop()
    try:
        config = uvicorn.Config(_app, log_level="warning")
        protocol = timeouts.bounded(timeouts.ReadTimeoutProtocol, header_timeout=10.0, max_connections=10)(
            config=config, server_state=ServerState(), app_state={}, _loop=loop)
        protocol._start_asgi_task = lambda cycle, app: None  # the parse alone: no request runs
        protocol.connection_made(_Transport())
        stream, heads, chunked_bodies = _requests(rng, chunked)
        fed, began = 0, {}  # where the read began in which each head began
        while fed < len(stream):
            n = rng.choice((1, 2, 3, 5, rng.randint(1, 3000), rng.randint(1, 256 * 1024)))
            inside = [end - k - fed for _, end in heads for k in (1, 2, 3) if end - k > fed]
            if inside and rng.random() < 0.3:  # this read ends inside the next head's blank line
                n = min(inside)
            protocol.data_received(stream[fed : fed + n])
            began.update((start, fed) for start, _ in heads if fed <= start < fed + n)
            fed = min(fed + n, len(stream))
            # The first request never ends here (no request runs), so each later complete head is queued behind it
            # and held by what uvicorn keeps of it: its URL, its headers' names and values.
            assert list(protocol._queued) == [_kept(stream[start:end]) for start, end in heads[1:] if end <= fed]
            assert timeouts.ReadTimeoutProtocol.heads_held == protocol._head_size + sum(protocol._queued)
            within = [start for start, end in heads if start < fed < end]  # the head the parser is in, if any
            if not within:
                assert protocol._head_size == 0, (seed, fed)
                continue
            start = within[0]
            if any(began[start] < body_end and body_start < start for body_start, body_end in chunked_bodies):
                assert fed - start <= protocol._head_size <= fed - began[start], (seed, fed)
            else:
                assert protocol._head_size == fed - start, (seed, fed)
        assert not protocol.transport.is_closing()
        protocol.connection_lost(None)
        assert timeouts.ReadTimeoutProtocol.heads_held == 0  # the queued heads are released with their connection
    finally:
        loop.close()


def test_queued_heads_count_toward_the_workers_heads_and_past_it_nothing_more_is_read(monkeypatch):
    """A connection's requests pipelined behind a stalled one are held whole (uvicorn keeps their scopes until their
    turn): up to MAX_PIPELINED heads of MAX_HEAD_BYTES, 1 MiB a connection, that the worker's budget did not see.
    Now they count toward MAX_HEADS_HELD until they start; a worker past it reads no more pipelined requests from
    the connection (its owed answers are sent, then it closes, as past MAX_PIPELINED), and releases them all when
    the connection ends."""
    loop = asyncio.new_event_loop()
    try:
        monkeypatch.setattr(timeouts.ReadTimeoutProtocol, "heads_held", 0)
        config = uvicorn.Config(_app, log_level="warning")
        protocol = timeouts.bounded(timeouts.ReadTimeoutProtocol, header_timeout=10.0, max_connections=10)(
            config=config, server_state=ServerState(), app_state={}, _loop=loop)
        protocol._start_asgi_task = lambda cycle, app: None  # the first request stalls: the others queue behind it
        protocol.connection_made(_Transport())
        head = b"GET /healthz HTTP/1.1\r\nHost: h\r\nX-Pad: %s\r\n\r\n" % (b"a" * 60_000)
        protocol.data_received(head * 3)
        assert list(protocol._queued) == [_kept(head)] * 2
        assert timeouts.ReadTimeoutProtocol.heads_held == 2 * _kept(head)
        timeouts.ReadTimeoutProtocol.heads_held += timeouts.MAX_HEADS_HELD  # other connections' heads
        protocol.data_received(head * 2)  # past the bound: not read, the connection cut
        assert len(protocol.pipeline) == 2 and protocol._cut
        protocol.connection_lost(None)
        assert timeouts.ReadTimeoutProtocol.heads_held == timeouts.MAX_HEADS_HELD
    finally:
        loop.close()


def test_a_connection_reads_its_bounds_alone_from_the_environment(monkeypatch):
    """The protocols read their unset bounds per connection, each field alone: the whole table, `Settings()` (20
    variables read and parsed, 35-160 us), read twice per HTTP connection was ~7-15% of a worker's CPU for a
    connection asking `/healthz`. A variable changed between connections is read by the next one."""
    from jointlimits.service import settings

    def whole_table(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("Settings() read per connection")

    monkeypatch.setattr(settings, "Settings", whole_table)
    monkeypatch.setattr(timeouts, "Settings", whole_table, raising=False)
    loop = asyncio.new_event_loop()
    try:
        config = uvicorn.Config(_app, log_level="warning")
        made = []
        for header in ("7", "8"):
            monkeypatch.setenv("JOINTLIMITS_HEADER_TIMEOUT", header)
            monkeypatch.setenv("JOINTLIMITS_MAX_CONNECTIONS", "9")
            monkeypatch.setenv("JOINTLIMITS_WRITE_TIMEOUT", "11")
            made.append(timeouts.ReadTimeoutProtocol(config=config, server_state=ServerState(), app_state={}, _loop=loop))
    finally:
        loop.close()
    assert [(p.header_timeout, p.max_connections, p.write_timeout) for p in made] == [(7.0, 9, 11.0), (8.0, 9, 11.0)]
