"""A client's expected faults on a session (issue 19) are one log line at WARNING or below, never a traceback
at ERROR: invalid UTF-8 in a text frame (close 1007), a broken frame (close 1002), a reset mid-session."""

from __future__ import annotations

import json
import logging
import socket
import struct
import time

import pytest

from jointlimits.service.settings import Settings
from tests.drills import scene
from tests.inprocess import frame, read_close, serve, upgrade

pytestmark = pytest.mark.serial  # waits fixed fractions of a second for log lines that must not come

OPEN = json.dumps(scene(6, seed=3)).encode()


@pytest.fixture(scope="module")
def live():
    with serve(Settings(token=None, cors_origins=())) as server:
        yield server


def opened(port: int) -> socket.socket:
    s, head = upgrade(port)
    assert head.startswith(b"HTTP/1.1 101"), head
    s.sendall(frame(0x1, OPEN))
    return s


def no_tracebacks(records: list[logging.LogRecord]) -> None:
    bad = [r for r in records if r.levelno >= logging.ERROR or r.exc_info]
    assert not bad, [(r.name, r.levelname, r.getMessage()) for r in bad]


def wait_for(cond, give_up: float = 5.0) -> None:
    deadline = time.monotonic() + give_up
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.02)


@pytest.mark.parametrize("payload", [b"\xff\xfe", b'{"kind": "evaluate", "q": "\xc3\x28"}'], ids=["bytes", "in-json"])
def test_invalid_utf8_text_frame_closes_1007_with_one_line(live, caplog, payload):
    caplog.set_level(logging.INFO)
    s = opened(live.port)
    s.sendall(frame(0x1, payload))
    assert read_close(s) == 1007
    s.close()
    wait_for(lambda: any("1007" in r.getMessage() for r in caplog.records))
    time.sleep(0.2)  # the session's own end, logged after the close
    no_tracebacks(caplog.records)
    lines = [r for r in caplog.records if r.name == "jointlimits.timeouts" and "1007" in r.getMessage()]
    assert len(lines) == 1 and lines[0].levelno == logging.WARNING, [r.getMessage() for r in caplog.records]


@pytest.mark.parametrize("bad", [
    frame(0x1, b"{}", rsv=4),  # RSV1 without a negotiated extension
    b"\x81\x02{}",  # an unmasked client frame
    frame(0x3, b"x"),  # a reserved opcode
], ids=["rsv1", "unmasked", "opcode"])  # fmt: skip
def test_protocol_error_closes_1002_with_one_line(live, caplog, bad):
    caplog.set_level(logging.INFO)
    s = opened(live.port)
    s.sendall(bad)
    assert read_close(s) == 1002
    s.close()
    wait_for(lambda: any("1002" in r.getMessage() for r in caplog.records))
    time.sleep(0.2)
    no_tracebacks(caplog.records)
    lines = [r for r in caplog.records if r.name == "jointlimits.timeouts" and "1002" in r.getMessage()]
    assert len(lines) == 1 and lines[0].levelno == logging.WARNING


def test_resets_mid_session_and_mid_message_log_no_traceback(live, caplog):
    caplog.set_level(logging.INFO)
    before = live.connections()
    for partial in (False, True):
        s = opened(live.port)
        q = json.dumps({"kind": "evaluate", "q": scene(6, seed=3)["bodies"]["q"]}).encode()
        s.sendall(frame(0x1, q)[: 20 if partial else None])
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close = RST
        s.close()
    wait_for(lambda: live.connections() <= before)
    time.sleep(0.3)
    assert live.connections() <= before
    no_tracebacks(caplog.records)
    assert sum(r.getMessage() == "session" for r in caplog.records) >= 2  # each session's one access line
