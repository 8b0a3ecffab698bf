"""Shared fixtures: the golden cases and normwise error measures."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

GOLDEN = json.loads((Path(__file__).parent / "golden_cases.json").read_text())["cases"]


ANSWER_FIELDS = ("index", "x", "coordinate", "energy", "gradient", "hessian")


def same_joints(got, want) -> None:
    """Bitwise the same joints of two SDK evaluations: batches, constitutions, and each field's shape, dtype and
    bits (absent on both sides or on neither)."""
    assert len(got.batches) == len(want.batches)
    for g, w in zip(got.batches, want.batches):
        assert g.constitution_uid == w.constitution_uid
        for f in ANSWER_FIELDS:
            a, b = getattr(g, f), getattr(w, f)
            assert (a is None) == (b is None), f
            if a is not None:
                assert a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes(), f


def same_evaluation(got, want) -> None:
    """Bitwise the same evaluation: its joints and its total energy."""
    assert got.total_energy == want.total_energy
    same_joints(got, want)


def relerr(got, want, floor: float = 0.0) -> float:
    """Normwise relative error `max|got - want| / max(max|want|, floor)` (0 when both are zero)."""
    got, want = np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape, (got.shape, want.shape)
    scale = max(float(np.max(np.abs(want), initial=0.0)), floor)
    diff = float(np.max(np.abs(got - want), initial=0.0))
    return diff / scale if scale > 0 else diff


# The docs' example (body 1 turned 0.7 rad about z, upper 0.5, strength 100) printed as this machine computes it.
# x is one arctan2, and another CPU's kernel may round it differently: AVX-512's SVML (numpy's float64 arctan2 there)
# is within 1 ulp, not correctly rounded, and the exact angle lies 0.25 ulp from 0.7 (tests/perturb.py). Allowing
# 4 ulps, |dx| <= 4.4e-16: E = 100 (x - 0.5)^3 moves by 12 |dx| (6.7e-15 of 0.8), E' = 300 (x - 0.5)^2 by
# 120 |dx| (4.4e-15 of 12), and the gradient's entries, E' times O(1) frame entries, as E' does. Under
# `--perturb-ulps 1` these examples read 0.7000000000000001 and 0.8000000000000009 (1.8e-15 of 0.8).
EXAMPLE_RTOL = 1e-14
_FLOAT = re.compile(r"(-?(?:\d+\.\d*|\.\d+)(?:[eE][-+]?\d+)?|-?\d+[eE][-+]?\d+)")


def same_numbers(got: str, want: str, rtol: float = EXAMPLE_RTOL) -> bool:
    """`got` reads as `want` up to last bits: the same text around the floats (integers included, exactly),
    and the floats within `rtol` of the largest of `want`'s (normwise, as `relerr`: a zero here may be a rounding
    of the larger entries' size elsewhere, as when a rotation's sin and cos come from another kernel)."""
    g, w = _FLOAT.split(got), _FLOAT.split(want)
    if len(g) != len(w) or g[::2] != w[::2]:
        return False
    a, b = np.array(g[1::2], dtype=float), np.array(w[1::2], dtype=float)
    return bool((np.abs(a - b) <= rtol * np.max(np.abs(b), initial=0.0)).all())


@pytest.fixture(params=GOLDEN, ids=[c["name"] for c in GOLDEN])
def golden_case(request):
    return request.param


# ---------------------------------------------------------------- the fast subset
# `pytest -m "not slow"` leaves out the tests marked `slow` where they are: `pytestmark = pytest.mark.slow` at the top
# of a wholly slow module, `@pytest.mark.slow` on a test, each with its reason (live servers in subprocesses, the load
# and fault drills, the Dockerfile's replay, the bench, fuzzers, timers that wait on purpose, property tests over random
# scenes). tests/test_slow_marks.py checks that the tests known slow stay marked and that a test starting a process is.


# ---------------------------------------------------------------- one CA bundle per test run
# httpx builds an SSL context for every client it makes (the SDK's `Client`, each `httpx.get`/`httpx.post`), loading
# the system's CA bundle: `load_verify_locations` takes 40 ms on a quiet core and 170-290 ms on the loaded 2-core
# machine, and the suite makes thousands of clients, all to plain-HTTP servers on loopback that never use TLS. The test
# process builds that default context once and gives the same object to every client that asks for it (verify=True,
# no client certificate); any other request builds its own as before. What the clients send and receive is unchanged.
@pytest.fixture(scope="session", autouse=True)
def _one_default_ssl_context():
    try:
        from httpx._transports import default as transports  # where httpx's transports call it
    except ImportError:  # another httpx layout: every client builds its own context, as without this fixture
        yield
        return
    build = transports.create_ssl_context
    built: dict[tuple, object] = {}

    def create_ssl_context(verify=True, cert=None, trust_env=True):  # noqa: ANN001, ANN202 (httpx's signature)
        if verify is not True or cert is not None:
            return build(verify=verify, cert=cert, trust_env=trust_env)
        key = (trust_env, os.environ.get("SSL_CERT_FILE"), os.environ.get("SSL_CERT_DIR"))
        if key not in built:
            built[key] = build(verify=verify, cert=cert, trust_env=trust_env)
        return built[key]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(transports, "create_ssl_context", create_ssl_context)
        yield


# ---------------------------------------------------------------- CI's two runs
# CI runs `pytest -n 2 -m "not serial"` (pytest-xdist: 2 worker processes, each test module wholly on one worker,
# `--dist loadfile` in pyproject.toml, so that a module's fixtures (a built venv, a live server) are made once), then
# `pytest -m serial` alone: the tests that measure time or wait on wall-clock bounds (the `serial` marker). On the
# workers the longest modules go first, so that neither worker is left with one of them at the end while the other
# idles; a run without xdist keeps the files' order.
LONGEST_FIRST = ("tests/ops/test_docker.py", "tests/ops/test_newcomer_bench.py", "tests/ops/test_wheel.py")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not hasattr(config, "workerinput"):  # not an xdist worker: the files' order, nothing to check
        return
    # xdist schedules by node id: two items with one id (schemathesis' per-operation items, under pytest 9) would run
    # once. Such a test is marked `serial` (run without xdist); any other is refused here rather than lost.
    ids = [item.nodeid for item in items if item.get_closest_marker("serial") is None]
    if len(set(ids)) != len(ids):
        raise pytest.UsageError("two tests share a node id: pytest-xdist would run only one of them (mark it serial)")
    rank = {path: k for k, path in enumerate(LONGEST_FIRST)}  # the controller schedules in this order
    items.sort(key=lambda item: rank.get(item.nodeid.split("::", 1)[0], len(rank)))


# ---------------------------------------------------------------- another machine's math kernels
# `--perturb-ulps N` (off by default) runs the tests with NumPy's transcendental ufuncs moved by up to N ulps and its
# BLAS/LAPACK calls by another summation order's error (tests/perturb.py says what and why), as on a CPU with AVX-512
# or another OpenBLAS kernel. Installed at configure time, before any test module is imported, in every xdist worker,
# and (tests/perturb_site/sitecustomize.py) in every Python process the tests start;
# tests/core/test_perturb.py::test_the_perturbation_reaches_the_core fails if it does not take effect.
def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--perturb-ulps", type=int, default=0, metavar="N",
                     help="simulate another CPU's math kernels: NumPy's transcendentals off by up to N ulps (tests/perturb.py)")
    parser.addoption("--perturb-seed", type=int, default=0, help="the seed of --perturb-ulps' moves")


def pytest_configure(config: pytest.Config) -> None:
    n = config.getoption("--perturb-ulps")
    if n > 0:
        from tests.perturb import perturbed

        seed = config.getoption("--perturb-seed")
        context = perturbed(n, seed)
        context.__enter__()
        config.add_cleanup(lambda: context.__exit__(None, None, None))
        site = str(Path(__file__).parent / "perturb_site")
        os.environ.update(JL_PERTURB_ULPS=str(n), JL_PERTURB_SEED=str(seed),
                          PYTHONPATH=os.pathsep.join(filter(None, (site, os.environ.get("PYTHONPATH")))))
