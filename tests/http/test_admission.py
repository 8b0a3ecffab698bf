"""Admission by cost before any work (issue 9, items 3, 7, 8) and the per-request deadline.

Every bound answers 413 naming the bound, the figure and what to do, before the core
runs; the answer's size is bounded from joints x outputs x encoding, and the bound
is checked to hold against real and worst-case answers of both encodings.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient

from jointlimits.client import JointBatch, codec, request_from_arrays
from jointlimits.schemas import binary as wire
from jointlimits.service.app import create_app
from jointlimits.service.core import BatchResult, Evaluation, evaluate
from jointlimits.service.core.errors import DeadlineExceeded
from jointlimits.service.core.evaluate import CHUNK
from jointlimits.service.core import evaluate as checked_evaluate
from jointlimits.service.http import binary, convert, document, limits, routes
from jointlimits.service.settings import Settings
from tests import drills as lt

EGH = ("energy", "gradient", "hessian")
J, B = "application/json", "application/msgpack"


scene = lt.array_scene  # n revolute joints on body pairs, every one past its upper limit


def client(**settings) -> TestClient:
    return TestClient(create_app(Settings(**{"token": None, "cors_origins": (), **settings})))


def post(c: TestClient, request, binary_request: bool, answer: str | None = None):
    body, ctype = codec.encode(request, binary=binary_request)
    headers = {"Content-Type": ctype, **({"Accept": answer} if answer else {})}
    return c.post("/v1/evaluate", content=body, headers=headers)


# ------------------------------------------------------------------ the answer's size, bounded before work


def answers(ev: Evaluation) -> dict[bool, bytes]:
    return {False: convert.encode(ev), True: binary.encode(ev)}


@pytest.mark.parametrize("outputs", [("energy",), ("energy", "gradient"), EGH, ("hessian",)])
@pytest.mark.parametrize("n,batches", [(0, 1), (1, 1), (7, 3), (CHUNK + 5, 2)])
def test_the_bound_holds_for_real_answers(outputs, n, batches):
    req = scene(n, batches, outputs)
    ev = checked_evaluate(**_core_args(req))
    for binary_answer, content in answers(ev).items():
        bound = limits.answer_bytes([len(b) for b in req.batches], outputs, binary_answer)
        assert len(content) <= bound
        if binary_answer and n > 100:  # msgpack: exact but for the headers
            assert bound - len(content) < 2 * limits.BATCH_OVERHEAD_BYTES * (batches + 1)


def test_the_bound_holds_for_the_longest_floats_and_indices():
    """Every float the longest shortest-round-trip repr (24 characters), every index as long as it gets."""
    worst = -2.2250738585072014e-308
    assert len(repr(worst)) == 24
    n = 1001
    batch = BatchResult(
        constitution_uid=670,
        index=np.arange(n, dtype=np.int64),
        x=np.full(n, worst),
        energy=np.full(n, worst),
        gradient=np.full((n, 24), worst),
        hessian=np.full((n, 24, 24), worst),
    )
    ev = Evaluation(total_energy=worst, batches=[batch, replace(batch, constitution_uid=669)])
    for binary_answer, content in answers(ev).items():
        bound = limits.answer_bytes([n, n], EGH, binary_answer)
        assert len(content) <= bound
        assert len(content) > 0.95 * bound  # and tight: the bound is what a worst answer costs


def test_json_answer_is_written_in_pieces_with_the_bytes_of_one_dumps(monkeypatch):
    """orjson holds the GIL per call: no call writes more than FLOATS_PER_PIECE numbers, and the bytes are unchanged."""
    ev = checked_evaluate(**_core_args(scene(3000, 2)))
    doc = convert.to_wire(ev)
    for b in doc["batches"]:
        for k, v in b.items():
            b[k] = np.ascontiguousarray(v) if isinstance(v, np.ndarray) else v
    whole = orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY)
    sizes, dumps = [], orjson.dumps

    def counting(obj, *args, **kw):
        sizes.append(np.size(obj))
        return dumps(obj, *args, **kw)

    monkeypatch.setattr(convert.orjson, "dumps", counting)
    assert convert.encode(ev) == whole
    assert max(sizes) <= convert.FLOATS_PER_PIECE and len(sizes) > 10


def _core_args(req) -> dict:
    """The core's keyword arguments for `req`, as the msgpack path makes them."""
    return binary.decode(codec.encode(req, binary=True)[0])


# ------------------------------------------------------------------ 413s, before any work


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if the core is called: admission must refuse before it."""

    def refuse(*a, **kw):
        raise AssertionError("the core ran for a request that admission should have refused")

    monkeypatch.setattr(routes, "evaluate", refuse)


@pytest.mark.parametrize("binary_request", [False, True])
def test_answer_over_the_bound_is_413_before_any_work(binary_request, no_work):
    n = 100
    cap = limits.answer_bytes([n], EGH, binary_answer=True) - 1  # one byte short, even for msgpack
    c = client(max_answer_bytes=cap)
    for answer in (J, B):
        r = post(c, scene(n, outputs=EGH), binary_request, answer)
        assert r.status_code == 413, r.text
        (d,) = r.json()["detail"]
        assert d["loc"] == ["body", "outputs"] and d["type"] == "too_large"
        want = limits.answer_bytes([n], EGH, answer == B)
        for words in (str(want), str(cap), "JOINTLIMITS_MAX_ANSWER_BYTES", "split the batch", "fewer outputs", "active_only"):
            assert words in d["msg"]
        assert ("Accept: application/msgpack" in d["msg"]) == (answer == J)


@pytest.mark.parametrize("binary_request", [False, True])
def test_at_the_answer_bound_is_answered(binary_request):
    n = 100
    c = client(max_answer_bytes=limits.answer_bytes([n], EGH, binary_answer=True))
    assert post(c, scene(n), binary_request, B).status_code == 200
    assert post(c, scene(n), binary_request, J).status_code == 413  # JSON's bound is three times larger
    assert post(c, scene(n, outputs=("energy", "gradient")), binary_request, J).status_code == 200


def test_active_only_is_bounded_as_if_every_joint_were_active(no_work):
    """Which joints are active is known only after evaluating them: the bound counts all of them."""
    n = 100
    c = client(max_answer_bytes=limits.answer_bytes([n], EGH, binary_answer=True) - 1)
    r = post(c, scene(n, active_only=True), True, B)
    assert r.status_code == 413 and "active_only does not lower this bound" in r.json()["detail"][0]["msg"]


@pytest.mark.parametrize("binary_request", [False, True])
def test_batches_over_the_bound_are_413_before_any_work(binary_request, no_work):
    r = post(client(max_batches=8), scene(9, batches=9, outputs=("energy",)), binary_request)
    assert r.status_code == 413, r.text
    (d,) = r.json()["detail"]
    assert d["loc"] == ["body", "batches"]
    for words in ("9 batches", "at most 8", "JOINTLIMITS_MAX_BATCHES", "merge batches"):
        assert words in d["msg"]


@pytest.mark.parametrize("binary_request", [False, True])
def test_batches_at_the_bound_are_answered(binary_request):
    r = post(client(max_batches=8), scene(8, batches=8, outputs=("energy",)), binary_request)
    assert r.status_code == 200 and len(r.json()["batches"] if not binary_request else wire.loads(r.content)["batches"]) == 8


def test_json_values_over_the_bound_are_413_before_parsing(monkeypatch):
    body, _ = codec.encode(scene(50, outputs=("energy",)), binary=False)
    values = body.count(b",") + 1

    def no_parse(*a, **kw):
        raise AssertionError("parsed a body that should have been refused")

    monkeypatch.setattr(convert, "from_json", no_parse)
    r = client(max_json_values=values - 1).post("/v1/evaluate", content=body, headers={"Content-Type": J})
    assert r.status_code == 413
    (d,) = r.json()["detail"]
    assert d["loc"] == ["body"]
    for words in (str(values), str(values - 1), "JOINTLIMITS_MAX_JSON_VALUES", "msgpack", "split"):
        assert words in d["msg"]
    monkeypatch.undo()
    assert client(max_json_values=values).post("/v1/evaluate", content=body, headers={"Content-Type": J}).status_code == 200
    # msgpack has no per-value cost: the same request in msgpack is not counted.
    assert post(client(max_json_values=values - 1), scene(50, outputs=("energy",)), True).status_code == 200


def test_nested_lists_count_as_values_before_parsing(monkeypatch):
    """Commas bound a document's numbers, not its lists: `[[[[[[[[0]]]]]]]]` is one comma's worth and 9 Python
    objects. 1e6 such items (18 MB, half the value bound) took a worker from 67 to 993 MiB and held the GIL 8.4 s
    (HTTP) to 10 s (a session message, parsed on the event loop): every other client of the worker stalled that long.
    The count is now the larger of the commas and twice the lists and objects (a list costs the parse 3 to 7
    numbers), whatever the nesting; an honest request's count is its commas, as before."""
    body, _ = codec.encode(scene(50, outputs=("energy",)), binary=False)
    assert limits.check_json(body, 10**9) == body.count(b",") + 1  # an honest request: the commas (more than brackets)
    items = b"[" + b",".join([b"[" * 8 + b"0" + b"]" * 8] * 1000) + b"]"  # 1000 commas, 8002 brackets
    # Each under 16004 by its commas (1001, 1000): the request counts 16009 (and 2 braces), the message 16005.
    refused_unparsed(monkeypatch, items, items, 16004, 16009, 16005)


def test_an_objects_keys_count_before_parsing(monkeypatch):
    """A key costs the parse 1 to 4 lists (8 of the count; a list is 2): 2e6 distinct keys of one object (25 MB, a count of 2e6
    by its commas) took the parse 2.3-2.7 s, 5.4 s where the object sits in a list (its keys are then not the
    request's, and `convert.load` reads the body again with `json` to name repeated ones), against 0.7-1.2 s for
    the 1e6 lists the count admits. The count is now also 8 times the colons, whose keys follow; an honest
    request's keys (a dozen per batch, at most `JOINTLIMITS_MAX_BATCHES` batches) count far less than its commas
    wherever that is near the bound."""
    body, _ = codec.encode(scene(50, outputs=("energy",)), binary=False)
    assert limits.check_json(body, 10**9) == body.count(b",") + 1  # an honest request: still its commas
    keys = b"{" + b",".join(b'"k%05d":0' % i for i in range(1000)) + b"}"  # 999 commas, 1000 colons
    # Each far under 8000 by its commas and brackets: the request counts 8025 by its colons, the message 8017.
    refused_unparsed(monkeypatch, b"[[" + keys + b"]]", b"[" + keys + b"]", 8000, 8025, 8017)


def refused_unparsed(monkeypatch, request_q: bytes, message_q: bytes, bound: int, request_count: int,
                     message_count: int) -> None:
    """Under `max_json_values=bound`, a request whose `q` is `request_q` and a session's later message whose `q`
    is `message_q` are refused 413 with these counts, neither parsed."""

    def no_parse(*a, **kw):
        raise AssertionError("parsed a document that should have been refused")

    c = client(max_json_values=bound)
    with c.websocket_connect("/v1/sessions") as ws:
        ws.send_text(codec.encode(scene(1, outputs=("energy",)), binary=False)[0].decode())
        assert orjson.loads(ws.receive_text())["kind"] == "opened"
        monkeypatch.setattr(convert, "from_json", no_parse)
        ws.send_text((b'{"kind":"evaluate","q":' + message_q + b"}").decode())
        reply = orjson.loads(ws.receive_text())
        assert reply["kind"] == "error" and reply["status"] == 413
        assert f"up to {message_count} values" in reply["detail"][0]["msg"]
    r = c.post("/v1/evaluate", content=b'{"bodies":{"q":' + request_q + b'},"batches":[]}', headers={"Content-Type": J})
    assert r.status_code == 413 and r.json()["detail"][0]["loc"] == ["body"], r.text
    assert f"up to {request_count} values (counted by its commas, brackets and keys)" in r.json()["detail"][0]["msg"]


def test_msgpack_refuses_an_array_beyond_its_largest_bin():
    assert wire._bin_header(2**32 - 1) == b"\xc6\xff\xff\xff\xff"
    with pytest.raises(ValueError, match="exceeds msgpack's largest bin"):
        wire._bin_header(2**32)


def test_the_default_bound_keeps_msgpack_answers_far_below_4_gib():
    """The 500 of issue 9 (an OverflowError after computing a > 4 GiB answer) cannot be reached at the defaults."""
    s = Settings()
    assert limits.answer_bytes([s.max_joints], EGH, binary_answer=True) > 2**32  # what used to be computed
    assert s.max_answer_bytes < 2**32 // 4
    r = post(client(), scene(10, outputs=EGH), True, B)
    assert r.status_code == 200


@pytest.mark.slow  # issue 9's 1e6-joint bodies
@pytest.mark.parametrize("n", [250_000, 1_000_000])
def test_issue_9s_hessian_requests_are_refused_at_the_defaults(n, no_work):
    """Issue 9's probes: 2.5e5 joints with Hessians (a 1.2 GB answer, 2.9 GB peak RSS) and 1e6
    (a > 4 GiB msgpack answer, then a 500): 413s before any work."""
    ids = np.tile([[0, 1]], (n, 1))
    edges = np.tile([[0.0, 0, 0], [0, 0, 1]], (n, 1, 1))
    req = request_from_arrays(np.tile(np.r_[np.zeros(3), np.eye(3).reshape(9)], (2, 1)), [JointBatch.of(670, ids, edges, -np.ones(n), np.ones(n), np.ones(n))])
    r = post(client(), req, True, B)
    assert r.status_code == 413 and r.json()["detail"][0]["loc"] == ["body", "outputs"]


# ------------------------------------------------------------------ the deadline


def test_core_checks_the_deadline_between_batches_and_chunks(monkeypatch):
    """A clock that ticks once per look: the k-th check past the deadline stops the evaluation there."""
    from jointlimits.service.core import errors

    req = scene(2 * CHUNK + 10, batches=2)
    args = _core_args(req)
    full = evaluate(**args)
    checks = []

    class Clock:
        t = 0.0

        def monotonic(self) -> float:
            self.t += 1.0
            checks.append(self.t)
            return self.t

    monkeypatch.setattr(errors, "time", Clock())
    evaluate(**args, deadline=1e9)
    # One check per batch and per derivative chunk (each batch of CHUNK + 5 active joints has 2 chunks).
    assert len(checks) == 2 + 2 * 2
    for k in range(1, 7):
        checks.clear()
        Clock.t = 0.0
        monkeypatch.setattr(errors, "time", Clock())
        with pytest.raises(DeadlineExceeded):
            evaluate(**args, deadline=k - 0.5)
        assert len(checks) == k  # stopped at the first check past the deadline
    monkeypatch.undo()
    again = evaluate(**args, deadline=time.monotonic() + 3600)
    assert again.total_energy == full.total_energy
    assert all(np.array_equal(a.hessian, b.hessian) for a, b in zip(again.batches, full.batches))


def test_checked_evaluate_passes_the_deadline():
    with pytest.raises(DeadlineExceeded):
        checked_evaluate(**_core_args(scene(10)), deadline=time.monotonic() - 1)


@pytest.mark.slow  # evaluations held past the deadline
@pytest.mark.serial  # a 0.3 s evaluation against a 0.1 s deadline
@pytest.mark.parametrize("binary_request", [False, True])
def test_past_the_deadline_is_503_with_retry_after(binary_request, monkeypatch):
    """The request timeout passes while the core runs: 503, Retry-After, the bound named."""
    real = routes.evaluate

    def slow(*a, deadline=None, **kw):
        time.sleep(0.3)
        return real(*a, deadline=deadline, **kw)

    monkeypatch.setattr(routes, "evaluate", slow)
    c = client(request_timeout=0.1)
    r = post(c, scene(10), binary_request)
    assert r.status_code == 503, r.text
    assert int(r.headers["Retry-After"]) >= 1
    (d,) = r.json()["detail"]
    assert d["type"] == "timeout" and "0.1 s" in d["msg"] and "JOINTLIMITS_REQUEST_TIMEOUT" in d["msg"]
    assert post(client(request_timeout=60), scene(10), binary_request).status_code == 200


@pytest.mark.slow  # 3 x 1e4 joints with Hessians, stopped at a 1 ms deadline
@pytest.mark.serial  # a deadline in wall-clock time
def test_a_real_evaluation_past_a_short_deadline_is_stopped():
    """No mock: 3 x 1e4 joints with Hessians take far more than 1 ms; stopped after the parse or in the core."""
    c = client(request_timeout=0.001)
    r = post(c, scene(30_000, batches=3), True, B)
    assert r.status_code == 503 and r.headers["Retry-After"]


# ------------------------------------------------------------------ settings and flags agree


def test_flags_default_to_the_settings_defaults_and_read_the_environment(monkeypatch):
    from jointlimits.service import cli

    names = ("max_batches", "max_answer_bytes", "max_json_values", "request_timeout")
    for name in names:
        monkeypatch.delenv("JOINTLIMITS_" + name.upper(), raising=False)
    args, settings = cli.build_parser().parse_args(["serve"]), Settings()
    assert [getattr(args, n) for n in names] == [getattr(settings, n) for n in names]
    assert (args.max_batches, args.max_answer_bytes, args.max_json_values, args.request_timeout) == (4096, 256 * 2**20, 2_000_000, 60.0)
    monkeypatch.setenv("JOINTLIMITS_MAX_ANSWER_BYTES", "1234")
    monkeypatch.setenv("JOINTLIMITS_REQUEST_TIMEOUT", "2.5")
    args = cli.build_parser().parse_args(["serve", "--max-batches", "7"])
    assert (args.max_answer_bytes, args.request_timeout, args.max_batches) == (1234, 2.5, 7)
    assert (Settings().max_answer_bytes, Settings().request_timeout) == (1234, 2.5)
    for bad in (["--request-timeout", "0"], ["--max-answer-bytes", "-1"], ["--healthcheck-timeout", "0"]):
        with pytest.raises(SystemExit):
            cli.build_parser().parse_args(["serve", *bad])


# ------------------------------------------------------------------ the SDK splits by the same bounds


@pytest.mark.slow  # split requests to a live server
@pytest.mark.parametrize("binary_client", [False, True])
def test_sdk_splits_by_the_answer_bound_and_json_values(binary_client):
    """The server tells its bounds; the SDK's parts all fit them, and the merged answer is the whole one."""
    from jointlimits.client import Client, LocalClient
    from tests.http.test_contract_live import serve

    req = scene(600, batches=2, pairs=3)
    cap = limits.answer_bytes([100], EGH, binary_answer=binary_client)  # ~100 joints with Hessians per part
    settings = Settings(token=None, cors_origins=(), max_answer_bytes=cap, max_json_values=100 * 91)
    with serve(settings) as url, Client(url, binary=binary_client) as c:
        lim = c.constitutions().limits
        assert (lim.max_answer_bytes, lim.max_json_values, lim.max_batches) == (cap, 100 * 91, settings.max_batches)
        sent = []
        with httpx_spy(sent):
            got = c.evaluate(req)
    want = LocalClient().evaluate(req)
    assert 6 <= len(sent) <= 8 and set(sent) == {200}
    assert got.total_energy == pytest.approx(want.total_energy, rel=1e-14)  # a sum of the parts' sums
    for g, w in zip(got.batches, want.batches):
        assert np.array_equal(g.x, w.x) and np.array_equal(g.hessian, w.hessian)


def httpx_spy(statuses: list[int]):
    """Record the status of every /v1/evaluate answer the SDK receives."""
    import contextlib

    import httpx

    real = httpx.Client.send

    def send(self, request, *a, **kw):
        response = real(self, request, *a, **kw)
        if request.url.path == "/v1/evaluate":
            statuses.append(response.status_code)
        return response

    @contextlib.contextmanager
    def patched():
        httpx.Client.send = send
        try:
            yield
        finally:
            httpx.Client.send = real

    return patched()


@pytest.mark.slow  # issue 9's 10k-batch bodies
def test_issue_9s_ten_thousand_batches_are_refused_at_the_defaults(no_work):
    """Issue 9's probe: 10k one-joint batches took 5 s; now a 413 at the default 4096, in either encoding."""
    req = scene(10_000, batches=10_000, outputs=("energy",))
    for binary_request in (False, True):
        r = post(client(), req, binary_request)
        assert r.status_code == 413 and "JOINTLIMITS_MAX_BATCHES" in r.json()["detail"][0]["msg"]


def test_batches_are_counted_before_they_are_read(no_work, monkeypatch):
    """msgpack: refused before any batch is decoded; JSON: before parsing, by their braces."""
    req = scene(9, batches=9, outputs=("energy",))

    def no_batch(*a, **kw):
        raise AssertionError("a batch was read")

    monkeypatch.setattr(document.Checker, "batch", no_batch)
    r = post(client(max_batches=8), req, True)
    assert r.status_code == 413 and "has 9 batches" in r.json()["detail"][0]["msg"]
    monkeypatch.setattr(convert, "from_json", no_batch)
    r = post(client(max_batches=8), req, False)
    assert r.status_code == 413
    assert "up to 9 batches (counted by their braces)" in r.json()["detail"][0]["msg"]


def test_a_bad_variable_is_refused_like_a_bad_flag(monkeypatch):
    from jointlimits.service import cli

    monkeypatch.setenv("JOINTLIMITS_REQUEST_TIMEOUT", "0")
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["serve"])
