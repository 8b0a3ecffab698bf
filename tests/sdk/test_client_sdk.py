"""The SDK: scene builder, typed results, splitting with progress, error locs after a split, retries."""

from __future__ import annotations

import asyncio
import inspect
from dataclasses import replace

import httpx
import numpy as np
import pytest

from jointlimits.client import (
    AsyncClient,
    Client,
    InvalidInput,
    JointBatch,
    LocalClient,
    Scene,
    ServiceError,
    TooLarge,
    Unreachable,
    dofs,
    request_from_arrays,
)
from tests.conftest import EXAMPLE_RTOL, relerr
from tests.http.test_contract_live import live  # noqa: F401 (fixture)
from tests.http.test_errors_http import rot_z

# README example: body 1 turned by 0.7 rad about +z, 0.2 rad past the upper limit.
README_GRADIENT = [0.0, 0.0, 0.0, 0.0, 5.999999999999997, 0.0, -5.999999999999997, 0.0, 0.0, 0.0, 0.0, 0.0,
                   0.0, 0.0, 0.0, -3.8653061234261443, -4.589053123706929, 0.0, 4.589053123706929,
                   -3.8653061234261443, 0.0, 0.0, 0.0, 0.0]  # fmt: skip


def readme_scene(pose_kind: str = "matrix") -> Scene:
    turned = {"matrix": np.block([[rot_z(0.7), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]),
              "pair": (np.zeros(3), rot_z(0.7)),
              "dofs": np.concatenate([np.zeros(3), rot_z(0.7).reshape(9)])}[pose_kind]  # fmt: skip
    scene = Scene()
    a = scene.add_body(np.eye(4))
    b = scene.add_body(turned, ref=np.eye(4))
    scene.add_revolute_limit(a, b, [0, 0, 0], [0, 0, 1], lower=-0.5, upper=0.5, strength=100.0)
    return scene


@pytest.mark.parametrize("pose_kind", ["matrix", "pair", "dofs"])
def test_scene_builder_reproduces_the_readme_example(live, pose_kind):
    with Client(live) as client:
        ev = client.evaluate(readme_scene(pose_kind).request(outputs=["energy", "gradient"]))
    r = ev.batch(670)
    # This machine's last bits; another CPU's arctan2 may move them (EXAMPLE_RTOL argues the bound).
    assert r.x[0] == pytest.approx(0.7, rel=EXAMPLE_RTOL)
    assert ev.total_energy == r.energy[0] == pytest.approx(0.7999999999999995, rel=EXAMPLE_RTOL)
    assert relerr(r.gradient[0], README_GRADIENT) <= EXAMPLE_RTOL  # normwise: a zero here may be 3e-16 there
    assert r.hessian is None
    with pytest.raises(KeyError):
        ev.batch(669)


def test_scene_defaults_and_pose_forms():
    np.testing.assert_array_equal(dofs(np.eye(4)), [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1])
    with pytest.raises(ValueError):
        dofs(np.zeros(5))
    scene = Scene()
    scene.add_body(np.eye(4))
    scene.add_body(np.eye(4), ref=(np.ones(3), np.eye(3)))
    j = scene.add_prismatic_limit(0, 1, [0, 0, 0], [1, 0, 0], lower=-1, upper=1)
    req = scene.request(hessian_mode="psd", active_only=True)
    assert j == 0 and req.batches[0].base_uid == 20 and req.batches[0].strength.tolist() == [1.0]  # spec default
    np.testing.assert_array_equal(req.q_prev, req.q_ref)  # prev defaults to ref
    assert req.hessian_mode == "psd" and req.active_only


def chain(n_bodies: int, n_joints: int, seed: int = 0):
    """Random-ish chain: revolute limits (batch 0) and prismatic limits (batch 1), most of them active."""
    rng = np.random.default_rng(seed)
    q_ref = np.zeros((n_bodies, 12))
    q_ref[:, 3:] = np.eye(3).reshape(9)
    q_ref[:, :3] = rng.normal(size=(n_bodies, 3))
    q = q_ref.copy()
    angles = rng.uniform(-1, 1, n_bodies)
    q[:, 3:] = np.stack([rot_z(a).reshape(9) for a in angles])
    q[:, :3] += rng.normal(scale=0.3, size=(n_bodies, 3))
    i = rng.integers(0, n_bodies, n_joints)
    j = (i + 1 + rng.integers(0, n_bodies - 1, n_joints)) % n_bodies
    ids = np.stack([i, j], axis=1)
    axis = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    edges = np.tile(axis, (n_joints, 1, 1)) + rng.normal(scale=0.1, size=(n_joints, 1, 3))
    half = n_joints // 2
    return request_from_arrays(
        q,
        [
            JointBatch.of(670, ids[:half], edges[:half], -0.2, 0.2, rng.uniform(1, 10, half)),
            JointBatch.of(669, ids[half:], edges[half:], -0.1, 0.1, 5.0),
        ],
        q_ref=q_ref,
    )


def _same_rows(a, b):
    assert a.total_energy == pytest.approx(b.total_energy, rel=1e-12)
    for ra, rb in zip(a.batches, b.batches):
        for f in ("index", "x", "energy", "gradient", "hessian"):
            np.testing.assert_array_equal(getattr(ra, f), getattr(rb, f))


def test_large_batch_is_split_under_the_server_limit_with_progress(live):
    request = chain(300, 1000)
    seen = []
    with Client(live) as client:  # the live server accepts 400 joints per request
        ev = client.evaluate(request, progress=lambda done, total: seen.append((done, total)))
    assert [d for d, _ in seen] == [400, 800, 1000] and {t for _, t in seen} == {1000}
    local = LocalClient().evaluate(request)
    _same_rows(ev, local)
    assert sum(len(b.index) for b in ev.batches) == 1000
    _same_rows(local, LocalClient(threads=2).evaluate(request))  # the core's threads change no bit


def test_split_with_active_only_and_a_small_user_cap(live):
    request = replace(chain(50, 300, seed=3), active_only=True, outputs=("energy", "gradient"))
    with Client(live, binary=False, max_joints_per_request=70) as client:
        ev = client.evaluate(request)
    _same_rows(ev, LocalClient().evaluate(request))
    assert ev.batches[0].hessian is None and all(np.all(b.energy > 0) for b in ev.batches)


def test_async_split_runs_parts_concurrently_and_merges_in_order(live):
    request = chain(120, 900, seed=1)

    async def run():
        async with AsyncClient(live, concurrency=3, max_joints_per_request=100) as client:
            return await client.evaluate(request)

    _same_rows(asyncio.run(run()), LocalClient().evaluate(request))


def test_stderr_progress_bar(live, capsys):
    with Client(live, progress=True, max_joints_per_request=100) as client:
        client.evaluate(chain(20, 250))
    err = capsys.readouterr().err
    assert "250/250 joints" in err and "[" in err


@pytest.mark.parametrize("mode", ["sync", "async", "local"])
def test_errors_after_a_split_name_the_original_batch_joint_and_body(live, mode):
    request = chain(300, 1000, seed=2)
    lower = request.batches[1].lower.copy()
    lower[450] = 99.0  # batch 1 holds joints 500..999: its row 450 goes out in the third part, as its row 150
    bad_joint = replace(request, batches=[request.batches[0], replace(request.batches[1], lower=lower)])
    q = request.q.copy()
    body = int(request.batches[1].body_ids[470, 1])
    q[body, 4] = np.nan  # renumbered in every part that uses it
    bad_body = replace(request, q=q)

    def run(req):
        if mode == "local":
            return LocalClient().evaluate(req)
        if mode == "sync":
            with Client(live) as client:
                return client.evaluate(req)

        async def go():
            async with AsyncClient(live) as client:
                return await client.evaluate(req)

        return asyncio.run(go())

    with pytest.raises(InvalidInput) as err:
        run(bad_joint)
    assert [f.loc for f in err.value.faults] == [("body", "batches", 1, "lower", 450)]
    with pytest.raises(InvalidInput) as err:
        run(bad_body)
    assert [f.loc for f in err.value.faults] == [("body", "bodies", "q", body, 4)]  # to the element, as JSON names it


def test_too_large_is_raised_when_splitting_is_defeated(live):
    request = chain(10, 401)
    one = request_from_arrays(request.q, [JointBatch.of(669, np.tile([[0, 1]], (401, 1)), np.tile([[0, 0, 0], [0, 0, 1.0]], (401, 1, 1)), -1, 1)])
    with Client(live, max_joints_per_request=10**6) as client:
        client._limits = None  # never asked: pretend the server's limits are unknown
        client.constitutions = lambda: None  # type: ignore[method-assign]
        with pytest.raises(TooLarge) as err:
            client.evaluate(one)
    assert err.value.status == 413 and err.value.loc == ("body", "batches")


def _flaky(failures: int, exc: type[Exception], calls: list):
    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request.url.path)
        if len(calls) <= failures:
            raise exc("simulated", request=request)
        if request.url.path == "/v1/constitutions":
            return httpx.Response(200, json={"constitutions": [], "limits": {"max_body_bytes": 10**9, "max_joints": 10**6}})
        return httpx.Response(500, json={"detail": "boom"})

    return handler


def test_retries_connection_errors_with_backoff_then_reports_server_errors():
    calls: list = []
    client = Client("http://test", retries=3, backoff=0.001, http_transport=httpx.MockTransport(_flaky(2, httpx.ConnectError, calls)))
    with pytest.raises(ServiceError) as err:
        client.evaluate(readme_scene().request())
    assert calls == ["/v1/constitutions"] * 3 + ["/v1/evaluate"]  # 2 retried failures, then no retry of the 500
    assert err.value.status == 500 and err.value.msg == "boom"


def test_gives_up_after_the_retries():
    calls: list = []
    client = Client("http://test", retries=2, backoff=0.0, http_transport=httpx.MockTransport(_flaky(10, httpx.ConnectError, calls)))
    with pytest.raises(Unreachable) as err:
        client.constitutions()
    assert len(calls) == 3 and err.value.attempts == 3 and isinstance(err.value.__cause__, httpx.ConnectError)


def test_timeouts_are_not_retried():
    calls: list = []
    client = Client("http://test", retries=3, backoff=0.0, http_transport=httpx.MockTransport(_flaky(1, httpx.ReadTimeout, calls)))
    with pytest.raises(httpx.ReadTimeout):
        client.constitutions()
    assert len(calls) == 1


def test_async_retries_connection_errors():
    calls: list = []

    async def run():
        transport = httpx.MockTransport(_flaky(2, httpx.ConnectError, calls))
        async with AsyncClient("http://test", retries=2, backoff=0.001, http_transport=transport) as client:
            return await client.constitutions()

    assert asyncio.run(run()).limits.max_joints == 10**6 and len(calls) == 3


def test_connection_refused_on_a_real_socket_is_retried_then_raised():
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(Unreachable):
        Client(f"http://127.0.0.1:{port}", retries=1, backoff=0.01, timeout=2.0).constitutions()


def test_async_client_takes_the_sync_clients_arguments_and_defaults():
    def spelled(cls: type) -> dict:
        return {p.name: (p.kind, p.default) for p in inspect.signature(cls).parameters.values()}

    sync, aio = spelled(Client), spelled(AsyncClient)
    assert aio.pop("concurrency") == (inspect.Parameter.KEYWORD_ONLY, 4)
    assert list(aio.items()) == list(sync.items())


def test_local_mode_has_the_same_api_and_numbers(live):
    request = readme_scene().request()
    with LocalClient(binary=True, timeout=5) as local, Client(live) as remote:
        _same_rows(local.evaluate(request), remote.evaluate(request))
        assert local.constitutions().constitutions == remote.constitutions().constitutions


def test_split_carries_the_v11_state_per_joint(live):
    """offset and prev_coordinate are sliced with their joints; coordinate is merged with x."""
    request = chain(300, 1000, seed=5)
    rng = np.random.default_rng(5)
    rev, pri = request.batches
    request.batches = [
        replace(rev, offset=rng.uniform(-1, 1, len(rev)), prev_coordinate=rng.uniform(-20, 20, len(rev))),
        replace(pri, offset=rng.uniform(-1, 1, len(pri))),
    ]
    with Client(live) as client:  # 400 joints per request: three parts
        ev = client.evaluate(request)
    local = LocalClient().evaluate(request)
    _same_rows(ev, local)
    for r, l in zip(ev.batches, local.batches):
        np.testing.assert_array_equal(r.coordinate, l.coordinate)
    # coordinate = x + offset, formed as prev_coordinate + DeltaTheta(q, q_prev) (not through x = prev - offset + ...):
    # equal to the rounding of the three terms
    off, x = request.batches[0].offset, local.batches[0].x
    assert (np.abs(local.batches[0].coordinate - (x + off)) <= 4 * np.spacing(np.abs(x) + np.abs(off))).all()


def test_clients_share_one_tls_context_that_still_verifies(monkeypatch):
    """httpx builds an SSL context per client (40-170 ms loading the CA bundle); the SDK's clients share one per
    bundle, which still verifies certificates and host names, and a different SSL_CERT_FILE gets its own."""
    import ssl

    import certifi

    from httpx import _config
    from httpx._transports import default as transports

    from jointlimits.client import AsyncClient, transport

    monkeypatch.setattr(transports, "create_ssl_context", _config.create_ssl_context)  # not the tests' shared one
    transport._ssl_context.cache_clear()

    def context(c) -> ssl.SSLContext:
        return c._http._transport._pool._ssl_context

    a, b, s = Client("http://127.0.0.1:1"), Client("https://example.invalid"), AsyncClient("https://example.invalid")
    assert context(a) is context(b) is context(s)
    assert context(a).verify_mode == ssl.CERT_REQUIRED and context(a).check_hostname
    monkeypatch.setenv("SSL_CERT_FILE", certifi.where())
    other = Client("https://example.invalid")
    assert context(other) is not context(a) and context(other).verify_mode == ssl.CERT_REQUIRED
    for c in (a, b, other):
        c.close()
