"""Every close of a session reaches the client with its code and reason, and is counted under its own reason
(issue 20): an oversized message at the default 64 MiB limit (1009, 20 of 20 tries, a client that keeps
sending), a text message that is not UTF-8 (1007); the limits the opening reply reports are those in force."""

from __future__ import annotations

import json
import re
import time

import httpx
import pytest
import uvicorn
from websockets.exceptions import ConnectionClosed
from websockets.frames import Frame, Opcode
from websockets.sync.client import connect

from jointlimits.service.app import create_app
from jointlimits.service.settings import Settings
from tests.http.test_contract_live import LIMITS, running, serve

TRIES = 20


@pytest.fixture(scope="module")
def live():
    assert LIMITS.max_frame_bytes == Settings().max_frame_bytes == 64 * 2**20  # the default limit
    with serve() as url:
        yield url


def ws(url: str) -> str:
    return url.replace("http://", "ws://") + "/v1/sessions"


def counted(url: str, reason: str) -> float:
    text = httpx.get(url + "/metrics").text
    m = re.search(r'jointlimits_sessions_total\{reason="%s"\} ([0-9.]+)' % reason, text)
    return float(m.group(1)) if m else 0.0


def wait_counted(url: str, reason: str, n: float) -> float:
    deadline = time.monotonic() + 10
    while (got := counted(url, reason)) < n and time.monotonic() < deadline:
        time.sleep(0.02)
    return got


def close_of(url: str, *messages: bytes | str, keep_sending: int = 0) -> tuple[int | None, str]:
    """Send `messages` (then the last one `keep_sending` times more, not waiting for anything) and read: the
    close frame the client received."""
    with connect(ws(url), max_size=None, compression=None, open_timeout=30, close_timeout=30) as c:
        try:
            for m in [*messages, *[messages[-1]] * keep_sending]:
                c.send(m)
            c.recv(timeout=60)
        except ConnectionClosed as e:
            return (e.rcvd.code, e.rcvd.reason) if e.rcvd else (None, f"no close frame ({e})")
    return None, "the connection stayed open"


def test_an_oversized_message_is_read_as_1009_every_time(live):
    big = bytes(64 * 2**20 + 1)
    before = counted(live, "frame_too_large")
    closes = [close_of(live, big, keep_sending=2) for _ in range(TRIES)]
    codes = [code for code, _ in closes]
    assert codes == [1009] * TRIES, closes
    assert all("at most 67108864" in reason and "JOINTLIMITS_MAX_FRAME_BYTES" in reason for _, reason in closes)
    assert wait_counted(live, "frame_too_large", before + TRIES) == before + TRIES


def test_a_text_message_that_is_not_utf8_is_1007_with_a_reason(live):
    before = counted(live, "invalid_utf8")
    with connect(ws(live), open_timeout=30) as c:
        # A text frame whose payload is not UTF-8: websockets' client would not send one, so the raw frame.
        with c.protocol_mutex:
            c.protocol.send_frame(Frame(Opcode.TEXT, b"\xff\xfe"))
            c.send_data()
        with pytest.raises(ConnectionClosed) as e:
            c.recv(timeout=30)
    assert e.value.rcvd.code == 1007 and "UTF-8" in e.value.rcvd.reason
    assert wait_counted(live, "invalid_utf8", before + 1) == before + 1


def test_the_reported_limit_is_the_one_in_force_under_plain_uvicorn():
    """`uvicorn jointlimits.service.app:app` keeps uvicorn's 16 MiB ws_max_size: the opening reply says 16 MiB, not 64."""
    from jointlimits.client import Client
    from tests.sdk.test_client_sdk import readme_scene

    with running(uvicorn.Config(create_app(LIMITS), log_level="warning", lifespan="off")) as (_, port):  # uvicorn's defaults
        with Client(f"http://127.0.0.1:{port}").session(readme_scene().request()) as s:
            assert s.limits["max_frame_bytes"] == 16 * 2**20


def test_a_shutdown_closes_with_1012_and_a_reason():
    from jointlimits.client import Client, SessionClosed
    from tests.sdk.test_client_sdk import readme_scene

    request = readme_scene().request()
    with serve() as url:
        s = Client(url).session(request)
    # serve() has stopped the server: the session was closed by it, with its code and reason.
    with pytest.raises(SessionClosed) as e:
        s.evaluate(request.q)
    assert e.value.code == 1012 and "shutting down" in e.value.reason


def test_a_message_in_tiny_frames_is_closed_with_1009_once_its_frames_outrun_its_bytes(live):
    """Each frame of a message is ~6 us of websockets' parse on the event loop: a 300 kB message in 1-byte frames took
    1.8 s of the worker's CPU and stalled its other clients as long (a 64 MiB one, minutes). Now a message gets
    `MIN_CHUNKS` frames, then one per `CHUNK_BYTES` bytes, as a chunked body; past it, 1009 with the reason, and
    the rest is drained unparsed. The same message in frames of `CHUNK_BYTES` is answered."""
    from jointlimits.service.http.timeouts import CHUNK_BYTES, MIN_CHUNKS
    from tests.http.test_errors_http import _json

    doc = _json()
    message = json.dumps({"kind": "evaluate", "q": doc["bodies"]["q"]}).encode() + b" " * 20_000

    def fragmented(c, size: int) -> None:
        pieces = [message[i : i + size] for i in range(0, len(message), size)]
        with c.protocol_mutex:
            for i, p in enumerate(pieces):
                c.protocol.send_frame(Frame(Opcode.TEXT if i == 0 else Opcode.CONT, p, fin=i == len(pieces) - 1))
            c.send_data()

    before = counted(live, "frame_too_large")
    with connect(ws(live), open_timeout=30) as c:
        c.send(json.dumps(doc))
        assert json.loads(c.recv(timeout=30))["kind"] == "opened"
        fragmented(c, 1)
        with pytest.raises(ConnectionClosed) as e:
            c.recv(timeout=30)
    assert e.value.rcvd is not None and e.value.rcvd.code == 1009, e.value
    assert f"{MIN_CHUNKS} frames, then one per {CHUNK_BYTES} bytes" in e.value.rcvd.reason
    assert wait_counted(live, "frame_too_large", before + 1) == before + 1
    with connect(ws(live), open_timeout=30) as c:
        c.send(json.dumps(doc))
        assert json.loads(c.recv(timeout=30))["kind"] == "opened"
        fragmented(c, CHUNK_BYTES)
        assert json.loads(c.recv(timeout=30))["kind"] == "evaluation"
