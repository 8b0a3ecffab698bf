"""Sentences of the docs that no example runs, held to the code: the refusal of a flood of batches at the defaults
(docs/http-api.md), the sessions' close reasons in the metrics table (docs/deployment.md), and the install hints
of the optional imports, which must name a package a registry holds (jointlimits itself is on none)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import msgpack
import pytest

from jointlimits.service.http import binary, convert, document, routes, sessions
from jointlimits.service.http.errors import HttpError
from jointlimits.service.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
FLOOD = {"bodies": {}, "batches": [{}] * 300_000}


@pytest.mark.parametrize("decoder", [convert, binary], ids=["json", "msgpack"])
def test_300k_empty_batches_are_one_413_before_any_batch_is_read(decoder, monkeypatch):
    """docs/http-api.md, "Errors" (hostile bodies): at the defaults one 413 naming JOINTLIMITS_MAX_BATCHES, no batch read."""
    assert "300k empty batches (300 KB of msgpack, or its 1.2 MB JSON twin) are one\n413 fault" in \
        (ROOT / "docs" / "http-api.md").read_text()

    def never(*args: object) -> None:
        raise AssertionError("a batch was read")

    monkeypatch.setattr(document.Checker, "batch", never)
    body = msgpack.packb(FLOOD) if decoder is binary else json.dumps(FLOOD).encode()
    with pytest.raises(HttpError) as e:
        routes._evaluate(body, decoder, decoder, Settings())
    assert e.value.status == 413
    [fault] = e.value.faults
    assert fault.loc == ("body", "batches") and "JOINTLIMITS_MAX_BATCHES" in fault.msg, fault


def test_the_metrics_table_lists_every_reason_a_session_ends_with():
    row = next(line for line in (ROOT / "docs" / "deployment.md").read_text().splitlines()
               if line.startswith("| `jointlimits_sessions_total`"))
    listed = set(re.findall(r"`(\w+)`", row.split("`reason`:", 1)[1]))
    source = (ROOT / "service" / "http" / "sessions.py").read_text()
    # the reasons the session route counts: its disconnect table's, those it counts or closes with, its fallbacks
    reasons = set(sessions.DISCONNECT_REASONS.values()) | set(re.findall(r'labels\("(\w+)"\)', source))
    reasons |= {c.group(1) for c in re.finditer(r'raise Closing\([^\n]*"(\w+)"\)', source)}
    assert '"disconnect")' in source and '"error", proto.INTERNAL_ERROR' in source
    reasons |= {"disconnect", "error"}
    assert {"uploads_full", "too_many_sessions", "idle", "scene_too_large"} <= reasons  # the scan finds them
    assert reasons <= listed, reasons - listed


def test_install_hints_name_a_package_a_registry_holds():
    extras = re.findall(r"^(\w+) = \[", (ROOT / "pyproject.toml").read_text().split("[project.optional-dependencies]")[1],
                        flags=re.M)
    hints = []
    for folder in ("service", "schemas", "client", "jointlimits"):
        for path in (ROOT / folder).rglob("*.py"):
            hints += re.findall(r"pip install ([^\"'()]+?) \(the (\w+) extra\)", path.read_text())
    assert len(hints) >= 4, hints  # scipy, pyuipc, yourdfpy, matplotlib
    for package, extra in hints:
        assert not package.startswith("jointlimits"), package  # the project is published on no registry
        assert extra in extras, (extra, extras)

