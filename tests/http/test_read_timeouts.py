"""Read timeouts (issue 9, item 9) and clients that leave mid-upload (item 10), on a real uvicorn.

The server runs in-process with `ReadTimeoutProtocol` (1 s for the head) and a 1.5 s body
timeout, as `jointlimits serve` runs it with its own settings; the slowloris drill of
50 connections against `jointlimits serve --workers 2` is in tests/ops/test_ops_load.py.
"""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager

import httpx
import pytest
import uvicorn

from jointlimits.service.app import create_app
from jointlimits.service.http import timeouts
from jointlimits.service.settings import Settings
from tests.drills import scraped
from tests.http.test_contract_live import running
from tests.http.test_errors_http import _json

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # waits out header and body deadlines (~7 s)

HEADER_TIMEOUT, BODY_TIMEOUT = 1.0, 1.5
SLACK = 1.5  # scheduling on a loaded 2-core machine; the timers themselves are exact


@contextmanager
def serve_with_timeouts(body_timeout: float = BODY_TIMEOUT) -> Iterator[int]:
    settings = Settings(max_body_bytes=2_000_000, token=None, cors_origins=(), body_timeout=body_timeout)
    http = timeouts.bounded(timeouts.ReadTimeoutProtocol, header_timeout=HEADER_TIMEOUT)
    config = uvicorn.Config(create_app(settings), log_level="warning", lifespan="on", http=http)
    with running(config) as (_, port):
        yield port


@pytest.fixture(scope="module")
def port() -> Iterator[int]:
    with serve_with_timeouts() as p:
        yield p


def requests_counted(port: int, status: str) -> float:
    return scraped(port, "jointlimits_http_requests_total", route="/v1/evaluate", status=status)


def closed_counted(port: int, reason: str) -> float:
    """Connections closed for a slow head, by `reason` (silent, slow_head), as /metrics counts them."""
    return scraped(port, "jointlimits_connections_closed_total", reason=reason)


def wait_closed(s: socket.socket, give_up: float) -> tuple[float | None, bytes]:
    """Seconds until the server closes `s` (None: still open after `give_up`), and what it sent."""
    t0, got = time.monotonic(), b""
    s.settimeout(0.1)
    while time.monotonic() - t0 < give_up:
        try:
            chunk = s.recv(4096)
        except TimeoutError:
            continue
        except ConnectionResetError:
            return time.monotonic() - t0, got
        if not chunk:
            return time.monotonic() - t0, got
        got += chunk
    return None, got


HEAD = b"POST /v1/evaluate HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"


def test_a_connection_that_sends_nothing_is_closed(port):
    before = closed_counted(port, "silent"), closed_counted(port, "slow_head")
    with socket.create_connection(("127.0.0.1", port)) as s:
        after, got = wait_closed(s, HEADER_TIMEOUT + 10)
    assert after is not None and after < HEADER_TIMEOUT + SLACK, after
    assert got == b""  # nothing to answer
    # No request exists for it: the connection layer counts it (the lifespan state hands it the metrics).
    assert (closed_counted(port, "silent"), closed_counted(port, "slow_head")) == (before[0] + 1, before[1])


def test_half_headers_get_408_and_are_closed(port):
    before = closed_counted(port, "silent"), closed_counted(port, "slow_head"), requests_counted(port, "408")
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(HEAD)  # no blank line, ever
        after, got = wait_closed(s, HEADER_TIMEOUT + 10)
    assert after is not None and HEADER_TIMEOUT - 0.1 < after < HEADER_TIMEOUT + SLACK, after
    assert got.startswith(b"HTTP/1.1 408 ")
    said = json.loads(got.split(b"\r\n\r\n", 1)[1])  # a fault list, as every other refusal (was plain text)
    assert said == {"detail": [{"loc": ["header"], "type": "timeout", "msg": "request headers not received within "
                                f"{HEADER_TIMEOUT:g} s (JOINTLIMITS_HEADER_TIMEOUT)"}]}
    assert closed_counted(port, "slow_head") == before[1] + 1 and closed_counted(port, "silent") == before[0]
    assert requests_counted(port, "408") == before[2]  # not a request: its head never completed


def test_headers_trickled_one_byte_at_a_time_are_cut_at_the_deadline(port):
    """Each byte resets no timer: the deadline is for the whole head."""
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(HEAD)
        t0 = time.monotonic()
        closed = None
        for byte in b"X-Slow: " + b"a" * 100:
            try:
                s.sendall(bytes([byte]))
            except OSError:
                closed = time.monotonic() - t0
                break
            after, _ = wait_closed(s, 0.2)
            if after is not None:
                closed = time.monotonic() - t0
                break
    assert closed is not None and closed < HEADER_TIMEOUT + SLACK, closed


def test_half_body_gets_408_naming_the_body_and_is_closed(port):
    before = requests_counted(port, "408")
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(HEAD + b"Content-Length: 1000\r\n\r\n{")
        after, got = wait_closed(s, BODY_TIMEOUT + 10)
    assert after is not None and BODY_TIMEOUT - 0.1 < after < BODY_TIMEOUT + SLACK, after
    head, _, body = got.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 408 ") and b"connection: close" in head.lower()
    detail = json.loads(body)["detail"]
    assert detail[0]["loc"] == ["body"] and "JOINTLIMITS_BODY_TIMEOUT" in detail[0]["msg"]
    assert requests_counted(port, "408") == before + 1


def test_keep_alive_idle_is_not_a_slow_head(port):
    """Idle time between two requests on one connection is the keep-alive timeout's, not the head's."""
    before = closed_counted(port, "silent") + closed_counted(port, "slow_head")
    with httpx.Client(base_url=f"http://127.0.0.1:{port}") as c:
        assert c.post("/v1/evaluate", json=_json()).status_code == 200
        time.sleep(HEADER_TIMEOUT + 0.5)  # longer than a head may take, shorter than keep-alive (5 s)
        assert c.post("/v1/evaluate", json=_json()).status_code == 200
        assert c.get("/healthz").status_code == 200
    assert closed_counted(port, "silent") + closed_counted(port, "slow_head") == before


def test_a_body_sent_in_pieces_within_the_deadline_is_answered(port):
    body = json.dumps(_json()).encode()
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(HEAD + f"Content-Length: {len(body)}\r\n\r\n".encode())
        for i in range(0, len(body), len(body) // 4 + 1):
            s.sendall(body[i : i + len(body) // 4 + 1])
            time.sleep(0.1)
        s.settimeout(10)
        assert s.recv(12) == b"HTTP/1.1 200"


def test_a_client_leaving_mid_upload_counts_as_499_not_500(port):
    before = {k: requests_counted(port, k) for k in ("499", "500")}
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(HEAD + b"Content-Length: 100000\r\n\r\n{" + b" " * 5000)
        time.sleep(0.3)  # the app is reading the body
    deadline = time.monotonic() + 10
    while requests_counted(port, "499") == before["499"] and time.monotonic() < deadline:
        time.sleep(0.05)
    assert requests_counted(port, "499") == before["499"] + 1
    assert requests_counted(port, "500") == before["500"]
    assert httpx.get(f"http://127.0.0.1:{port}/healthz").status_code == 200


def test_cli_hands_the_timeouts_to_uvicorn_and_the_workers(monkeypatch):
    import os

    from jointlimits.service import cli

    monkeypatch.setattr(os, "environ", {k: v for k, v in os.environ.items() if not k.startswith("JOINTLIMITS_")})
    a = cli.build_parser().parse_args(["serve"])
    assert (a.header_timeout, a.body_timeout) == (10.0, 30.0)
    os.environ["JOINTLIMITS_HEADER_TIMEOUT"] = "2.5"
    a = cli.build_parser().parse_args(["serve", "--body-timeout", "7", "--workers", "1"])
    seen: dict = {}
    monkeypatch.setattr(uvicorn, "run", lambda *args, **kwargs: seen.update(kwargs))
    monkeypatch.setattr(cli.signal, "signal", lambda *args: None)
    assert cli.serve(a) == 0
    assert seen["http"] == "jointlimits.service.http.timeouts:ReadTimeoutProtocol"
    assert Settings().header_timeout == 2.5 and Settings().body_timeout == 7.0
    for bad in (["--header-timeout", "0"], ["--body-timeout", "-1"], ["--body-timeout", "inf"]):
        with pytest.raises(SystemExit):
            cli.build_parser().parse_args(["serve", *bad])


def test_a_request_head_past_its_byte_bound_gets_431_at_once_and_is_closed(port):
    """The head's deadline bounds its time, not its bytes: before the bound one connection streaming a header
    value (or a URL) for the 10 s deadline took a worker from 69 to 533 MiB RSS and stalled its other requests
    5.5 s (httptools joins a header's pieces by copying: quadratic). Now the 431 comes once the head passes
    `MAX_HEAD_BYTES`, long before the deadline, with the connection layer's count."""
    before = closed_counted(port, "head_too_large"), closed_counted(port, "slow_head")
    for head in (HEAD + b"X-Big: " + b"a" * (4 * timeouts.MAX_HEAD_BYTES),  # one long header
                 b"GET /healthz?" + b"a" * (4 * timeouts.MAX_HEAD_BYTES)):  # one long URL
        with socket.create_connection(("127.0.0.1", port)) as s:
            try:
                s.sendall(head)  # no blank line: only the byte bound can end this head early
            except OSError:  # closed while sending: the answer is still in the receive buffer
                pass
            after, got = wait_closed(s, HEADER_TIMEOUT + 10)
        assert after is not None and after < HEADER_TIMEOUT - 0.1, after
        status, _, body = got.partition(b"\r\n\r\n")
        assert status.startswith(b"HTTP/1.1 431 ") and b"connection: close" in status.lower()
        fault = json.loads(body)["detail"][0]
        assert fault["loc"] == ["header"] and fault["type"] == "too_large"
        assert str(timeouts.MAX_HEAD_BYTES) in fault["msg"]
    assert (closed_counted(port, "head_too_large"), closed_counted(port, "slow_head")) == (before[0] + 2, before[1])


def test_a_head_within_its_byte_bound_and_a_body_past_it_are_answered(port):
    """Only the head's bytes count: a large header within the bound, and a body (sent with its head in one write)
    much larger than the head's bound, are answered as usual."""
    body = json.dumps(_json()).encode() + b" " * (2 * timeouts.MAX_HEAD_BYTES)  # JSON allows trailing spaces
    near = b"X-Near: " + b"a" * (timeouts.MAX_HEAD_BYTES - len(HEAD) - 200) + b"\r\n"
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(HEAD + near + f"Content-Length: {len(body)}\r\n\r\n".encode() + body)
        s.settimeout(10)
        assert s.recv(12) == b"HTTP/1.1 200"


def test_unfinished_heads_past_the_workers_budget_get_503_busy_and_the_budget_comes_back(port, monkeypatch):
    """The head's bound is per connection; a worker's connections are many: 3000 connections each holding 60 kB of an
    unfinished head took a worker from 93 to 266 MiB (one client opens ~11 000 in the 10 s deadline). The bytes of
    unfinished heads are counted per worker (`MAX_HEADS_HELD`); a head that arrives whole in one read holds nothing."""
    monkeypatch.setattr(timeouts, "MAX_HEADS_HELD", 100_000)
    part = HEAD + b"X-Part: " + b"a" * 40_000
    before = closed_counted(port, "heads_full")
    held = [socket.create_connection(("127.0.0.1", port)) for _ in range(2)]
    for s in held:
        s.sendall(part)
    time.sleep(0.3)  # both heads read: 80 kB held
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(part)  # 120 kB: past the budget
        after, got = wait_closed(s, HEADER_TIMEOUT + 10)
    assert after is not None and after < HEADER_TIMEOUT - 0.1, after
    status, _, body = got.partition(b"\r\n\r\n")
    assert status.startswith(b"HTTP/1.1 503 ") and b"retry-after: 5" in status.lower()
    fault = json.loads(body)["detail"][0]
    assert fault["loc"] == ["header"] and fault["type"] == "busy" and "100000" in fault["msg"]
    assert closed_counted(port, "heads_full") == before + 1
    assert httpx.get(f"http://127.0.0.1:{port}/healthz").status_code == 200  # a whole head holds nothing
    for s in held:
        s.close()
    deadline = time.monotonic() + 10
    while timeouts.ReadTimeoutProtocol.heads_held and time.monotonic() < deadline:
        time.sleep(0.05)
    assert timeouts.ReadTimeoutProtocol.heads_held == 0  # every held byte given back


def test_the_rest_of_a_body_answered_early_is_no_head(port):
    """A body refused on its declared size is answered 413 at once, while the client goes on sending it: those bytes
    are the rest of that request, not the next one's head, and never count against `MAX_HEAD_BYTES` (they did, for
    a merge: the flood drill's oversized requests got 431)."""
    before = closed_counted(port, "head_too_large")
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(HEAD + b"Content-Length: 1000000000000\r\n\r\n")
        try:
            for _ in range(16):  # 4 x the head's bound, in pieces, as a client streaming its body does
                s.sendall(b" " * (timeouts.MAX_HEAD_BYTES // 4))
                time.sleep(0.01)
        except OSError:  # closed after the answer: it is in the receive buffer
            pass
        _, got = wait_closed(s, HEADER_TIMEOUT + 10)
    assert got.startswith(b"HTTP/1.1 413 ") and b" 431 " not in got, got[:200]
    assert closed_counted(port, "head_too_large") == before


# ---------------------------------------------------------------- pipelining: requests sent ahead of their answers

GET = b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"


def answers(got: bytes) -> list[bytes]:
    """Each answer's status line and headers, in order (the bodies are `{"status":"ok"}` or a fault list)."""
    return [a.partition(b"\r\n\r\n")[0].lower() for a in got.split(b"HTTP/1.1 ")[1:]]


def test_requests_pipelined_past_the_bound_are_not_read_and_the_connection_closes_after_the_answers_owed(port):
    """uvicorn parsed every request of each read and read on after each answer: one connection pipelining `GET
    /healthz` for 10 s took a worker from 68 to 640 MiB and 10 s of CPU, answering 41. Now a connection has at most
    `MAX_PIPELINED` requests queued behind the one answered; the next is not read: those owed are answered, the last
    with `connection: close`, then the connection closes (the client resends the rest, RFC 9112 9.3.2)."""
    owed = timeouts.MAX_PIPELINED + 1
    before = closed_counted(port, "pipelined")
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(GET * (owed + 1000))  # 42 kB, one write: read at once, as a hostile client's flood is
        after, got = wait_closed(s, HEADER_TIMEOUT + 10)
    heads = answers(got)
    assert after is not None and owed <= len(heads) < 2 * owed, len(heads)  # a read may end between requests
    assert all(h.startswith(b"200 ") for h in heads)
    assert b"connection: close" in heads[-1] and not any(b"connection: close" in h for h in heads[:-1])
    assert closed_counted(port, "pipelined") == before + 1
    with socket.create_connection(("127.0.0.1", port)) as s:  # within the bound: every one answered, kept alive
        s.sendall(GET * owed)
        s.settimeout(10)
        got = b""
        while got.count(b"HTTP/1.1 200 ") < owed:
            got += s.recv(65536)
        assert b"connection: close" not in got.lower()


def test_a_pipelined_head_past_its_bound_does_not_answer_the_request_before_it(port):
    """A head over `MAX_HEAD_BYTES` behind a request still being answered: the 431 was written at once, so the
    client read it as the answer to that earlier, valid request (and the server logged an ERROR writing the real one
    to the closed transport). Now the earlier request gets its own answer, with `connection: close`, then EOF."""
    before = closed_counted(port, "head_too_large")
    with socket.create_connection(("127.0.0.1", port)) as s:
        try:
            s.sendall(GET + HEAD + b"X-Big: " + b"a" * (4 * timeouts.MAX_HEAD_BYTES))
        except OSError:  # closed while sending: the answer is in the receive buffer
            pass
        after, got = wait_closed(s, HEADER_TIMEOUT + 10)
    heads = answers(got)
    assert after is not None and len(heads) == 1, heads
    assert heads[0].startswith(b"200 ") and b"connection: close" in heads[0]
    assert closed_counted(port, "head_too_large") == before + 1


def test_a_pipelined_head_has_the_head_deadline_too(port):
    """Half a head sent behind a complete request had no deadline of its own (the head timer is armed when an answer
    completes, before any byte of the next head arrives): it was held for the keep-alive timeout (75 s under
    `jointlimits serve`). Now it gets `JOINTLIMITS_HEADER_TIMEOUT`, then 408, as a head alone does."""
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(GET + HEAD)  # the second head never ends
        after, got = wait_closed(s, HEADER_TIMEOUT + 10)
    heads = answers(got)
    assert after is not None and after < HEADER_TIMEOUT + SLACK, after
    assert [h[:4] for h in heads] == [b"200 ", b"408 "]


# ---------------------------------------------------------------- a body in tiny chunks

def chunked(body: bytes, size: int) -> bytes:
    """`body` as a chunked transfer of `size`-byte chunks, with its end."""
    return b"".join(b"%x\r\n%s\r\n" % (len(body[i : i + size]), body[i : i + size]) for i in range(0, len(body), size)) + b"0\r\n\r\n"


def test_a_body_in_tiny_chunks_gets_413_once_its_chunks_outrun_its_bytes(port):
    """Each chunk of a body is a Python call in uvicorn's parser: 1-byte chunks took 0.39 us of the worker's CPU per
    body byte (16 x Content-Length's) and each read of them ~50 ms of the event loop, so for the body deadline (30 s)
    the worker's other clients waited 0.4 s per request (p50; 6 ms alone); a refused body's rest was parsed too (5 s
    of stall). Now a body gets `timeouts.MIN_CHUNKS` chunks, then one per `timeouts.CHUNK_BYTES` bytes; past it,
    nothing more is read: 413 naming the body, and the connection closed. Larger chunks are answered."""
    before = closed_counted(port, "body_chunks")
    body = json.dumps(_json()).encode() + b" " * 20_000  # JSON allows trailing spaces
    with socket.create_connection(("127.0.0.1", port)) as s:
        try:
            s.sendall(HEAD + b"Transfer-Encoding: chunked\r\n\r\n" + chunked(body, 1))
        except OSError:  # closed while sending: the answer is in the receive buffer
            pass
        _, got = wait_closed(s, BODY_TIMEOUT + 10)
    head, _, rest = got.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 413 ") and b"connection: close" in head.lower(), got[:300]
    fault = json.loads(rest)["detail"][0]
    assert fault["loc"] == ["body"] and fault["type"] == "too_large" and "chunks" in fault["msg"], fault
    assert closed_counted(port, "body_chunks") == before + 1
    with socket.create_connection(("127.0.0.1", port)) as s:  # the same body in chunks of CHUNK_BYTES: answered
        s.sendall(HEAD + b"Transfer-Encoding: chunked\r\n\r\n" + chunked(body, timeouts.CHUNK_BYTES))
        s.settimeout(10)
        assert s.recv(12) == b"HTTP/1.1 200"


def test_a_pipelined_head_counts_only_its_own_bytes_not_a_body_or_a_head_before_it(port):
    """An honest client pipelines a POST whose body is larger than the head's bound, or a request with a large head,
    and the next request, in one write; the read ends inside the next head. Only that head's bytes count toward
    `MAX_HEAD_BYTES` (and `MAX_HEADS_HELD`). The whole read was counted: the next head got 431 (the connection closed
    after the first answer). Each write is under 100 kB, which loopback hands over in one read (asyncio reads up to
    256 KiB); however the reads fall, each request gets its own answer."""
    body = json.dumps(_json()).encode() + b" " * (timeouts.MAX_HEAD_BYTES + 16_000)  # JSON allows trailing spaces
    near = b"X-Near: " + b"a" * (timeouts.MAX_HEAD_BYTES - 200) + b"\r\n"
    pad = b"X-Pad: " + b"a" * 4000  # the next head's unfinished header
    before = closed_counted(port, "head_too_large")
    for first in (HEAD + f"Content-Length: {len(body)}\r\n\r\n".encode() + body,  # a body past the bound
                  GET[:-2] + near + b"\r\n"):  # a complete head within the bound, nearly at it
        with socket.create_connection(("127.0.0.1", port)) as s:
            s.sendall(first + GET[:-2] + pad)  # the next head, unfinished
            time.sleep(0.3)  # read and parsed
            s.sendall(b"\r\nConnection: close\r\n\r\n")
            _, got = wait_closed(s, HEADER_TIMEOUT + 10)
        assert [h[:4] for h in answers(got)] == [b"200 ", b"200 "], got[:300]
    assert closed_counted(port, "head_too_large") == before
    assert timeouts.ReadTimeoutProtocol.heads_held == 0


@pytest.fixture(scope="module")
def patient() -> Iterator[int]:
    """A server whose body deadline leaves a loaded machine time to read a body in many small reads."""
    with serve_with_timeouts(body_timeout=20.0) as p:
        yield p


def test_a_content_length_body_in_tiny_writes_gets_413_once_its_reads_outrun_its_bytes(patient):
    """A Content-Length body was bounded by the body deadline alone: 1-byte writes with Nagle off (each its own read)
    cost 2.2 us of the worker's CPU a byte, 41% of a core for the 30 s deadline, against 0.01 us for the same body
    sent at once. Now each read of it is a piece, as a chunk is: `MIN_CHUNKS`, then one per `CHUNK_BYTES`; past it, 413
    naming the body, closed. An honest slow link's reads (a segment, 536 bytes or more) never come near it."""
    before = closed_counted(patient, "body_chunks")
    with socket.create_connection(("127.0.0.1", patient)) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.sendall(HEAD + b"Content-Length: 1000000\r\n\r\n")
        try:
            for _ in range(20 * timeouts.MIN_CHUNKS):  # each byte given time to be read alone
                s.sendall(b" ")
                time.sleep(0.0002)
        except OSError:  # closed: the answer is in the receive buffer
            pass
        _, got = wait_closed(s, 30)
    assert closed_counted(patient, "body_chunks") == before + 1
    head, _, rest = got.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 413 ") and b"connection: close" in head.lower(), got[:300]
    fault = json.loads(rest)["detail"][0]
    assert fault["loc"] == ["body"] and fault["type"] == "too_large" and "pieces" in fault["msg"], fault


def test_a_content_length_body_over_a_slow_link_is_answered(patient):
    """1460-byte segments (Ethernet's MSS), each read alone: more reads than `MIN_CHUNKS`, far below the bound."""
    body = json.dumps(_json()).encode() + b" " * 1_900_000  # JSON allows trailing spaces
    with socket.create_connection(("127.0.0.1", patient)) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.sendall(HEAD + f"Content-Length: {len(body)}\r\n\r\n".encode())
        for i in range(0, len(body), 1460):  # ~1300 segments
            s.sendall(body[i : i + 1460])
            time.sleep(0.0002)
        s.settimeout(10)
        assert s.recv(12) == b"HTTP/1.1 200"
