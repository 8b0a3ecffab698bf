"""The write side (issue 19), on a real uvicorn with the project's protocols and a 1 s write timeout: a client
that stops reading is dropped within JOINTLIMITS_WRITE_TIMEOUT and frees what it held; an answer's bytes stay
counted in the in-flight budget until they have left; a session holds one unread reply at most; a ping flood
queues no pongs; a session message still arriving is bounded by the body timeout. The drills on `jointlimits
serve` (RSS against the sizing rule) are in tests/ops/test_write_drills.py."""

from __future__ import annotations

import socket
import time

import httpx
import pytest
import uvicorn

from jointlimits.client import codec
from jointlimits.service.http import timeouts
from jointlimits.service.settings import Settings
from tests import drills as lt
from tests.inprocess import frame, read_close, read_frame, serve, upgrade

pytestmark = [pytest.mark.slow, pytest.mark.serial]  # the write-side bounds one by one on in-process servers, each waits out a timeout

WRITE_TIMEOUT, MESSAGE_TIMEOUT = 1.0, 1.5
SLACK = 1.5  # scheduling on a loaded 2-core machine
B = "application/msgpack"
JOINTS = 2000  # E+G+H msgpack: a ~9.6 MB answer, more than the kernel's buffers take
BODY = codec.encode(lt.array_scene(JOINTS, pairs=JOINTS), binary=True)[0]


@pytest.fixture(scope="module")
def live():
    settings = Settings(token=None, cors_origins=(), body_timeout=MESSAGE_TIMEOUT, session_idle_seconds=2.0)
    with serve(settings, write_timeout=WRITE_TIMEOUT, message_timeout=MESSAGE_TIMEOUT) as server:
        yield server


def counted(live, reason: str) -> float:
    return lt.scraped(live.port, "jointlimits_connections_closed_total", reason=reason)


def wait_for(cond, give_up: float) -> float | None:
    """Seconds until `cond()` holds (None: not within `give_up`)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < give_up:
        if cond():
            return time.monotonic() - t0
        time.sleep(0.02)
    return None


def test_a_stalled_http_client_is_dropped_and_its_answer_counted_until_then(live):
    before = counted(live, "slow_read")
    s = lt.stalled_socket(live.port)
    s.sendall(lt.post_bytes(BODY, B, B))
    # The answer is written, most of it waits in the process: its bytes stay reserved in the budget meanwhile.
    assert wait_for(lambda: sum(live.buffered()) > 1_000_000, 20) is not None
    held = live.held()
    assert held >= sum(live.buffered()) > 1_000_000, (held, live.buffered())
    t0 = time.monotonic()
    assert wait_for(lambda: lt.dropped(s), WRITE_TIMEOUT + SLACK) is not None  # the client sees a reset
    s.close()
    assert time.monotonic() - t0 <= WRITE_TIMEOUT + SLACK
    assert wait_for(lambda: live.held() == 0, 2) is not None
    assert counted(live, "slow_read") == before + 1


def test_a_streamed_json_answer_stalled_is_dropped_without_a_traceback(live, caplog):
    """JSON answers are written in pieces: the route waits in `send` while the buffer is full, holding its
    reservation; the reset ends the wait (no exception, no ERROR) and releases it."""
    import logging

    caplog.set_level(logging.INFO)
    s = lt.stalled_socket(live.port)
    s.sendall(lt.post_bytes(BODY, B, "application/json"))
    assert wait_for(lambda: sum(live.buffered()) > 1_000_000, 20) is not None
    assert live.held() > sum(live.buffered())
    assert wait_for(lambda: lt.dropped(s), WRITE_TIMEOUT + SLACK) is not None
    s.close()
    assert wait_for(lambda: live.held() == 0, 3) is not None
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert [r.levelname for r in caplog.records if r.name == "jointlimits.timeouts"] == ["WARNING"]


def test_a_client_that_reads_gets_the_whole_answer(live):
    r = httpx.post(f"http://127.0.0.1:{live.port}/v1/evaluate", content=BODY,
                   headers={"Content-Type": B, "Accept": B}, timeout=30)
    assert r.status_code == 200 and len(r.content) > 5_000_000
    assert codec.decode(r.content, codec.BINARY).batches[0].hessian.shape == (JOINTS, 24, 24)
    assert wait_for(lambda: live.held() == 0, 2) is not None


def test_a_slow_but_steady_reader_is_not_dropped(live):
    """The bound is on a stall (the buffer full for the whole timeout), not on the answer's total time."""
    s = lt.stalled_socket(live.port, rcvbuf=65536)
    s.sendall(lt.post_bytes(BODY, B, B))
    s.settimeout(5)
    got, t0 = b"", time.monotonic()
    while b"\r\n\r\n" not in got:
        got += s.recv(65536)
    head, _, body = got.partition(b"\r\n\r\n")
    length = int(next(h.split(b":")[1] for h in head.split(b"\r\n") if h.lower().startswith(b"content-length")))
    while len(body) < length:
        chunk = s.recv(65536)
        assert chunk, "dropped"
        body += chunk
        time.sleep(0.004)  # ~16 MB/s at most: slower than the server writes, never a second without reading
    took = time.monotonic() - t0
    assert not lt.dropped(s)
    s.close()
    assert head.startswith(b"HTTP/1.1 200") and took > WRITE_TIMEOUT / 2, took  # it did take its time
    assert codec.decode(body, codec.BINARY).batches[0].hessian.shape == (JOINTS, 24, 24)


def test_pings_are_answered_the_latest_first(live):
    s, head = upgrade(live.port)
    assert head.startswith(b"HTTP/1.1 101")
    s.sendall(frame(0x9, b"one"))
    assert read_frame(s) == (0xA, b"one")
    s.sendall(frame(0x9, b"a") + frame(0x9, b"b") + frame(0x9, b"c"))  # one read: the latest is answered
    assert read_frame(s) == (0xA, b"c")
    s.close()


def _session(live, messages: int) -> socket.socket:
    opening, evaluate = lt.session_frames(2000)
    s, head = upgrade(live.port, rcvbuf=4096)
    assert head.startswith(b"HTTP/1.1 101"), head
    s.sendall(frame(0x2, opening) + frame(0x2, evaluate) * messages)
    return s


def evaluated(live) -> float:
    return lt.scraped(live.port, "jointlimits_session_messages_total", kind="evaluate")


def test_a_stalled_session_holds_one_reply_and_is_dropped(live):
    before, evals = counted(live, "slow_read"), evaluated(live)
    s = _session(live, messages=3)
    t0 = time.monotonic()
    assert wait_for(lambda: lt.dropped(s), 5 + WRITE_TIMEOUT + SLACK) is not None
    s.close()
    # The opening's reply and one evaluation went out; the next evaluate was never read (its reply would wait).
    assert evaluated(live) - evals <= 1
    assert wait_for(lambda: live.held() == 0, 2) is not None
    assert counted(live, "slow_read") == before + 1
    assert time.monotonic() - t0 < 5 + WRITE_TIMEOUT + SLACK


def test_a_close_the_client_does_not_answer_is_bounded(live):
    """The session's idle close (4408, after 2 s) goes to a client that reads nothing: it gets the write timeout
    to answer it, then a reset (uvicorn alone would wait 10 s, then leave the kernel holding the unread bytes)."""
    opening, _ = lt.session_frames(50)
    s, head = upgrade(live.port, rcvbuf=4096)
    assert head.startswith(b"HTTP/1.1 101")
    s.sendall(frame(0x2, opening))
    t0 = time.monotonic()
    took = wait_for(lambda: lt.dropped(s), 2.0 + WRITE_TIMEOUT + SLACK)
    s.close()
    assert took is not None and took >= 2.0 + WRITE_TIMEOUT - 0.2, took


def test_a_ping_flood_queues_no_pongs(live):
    """Pongs are not queued while writes are paused: the process holds at most the high-water mark for them."""
    s, head = upgrade(live.port, rcvbuf=4096)
    assert head.startswith(b"HTTP/1.1 101")
    ping = frame(0x9, b"p" * 125) * 512
    s.settimeout(0.2)
    sent, most, t0 = 0, 0, time.monotonic()
    while time.monotonic() - t0 < 3 * WRITE_TIMEOUT and not lt.dropped(s):
        try:
            sent += s.send(ping)
        except TimeoutError:
            pass
        except OSError:
            break
        most = max([most, *live.buffered()])
    s.close()
    assert sent > 4_000_000  # the kernel's buffers alone would have taken a few MB of pongs
    assert most <= 2**16 + 256, most  # asyncio's high-water mark (64 KiB) and one pong (not one per ping)


def test_a_message_still_arriving_is_bounded_by_the_body_timeout(live):
    before = counted(live, "slow_message")
    opening, _ = lt.session_frames(50)
    s, head = upgrade(live.port)
    assert head.startswith(b"HTTP/1.1 101")
    whole = frame(0x2, opening)
    s.sendall(whole[: len(whole) // 2])  # half a message, then nothing
    t0 = time.monotonic()
    assert read_close(s, give_up=MESSAGE_TIMEOUT + 5) == timeouts.MESSAGE_TOO_SLOW
    assert MESSAGE_TIMEOUT - 0.2 <= time.monotonic() - t0 <= MESSAGE_TIMEOUT + SLACK
    s.close()
    assert counted(live, "slow_message") == before + 1


def test_a_message_trickled_byte_by_byte_is_bounded_too(live):
    opening, _ = lt.session_frames(50)
    s, head = upgrade(live.port)
    whole = frame(0x2, opening)
    t0, i = time.monotonic(), 0
    try:
        while time.monotonic() - t0 < MESSAGE_TIMEOUT + 3 and i < len(whole):
            s.sendall(whole[i : i + 10])
            i += 10
            time.sleep(0.05)
    except OSError:
        pass
    assert read_close(s, give_up=5) == timeouts.MESSAGE_TOO_SLOW
    s.close()
    assert time.monotonic() - t0 <= MESSAGE_TIMEOUT + SLACK + 0.5


def test_cli_hands_the_write_timeout_and_the_protocols_to_uvicorn(monkeypatch):
    import os

    from jointlimits.service import cli

    monkeypatch.setattr(os, "environ", {k: v for k, v in os.environ.items() if not k.startswith("JOINTLIMITS_")})
    assert cli.build_parser().parse_args(["serve"]).write_timeout == 30.0
    os.environ["JOINTLIMITS_WRITE_TIMEOUT"] = "4.5"
    assert cli.build_parser().parse_args(["serve"]).write_timeout == 4.5
    a = cli.build_parser().parse_args(["serve", "--write-timeout", "7", "--workers", "1"])
    seen: dict = {}
    monkeypatch.setattr(uvicorn, "run", lambda *args, **kwargs: seen.update(kwargs))
    monkeypatch.setattr(cli.signal, "signal", lambda *args: None)
    assert cli.serve(a) == 0
    assert seen["http"] == "jointlimits.service.http.timeouts:ReadTimeoutProtocol"
    assert seen["ws"] == "jointlimits.service.http.timeouts:WriteTimeoutWebSocketProtocol"
    assert Settings().write_timeout == 7.0  # what the protocols read
    for bad in (["--write-timeout", "0"], ["--write-timeout", "-1"], ["--write-timeout", "inf"]):
        with pytest.raises(SystemExit):
            cli.build_parser().parse_args(["serve", *bad])
