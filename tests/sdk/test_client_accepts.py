"""What `evaluate` accepts and how the SDK reads in a notebook: dicts and wire models, TypeErrors,
unknown keywords, local errors without HTTP, `help(Client.evaluate)`, `repr(Evaluation)`."""

from __future__ import annotations

import doctest
import json
import socket
from dataclasses import replace

import numpy as np
import pytest

from jointlimits.client import AsyncClient, Client, InvalidInput, LocalClient, Scene, codec
from jointlimits.schemas import EvaluateRequest
from tests.sdk.test_client_sdk import chain, readme_scene
from tests.http.test_contract_live import live  # noqa: F401 (fixture)
from tests.conftest import same_numbers
from tests.http.test_errors_http import base_request


def wire_dict() -> dict:
    return json.loads(codec.encode(base_request(), binary=False)[0])


def same(a, b) -> None:
    assert a.total_energy == b.total_energy
    for ra, rb in zip(a.batches, b.batches, strict=True):
        for k in ("index", "x", "energy", "gradient", "hessian"):
            assert np.array_equal(getattr(ra, k), getattr(rb, k)), k


@pytest.mark.parametrize("mode", ["local", "binary", "json"])
def test_a_dict_and_a_wire_model_give_what_the_request_gives(live, mode):
    client = LocalClient() if mode == "local" else Client(live, binary=mode == "binary")
    want = client.evaluate(base_request())
    same(client.evaluate(wire_dict()), want)
    same(client.evaluate(EvaluateRequest.model_validate(wire_dict())), want)
    arrays = wire_dict()
    arrays["bodies"] = {k: np.asarray(v) for k, v in arrays["bodies"].items()}  # NumPy arrays inside are fine
    for b in arrays["batches"]:
        del b["strength"], b["base_uid"]  # the wire's defaults: strength 1, the constitution's base joint
    unit = base_request()
    unit.batches = [replace(b, strength=np.ones(len(b))) for b in unit.batches]
    same(client.evaluate(arrays), client.evaluate(unit))


def test_an_integer_past_64_bits_reads_as_the_server_reads_its_json(live):
    """Before: a dict holding 10**24 raised TypeError ("not wire JSON": orjson's 64-bit bound), where the server
    reads the same JSON number (a body id past int64: its 422; a bound: -1e24)."""
    import httpx

    d = wire_dict()
    d["batches"][0]["body_ids"][1][0] = 10**24
    served = httpx.post(f"{live}/v1/evaluate", content=json.dumps(d), headers={"Content-Type": "application/json"})
    assert served.status_code == 422
    for client in (LocalClient(), Client(live, binary=False), Client(live)):
        with pytest.raises(InvalidInput) as err:
            client.evaluate(d)
        assert [[list(f.loc), f.msg, f.type] for f in err.value.faults] == [
            [f["loc"], f["msg"], f["type"]] for f in served.json()["detail"]]
    d = wire_dict()
    d["batches"][0]["lower"][0] = -(10**24)
    want = LocalClient().evaluate({**d, "batches": [{**d["batches"][0], "lower": [-1e24, *d["batches"][0]["lower"][1:]]},
                                                    *d["batches"][1:]]})
    same(LocalClient().evaluate(d), want)
    same(Client(live).evaluate(d), want)


def test_a_bad_dict_gets_the_servers_loc_and_words(live):
    d = wire_dict()
    d["batches"][1]["lower"][2] = float("nan")
    for client in (LocalClient(), Client(live, binary=False), Client(live)):
        with pytest.raises(InvalidInput) as err:
            client.evaluate(d)
        assert (err.value.loc, err.value.msg) == (("body", "batches", 1, "lower", 2), "Input should be a finite number")
    d = wire_dict()
    d["batchs"] = d.pop("batches")
    with pytest.raises(InvalidInput) as err:
        LocalClient().evaluate(d)
    assert {f.loc for f in err.value.faults} == {("body", "batchs"), ("body", "batches")}


def closed_url() -> str:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return f"http://127.0.0.1:{port}"


@pytest.mark.parametrize("bad", [[1, 2], "request", None, np.zeros(3)])
def test_anything_else_is_a_type_error_naming_what_is_accepted(bad):
    import asyncio

    async def run():
        async with AsyncClient(closed_url(), retries=0) as c:
            await c.evaluate(bad)

    for call in (lambda: LocalClient().evaluate(bad), lambda: Client(closed_url(), retries=0).evaluate(bad),
                 lambda: asyncio.run(run())):
        with pytest.raises(TypeError) as err:  # before any connection is tried
            call()
        assert all(w in str(err.value) for w in ("client.Request", "dict", "schemas.EvaluateRequest")), err.value


def test_local_client_refuses_unknown_keywords_and_takes_the_http_ones():
    with pytest.raises(TypeError, match="'thread'"):
        LocalClient(thread=2)
    LocalClient(binary=True, timeout=5, retries=1, connect_timeout=1, concurrency=2)  # one word to switch modes


def test_local_errors_do_not_mention_http(live):
    """The same fault in the same words on each in-process path (LocalClient and its session: "invalid input") and
    over HTTP (Client and its session: "HTTP 422"), at the opening and at a later message (failed before: the local
    session said "HTTP 422")."""
    bad = base_request()
    bad.batches[1].lower[2] = 5.0
    good = base_request()
    q = np.array(good.q)[:-1]  # a body short: the core's fault, at the message's `q`
    errors: dict[tuple[str, str], InvalidInput] = {}
    with Client(live) as client:
        for name, c in (("local", LocalClient()), ("HTTP", client)):
            def in_session(message):
                with c.session(good) as s:
                    message(s)
            for path, call in (("evaluate", lambda: c.evaluate(bad)), ("opening", lambda: c.session(bad)),
                               ("message", lambda: in_session(lambda s: s.evaluate(q))),
                               ("update", lambda: in_session(lambda s: s.update(1, [7], upper=[1.0])))):
                with pytest.raises(InvalidInput) as e:
                    call()
                errors[name, path] = e.value
    assert str(errors["local", "evaluate"]).startswith("invalid input: body.batches.1.lower.2: ")
    assert str(errors["local", "message"]).startswith("invalid input: body.q: ")
    for path in ("evaluate", "opening", "message", "update"):
        local, remote = errors["local", path], errors["HTTP", path]
        assert (local.where, remote.where) == ("invalid input", "HTTP 422"), path
        assert str(local) == str(remote).replace("HTTP 422", "invalid input", 1) and "HTTP" not in str(local), path
        assert local.faults == remote.faults and local.status == remote.status == 422, path
    assert str(errors["local", "opening"]) == str(errors["local", "evaluate"])


class _UpToLastBits(doctest.OutputChecker):
    """The example's floats as printed here, up to another CPU's last bits (`same_numbers`)."""

    def check_output(self, want: str, got: str, optionflags: int) -> bool:
        return same_numbers(got, want)


def test_evaluate_has_a_real_docstring_and_its_example_runs():
    doc = Client.evaluate.__doc__
    for words in (".request(outputs=", "dict", "EvaluateRequest", "Returns", "Raises", "InvalidInput",
                  "Unreachable", "(M, 24, 24)", ">>>"):
        assert words in doc, words
    c, s = np.cos(0.7), np.sin(0.7)
    globs = {"np": np, "Scene": Scene, "client": LocalClient(),
             "turned": np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])}
    test = doctest.DocTestParser().get_doctest(doc, globs, "Client.evaluate", None, 0)
    result = doctest.DocTestRunner(checker=_UpToLastBits()).run(test)
    assert result.failed == 0 and result.attempted >= 5
    assert "Client.evaluate" in LocalClient.evaluate.__doc__ and "Client.evaluate" in AsyncClient.evaluate.__doc__


def test_repr_of_an_evaluation_is_a_summary():
    request = chain(60, 100, seed=1)
    ev = LocalClient().evaluate(request)
    text = repr(ev)
    assert len(text.splitlines()) == 2 + len(ev.batches) and len(text) < 600, text
    assert f"total_energy={ev.total_energy!r}" in text
    for b, r in zip(ev.batches, request.batches):
        assert f"constitution_uid={b.constitution_uid}, rows={len(b.index)} of {len(r)} joints" in text
    assert "outputs=x, energy, gradient, hessian" in text
    only = LocalClient().evaluate(readme_scene().request(outputs=("energy",), active_only=True))
    assert "outputs=x, energy)" in repr(only)


@pytest.mark.parametrize("big", [False, True], ids=["plain", "with an integer past 64 bits"])
def test_a_dicts_float32_arrays_and_scalars_are_read_at_their_value(big):
    """A dict's NumPy float32/float16 values are the numbers they hold, as a `Request` of the same arrays reads them
    (`np.asarray(a, np.float64)` widens exactly). Before, orjson wrote each float32 as its shortest decimal (0.7 for
    0.699999988...), so the dict was read 1e-8 away from its own values (energy 2.576620 against 2.576617), and a
    dict that also held an integer past 64 bits (the standard library's json) was read at the exact values."""
    d32, d64 = wire_dict(), wire_dict()
    q32 = np.asarray(d32["bodies"]["q"], np.float32)
    d32["bodies"]["q"], d64["bodies"]["q"] = q32, q32.astype(np.float64)
    lower = np.float32(-0.1), np.float16(-0.3)
    d32["batches"][0]["lower"] = list(lower)
    d64["batches"][0]["lower"] = [float(v) for v in lower]
    if big:  # an upper bound of 10**24 (the server reads it as 1e24): the standard library's json writes the dict
        d32["batches"][1]["upper"][0] = d64["batches"][1]["upper"][0] = 10**24
    assert np.asarray(d64["bodies"]["q"]).tolist() != np.asarray(d64["bodies"]["q"]).round(6).tolist()  # not decimals
    same(LocalClient().evaluate(d32), LocalClient().evaluate(d64))


def test_an_integer_past_float64_in_an_object_array_is_read_as_in_a_list():
    """10**400 in a NumPy object array is +inf, as in a list (JSON's 1 and 400 zeros): a session's update names it
    where it is, and `JointBatch.of` takes it as the list (the evaluation names it). Before (since ba7353e), the
    object array raised OverflowError ('int too large to convert to float') from both."""
    from jointlimits.client import JointBatch

    r = base_request()
    b = r.batches[0]
    for lower in ([10**400] * len(b.lower), np.array([10**400] * len(b.lower), dtype=object)):
        assert JointBatch.of(670, b.body_ids, b.edges, lower, b.upper, b.strength).lower.tolist() == [np.inf] * len(b.lower)
        with LocalClient().session(r) as s:
            with pytest.raises(InvalidInput) as err:
                s.update(0, [0], lower=lower[:1])
            assert [(f.loc, f.msg, f.type) for f in err.value.faults] == [
                (("body", "batches", 0, "lower", 0), "Input should be a finite number", "finite_number")]


@pytest.mark.parametrize("what", ["a set", "nested 3000 deep"])
def test_a_dict_no_json_writer_can_write_is_a_type_error(what):
    """A value JSON has no word for, or nesting deeper than any JSON reader takes: `TypeError` ("not wire JSON"),
    as the docstring of `as_request` says. Before, the nesting raised the standard library's RecursionError (the
    json fallback for integers past 64 bits, 6bdd800); orjson's own limit gave this TypeError."""
    d = wire_dict()
    if what == "a set":
        d["batches"][0]["lower"] = set(d["batches"][0]["lower"])
    else:
        x: list = [0.0]
        for _ in range(3000):
            x = [x]
        d["bodies"]["q"] = x
    with pytest.raises(TypeError, match="not wire JSON"):
        LocalClient().evaluate(d)
