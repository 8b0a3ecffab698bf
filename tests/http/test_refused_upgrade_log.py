"""A refused session upgrade (the bearer token's 401, a draining worker's 503) is an answer, not a server error:
uvicorn's WebSocket protocol marks only an accept or a close before accept as the end of a handshake and logged
"ASGI callable returned without completing handshake" at ERROR for each denial, an alert per reconnect during a
rollout. `service/http/timeouts.py:WriteTimeoutWebSocketProtocol.send` marks a sent denial as the handshake's end."""

from __future__ import annotations

import logging
import time

import pytest

from jointlimits.service.settings import Settings
from tests.inprocess import serve, upgrade

pytestmark = pytest.mark.serial  # waits a fixed 0.2 s for a log line that must not come


def _refused(caplog: pytest.LogCaptureFixture, settings: Settings, draining: bool) -> tuple[bytes, list[str]]:
    with caplog.at_level(logging.INFO), serve(settings) as live:
        live.app.state.draining = draining
        s, head = upgrade(live.port)
        s.close()
        time.sleep(0.2)  # the server's task ends after the response is written
    return head, [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]


def test_a_draining_workers_503_logs_no_error(caplog: pytest.LogCaptureFixture) -> None:
    head, errors = _refused(caplog, Settings(token=None, cors_origins=()), draining=True)
    assert head.startswith(b"HTTP/1.1 503")
    assert errors == []


def test_a_missing_tokens_401_logs_no_error(caplog: pytest.LogCaptureFixture) -> None:
    head, errors = _refused(caplog, Settings(token="s3cret", cors_origins=()), draining=False)
    assert head.startswith(b"HTTP/1.1 401")
    assert errors == []
