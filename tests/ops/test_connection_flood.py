"""A connection flood against `jointlimits serve` (1 worker, loopback): one client opens connections as fast as it
can and sends nothing. The worker holds `--max-connections` of them and answers the rest 503 `busy` at once, a normal
client's probes included, so its file descriptors stay bounded; its soft open-file limit of 1024 is raised first.
The same drill at the default cap: `python -m tests.drills --spawn --scenario connections --nofile 1024:<hard>`
(docs/reliability.md)."""

from __future__ import annotations

import resource
import shutil

import pytest

from jointlimits.service import cli
from tests import drills as lt

pytestmark = pytest.mark.slow  # its own `jointlimits serve` (~3 s)

CAP, FLOOD = 64, 300


def test_a_flood_meets_the_cap_and_the_worker_keeps_its_descriptors():
    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    if not shutil.which("prlimit") or hard <= 1024:
        pytest.skip("needs prlimit and a hard fd limit above 1024")
    r = lt.scenario_connections(FLOOD, ["--max-connections", str(CAP)], nofile=f"1024:{hard}")
    assert r["opened"] == FLOOD
    assert r["flood_answered"] == {"held": CAP, "503": FLOOD - CAP}  # none reset, none left unanswered
    assert r["worker_fds"] <= CAP + cli.FD_RESERVE
    assert r["probes"] == {"/healthz": "503", "/readyz": "503"}  # not exempt (docs/deployment.md says why)
    assert r["closed_counted"]["connections_full"] == FLOOD - CAP + 2
    assert r["healthz_after"] == 200  # the flood gone, its places are free
