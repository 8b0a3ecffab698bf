"""Shared fixtures: the golden cases and normwise error measures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

GOLDEN = json.loads((Path(__file__).parent / "golden_cases.json").read_text())["cases"]


def relerr(got, want, floor: float = 0.0) -> float:
    """Normwise relative error `max|got - want| / max(max|want|, floor)` (0 when both are zero)."""
    got, want = np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape, (got.shape, want.shape)
    scale = max(float(np.max(np.abs(want), initial=0.0)), floor)
    diff = float(np.max(np.abs(got - want), initial=0.0))
    return diff / scale if scale > 0 else diff


@pytest.fixture(params=GOLDEN, ids=[c["name"] for c in GOLDEN])
def golden_case(request):
    return request.param


# ---------------------------------------------------------------- the fast subset
# `pytest -m "not slow"` leaves these out: live servers in subprocesses, the load and fault drills, the Dockerfile's
# replay, the bench, the fuzzers, timers that wait on purpose and property tests over random scenes. Chosen by
# `pytest --durations=0` on the project's 2-core machine: the whole suite 9 min 10 s in a clean clone (2,317 tests,
# 2026-11-26), the rest (`-m "not slow"`, 1,349 tests) 71 s on the idle machine, no test of it over 2 s but the
# docs site's build (3.4 s). A module name marks all its tests; "module::test" one test (every parametrization of it).
# tests/test_slow_marks.py checks that every entry names a test that exists.
SLOW = (
    # The load and fault drills, the Dockerfile's replay, the bench, fuzzers:
    "test_ops_load.py",  # the drills against `jointlimits serve --workers 2` (~95 s)
    "test_newcomer_bench.py::test_readme_quick_bench_runs_on_a_fresh_venv_with_the_bench_extra",  # a fresh venv with JAX, then the quick bench (~90 s)
    "test_docker.py",  # replays the Dockerfile into a fresh venv and serves from it (~20 s)
    "test_write_drills.py",  # three drills, each its own `jointlimits serve` on loopback (~17 s)
    "test_write_timeouts.py",  # the write-side bounds one by one on in-process servers, each waits out a timeout (~15 s)
    "test_wheel.py",  # builds the wheel (pip, an isolated build environment) and runs the README example from it (~5 s)
    "test_fuzz_http.py",  # schemathesis and hypothesis over HTTP (~11 s)
    "test_sessions_fuzz.py",  # fuzzes the session protocol (~3 s)
    "test_bench.py",  # the bench end to end at tiny sizes, and bench.ab against a revision (~7 s)
    "test_bench_sessions.py",  # the sessions bench against a uvicorn subprocess (~3 s)
    # Live servers (subprocesses, or many uvicorn threads) and timers that wait on purpose:
    "test_budget.py",  # concurrent requests at the limits (~10 s)
    "test_worker_alive.py",  # the largest admitted bodies to a 2-worker server (~10 s)
    "test_read_timeouts.py",  # waits out header and body deadlines (~7 s)
    "test_connection_age.py::test_clients_reconnect_without_an_error",  # waits out four connection ages (~2.3 s)
    "test_sessions_live.py",  # sessions over real WebSockets, the idle timer's waits (~22 s)
    "test_client_unreachable.py",  # connect timeouts, refused ports, unrelated servers (~4 s)
    "test_screw.py",  # a screw driven three turns in-process and over HTTP (~3 s)
    "test_nonfinite_paths.py",  # each fault through JSON, msgpack, local and sessions on a live server (~3 s)
    "test_readme_errors.py",  # the Errors table's 30 answers from live servers (~2 s)
    "test_hostile_wire.py",  # floods of hostile bodies (millions of items) through both decoders (~2.5 s)
    "test_heap.py",  # counts page faults of repeated evaluations: a performance measurement
    "test_admission.py::test_sdk_splits_by_the_answer_bound_and_json_values",  # split requests to a live server
    "test_admission.py::test_issue_9s_hessian_requests_are_refused_at_the_defaults",  # issue 9's 1e6-joint bodies
    "test_admission.py::test_issue_9s_ten_thousand_batches_are_refused_at_the_defaults",
    "test_admission.py::test_past_the_deadline_is_503_with_retry_after",
    "test_admission.py::test_a_real_evaluation_past_a_short_deadline_is_stopped",
    "test_cli.py::test_serve_passes_limits_logs_json_and_stops_gracefully",  # `jointlimits serve` subprocesses
    "test_cli.py::test_token_file_and_cors",
    "test_cli.py::test_an_app_that_does_not_import_fails_fast",
    "test_lb_drill.py::test_the_load_balancer_drill_fails_no_request",  # HAProxy, three replicas, restarts (~40 s)
    "test_lb_drill.py::test_the_docs_nginx_configuration_passes_requests_and_sessions",  # nginx in front (~1 s)
    "test_lb_drill.py::test_keep_alive_clients_spread_again_onto_a_restarted_replica",  # HAProxy in TCP mode (~8 s)
    "test_drain.py::test_sigterm_drains_then_stops",  # `jointlimits serve` with 1 and 2 workers, a 1.5 s drain (~4.6 s)
    "test_drain.py::test_a_second_sigterm_changes_nothing_and_sigint_stops_at_once",  # (~2 s)
    "test_drain.py::test_a_draining_worker_serves_its_sessions_refuses_new_ones_then_closes_them_with_1012",  # (~3 s)
    # Property tests over random scenes and the 50-digit reference (the golden cases stay in the fast subset):
    "test_reference.py",  # mpmath over random scenes (~10 s)
    "test_properties.py",  # derivatives by finite differences over random scenes (~8 s)
    "test_degenerate_scales.py",  # 1e-300..1e300 scales (~4 s)
    "test_v12_properties.py",  # v1.2 over random scenes (~3 s)
    "test_hard_cases.py",  # the hard cases against mpmath (~2 s)
    "test_revolute_psd_scales.py::test_psd_hessian_at_the_issues_scales",  # a fresh 50-digit reference per scale (~6 s)
    "test_prismatic_scales.py",  # 50- and 700-digit references at extreme scales
    "test_session_bounds.py::test_a_message_over_the_limit_is_read_as_1009_with_its_reason_every_time",  # ~330 MiB over loopback a try (~8 s)
)


def pytest_collection_modifyitems(config, items):
    for item in items:
        module = item.nodeid.split("::", 1)[0].rsplit("/", 1)[-1]
        test = item.nodeid.split("::", 1)[1].split("[", 1)[0] if "::" in item.nodeid else ""
        if module in SLOW or f"{module}::{test}" in SLOW:
            item.add_marker(pytest.mark.slow)
