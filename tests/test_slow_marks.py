"""The fast subset (`pytest -m "not slow"`) leaves out what is slow, and a move or a rename cannot quietly make a slow
test fast. Slow is marked in each module: `pytestmark = pytest.mark.slow` at the top of a wholly slow module, or
`@pytest.mark.slow` on a test, each with its reason; this file reads the marks from the source (no import, no run)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

HERE = Path(__file__).resolve().parent

# Every test known slow when the marks moved into the modules (issue 28; before, one list in conftest.py). Chosen by
# `pytest --durations=0` on the project's 2-core machine: live servers in subprocesses, the load and fault drills, the
# Dockerfile's replay, the bench, fuzzers, timers that wait on purpose, property tests over random scenes.
KNOWN_SLOW = (
    "ops/test_ops_load.py",
    "ops/test_newcomer_bench.py::test_readme_quick_bench_runs_on_a_fresh_venv_with_the_bench_extra",
    "ops/test_docker.py",
    "ops/test_write_drills.py",
    "http/test_write_timeouts.py",
    "ops/test_wheel.py",
    "http/test_fuzz_http.py",
    "http/test_sessions_fuzz.py",
    "ops/test_bench.py",
    "ops/test_bench_sessions.py",
    "http/test_budget.py",
    "ops/test_worker_alive.py",
    "http/test_read_timeouts.py",
    "http/test_connection_age.py::test_clients_reconnect_without_an_error",
    "sdk/test_sessions_live.py",
    "sdk/test_client_unreachable.py",
    "sdk/test_screw.py",
    "http/test_nonfinite_paths.py",
    "docs/test_readme_errors.py",
    "http/test_hostile_wire.py",
    "core/test_heap.py",
    "http/test_admission.py::test_sdk_splits_by_the_answer_bound_and_json_values",
    "http/test_admission.py::test_issue_9s_hessian_requests_are_refused_at_the_defaults",
    "http/test_admission.py::test_issue_9s_ten_thousand_batches_are_refused_at_the_defaults",
    "http/test_admission.py::test_past_the_deadline_is_503_with_retry_after",
    "http/test_admission.py::test_a_real_evaluation_past_a_short_deadline_is_stopped",
    "http/test_cli.py::test_serve_passes_limits_logs_json_and_stops_gracefully",
    "http/test_cli.py::test_token_file_and_cors",
    "http/test_cli.py::test_an_app_that_does_not_import_fails_fast",
    "ops/test_lb_drill.py::test_the_load_balancer_drill_fails_no_request",
    "ops/test_lb_drill.py::test_the_docs_nginx_configuration_passes_requests_and_sessions",
    "ops/test_lb_drill.py::test_keep_alive_clients_spread_again_onto_a_restarted_replica",
    "http/test_drain.py::test_sigterm_drains_then_stops",
    "http/test_drain.py::test_a_second_sigterm_changes_nothing_and_sigint_stops_at_once",
    "http/test_drain.py::test_a_draining_worker_serves_its_sessions_refuses_new_ones_then_closes_them_with_1012",
    "core/test_reference.py",
    "core/test_properties.py",
    "core/test_degenerate_scales.py",
    "core/test_v12_properties.py",
    "core/test_hard_cases.py",
    "core/test_revolute_psd_scales.py::test_psd_hessian_at_the_issues_scales",
    "core/test_prismatic_scales.py",
    "http/test_session_bounds.py::test_a_message_over_the_limit_is_read_as_1009_with_its_reason_every_time",
)

# Every test that measures time, latency or throughput or waits on wall-clock bounds: CI runs the others on 2 worker
# processes (`pytest -n 2 -m "not serial"`), then these alone (`pytest -m serial`), so that no other test shares the
# 2 cores with them (the `serial` marker in pyproject.toml). Besides them, schemathesis' test: its items (one per API
# operation) share one node id, and xdist, which schedules by node id, would run one of them (tests/conftest.py).
KNOWN_SERIAL = (
    "ops/test_ops_load.py",
    "ops/test_lb_drill.py",
    "ops/test_write_drills.py",
    "ops/test_worker_alive.py",
    "ops/test_bench.py",
    "ops/test_bench_sessions.py",
    "ops/test_robot_scale.py",
    "http/test_fuzz_http.py::test_schemathesis_openapi",
    "http/test_read_timeouts.py",
    "http/test_write_timeouts.py",
    "http/test_drain.py",
    "http/test_connection_age.py",
    "http/test_budget.py",
    "http/test_refused_upgrade_log.py",
    "http/test_admission.py::test_past_the_deadline_is_503_with_retry_after",
    "http/test_admission.py::test_a_real_evaluation_past_a_short_deadline_is_stopped",
    "http/test_session_bounds.py::test_a_message_over_the_limit_is_read_as_1009_with_its_reason_every_time",
    "http/test_session_bounds.py::test_a_reply_due_when_the_limit_closes_the_session_is_dropped_not_an_error",
    "sdk/test_sessions_live.py",
    "sdk/test_client_unreachable.py",
    "sdk/test_client_faults_log.py",
    "core/test_heap.py",
)


def _is_mark(node: ast.expr, mark: str = "slow") -> bool:
    """`pytest.mark.<mark>`, or a list/tuple holding it (`pytestmark = [..., pytest.mark.slow]`)."""
    if isinstance(node, (ast.List, ast.Tuple)):
        return any(_is_mark(e, mark) for e in node.elts)
    return ast.unparse(node) == f"pytest.mark.{mark}"


def _module_slow(tree: ast.Module, mark: str = "slow") -> bool:
    return any(isinstance(n, ast.Assign) and any(ast.unparse(t) == "pytestmark" for t in n.targets)
               and _is_mark(n.value, mark) for n in tree.body)


def _functions(tree: ast.Module) -> dict[str, ast.FunctionDef | ast.AsyncFunctionDef]:
    return {n.name: n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}


def _marked(fn: ast.FunctionDef | ast.AsyncFunctionDef, mark: str = "slow") -> bool:
    return any(_is_mark(d, mark) for d in fn.decorator_list)


def _starters(tree: ast.Module) -> set[str]:
    """How the module spells the calls that start a process: `subprocess.Popen`, and `Server` when it is tests.drills'
    (imported by name, or through the module: `drills.Server`, `lt.Server`). Another `Server` (test_client_busy's
    mock transport) starts nothing."""
    names = {"subprocess.Popen"}
    for n in ast.walk(tree):
        if isinstance(n, ast.ImportFrom) and n.module == "tests.drills":
            names |= {a.asname or a.name for a in n.names if a.name == "Server"}
        elif isinstance(n, ast.ImportFrom) and n.module == "tests":
            names |= {f"{a.asname or a.name}.Server" for a in n.names if a.name == "drills"}
        elif isinstance(n, ast.ImportFrom) and n.module == "subprocess":
            names |= {a.asname or a.name for a in n.names if a.name == "Popen"}
    return names


def _starts(fn: ast.AST, starters: set[str]) -> bool:
    return any(isinstance(n, ast.Call) and ast.unparse(n.func) in starters for n in ast.walk(fn))


def _modules() -> list[Path]:
    return sorted(HERE.glob("*/test_*.py"))


def _unmarked(known: tuple[str, ...], mark: str) -> list[str]:
    """The entries of `known` not marked `mark`: a module marked whole, a test marked (or its module)."""
    wrong = []
    for entry in known:
        module, _, test = entry.partition("::")
        path = HERE / module
        if not path.exists():
            wrong.append(f"{entry}: no such module")
            continue
        tree = ast.parse(path.read_text())
        if _module_slow(tree, mark):
            continue
        fn = _functions(tree).get(test) if test else None
        if fn is None or not _marked(fn, mark):
            wrong.append(f"{entry}: not marked {mark}")
    return wrong


def test_every_known_slow_test_is_still_marked():
    """A module of the list is marked whole; a test of the list is marked (or its module is). Renamed, moved or
    unmarked, it fails here: the list is this test's data, the marks are in the modules."""
    assert _unmarked(KNOWN_SLOW, "slow") == []


def test_every_known_serial_test_is_still_marked():
    """The drills, timeouts and benches stay out of CI's parallel run, whatever moves or is renamed."""
    assert _unmarked(KNOWN_SERIAL, "serial") == []


def test_ci_runs_the_parallel_part_then_the_serial_part():
    """The README's (and so .ci/run's) test command runs every test: those not `serial` on 2 workers, then the
    `serial` ones alone, in one process without xdist's `-n`."""
    readme = (HERE.parent / "README.md").read_text()
    command = readme.split("```bash\n", 1)[1].split("```", 1)[0].splitlines()[1]
    runs = [part.strip() for part in command.split("&&") if "-m pytest" in part]
    assert runs == ['.venv/bin/python -m pytest -n 2 -m "not serial"', ".venv/bin/python -m pytest -m serial"], runs


def test_every_test_that_starts_a_process_is_slow():
    """A test that starts `jointlimits serve` (tests.drills' `Server`) or any process with `subprocess.Popen`, in its
    own body or through a fixture of its module, is left out of the fast subset."""
    unmarked = []
    for path in _modules():
        tree = ast.parse(path.read_text())
        if _module_slow(tree):
            continue
        functions = _functions(tree)
        starters = _starters(tree)
        starting = {name for name, fn in functions.items() if _starts(fn, starters)}
        for name, fn in functions.items():
            if not name.startswith("test_") or _marked(fn):
                continue
            if name in starting or starting & {a.arg for a in fn.args.args}:
                unmarked.append(f"{path.relative_to(HERE)}::{name}")
    assert unmarked == []


def test_the_rule_sees_a_process_started_by_a_fixture():
    """The check above is not vacuous: a fixture that starts a server makes its unmarked user a finding."""
    source = "from tests import drills\n\n@pytest.fixture\ndef server():\n    return drills.Server()\n\ndef test_x(server):\n    pass\n"
    tree = ast.parse(source)
    functions = _functions(tree)
    starting = {name for name, fn in functions.items() if _starts(fn, _starters(tree))}
    assert starting == {"server"} and not _marked(functions["test_x"]) and not _module_slow(tree)
    assert not _starts(ast.parse("Server()"), _starters(ast.parse("from tests.sdk.test_client_busy import Server")))


def test_every_test_module_sits_in_a_layer_folder():
    """tests/ holds the shared helpers and this file; the tests are in core/, http/, sdk/, ops/ and docs/."""
    assert sorted(p.name for p in HERE.glob("test_*.py")) == ["test_slow_marks.py"]
    assert sorted({p.parent.name for p in _modules()}) == ["core", "docs", "http", "ops", "sdk"]
    assert all((p.parent / "__init__.py").exists() for p in _modules())


def test_the_markers_are_registered():
    text = (HERE.parent / "pyproject.toml").read_text()
    assert re.search(r'markers = \[\s*"slow: [^\n]*\n\s*"serial: ', text)
