"""The core against the independent 50-digit reference (bench/reference.py) on seeded random scenes.

Also checks the reference itself: its derivatives against 50-digit finite differences of its own
energy, its PSD projection against the characterisation of the projection, and x = +phi.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
import pytest
from mpmath import mp, mpf

from jointlimits.service.core import evaluate
from bench import reference as ref_mod
from tests.conftest import relerr
from bench.reference import JointRef, reference_request, reference_total_energy
from tests.scenes import E_X, Scene, axis_pair_scene, place_limits, random_scene, random_unit

pytestmark = pytest.mark.slow  # mpmath over random scenes (~10 s)

TOL = 1e-12  # well-conditioned: gaps >= 5% of max(1, |x|), frames far from collapse; measured 2.4e-14 (random), 3.4e-15 (pairs)
OFF_BOUND = ("inside", "above", "below", "degenerate")
RANDOM_SEEDS = range(48)
PAIR_SEEDS = range(16)


def random_family(seed: int) -> Scene:
    return random_scene(np.random.default_rng(seed), OFF_BOUND)


def pair_family(seed: int) -> Scene:
    """Two strained bodies with a generic (jittered) motion about / along a random axis."""
    rng = np.random.default_rng(10_000 + seed)
    uid = (670, 669)[seed % 2]
    sc = axis_pair_scene(rng, uid, random_unit(rng), rng.uniform(-1.5, 1.5), rng.uniform(-2.5, 2.5), strain=0.2, jitter=0.05)
    return place_limits(sc, rng, (("above", "below", "degenerate")[seed % 3],))


@lru_cache(maxsize=None)
def reference_of(family: str, seed: int) -> tuple[Scene, list[dict[str, Any]]]:
    sc = random_family(seed) if family == "random" else pair_family(seed)
    return sc, reference_request(sc.request())


def compare(sc: Scene, ref: list[dict[str, Any]], mode: str) -> dict[str, float]:
    """Worst normwise relative error of each field over the batches of one scene."""
    ev = evaluate(**sc.core_args(hessian_mode=mode))
    err = dict(x=0.0, energy=0.0, gradient=0.0, hessian=0.0, total=relerr(ev.total_energy, reference_total_energy(ref)))
    assert len(ev.batches) == len(ref)
    for got, want in zip(ev.batches, ref):
        assert got.constitution_uid == want["constitution_uid"]
        # x is an angle in radians or a slide in O(1) scenes: its error is absolute, ~eps, even when x is tiny.
        err["x"] = max(err["x"], relerr(got.x, want["x"], floor=1.0))
        for f in ("energy", "gradient"):
            err[f] = max(err[f], relerr(getattr(got, f), want[f]))
        err["hessian"] = max(err["hessian"], relerr(got.hessian, want[f"hessian_{mode}"]))
    return err


@pytest.mark.parametrize("mode", ["exact", "psd"])
@pytest.mark.parametrize("seed", RANDOM_SEEDS)
def test_random_scenes_match_reference(seed: int, mode: str) -> None:
    sc, ref = reference_of("random", seed)
    err = compare(sc, ref, mode)
    assert max(err.values()) <= TOL, err


@pytest.mark.parametrize("mode", ["exact", "psd"])
@pytest.mark.parametrize("seed", PAIR_SEEDS)
def test_strained_pairs_match_reference(seed: int, mode: str) -> None:
    sc, ref = reference_of("pair", seed)
    err = compare(sc, ref, mode)
    assert max(err.values()) <= TOL, err
    assert sum(b.energy.sum() for b in evaluate(**sc.core_args()).batches) > 0  # each pair is outside its range


def test_random_family_is_not_trivial() -> None:
    """The family exercises what it claims: active joints in both constitutions, psd != exact somewhere."""
    active = {670: 0, 669: 0}
    psd_differs = False
    for seed in RANDOM_SEEDS:
        sc, ref = reference_of("random", seed)
        for b in ref:
            active[b["constitution_uid"]] += int(np.count_nonzero(b["energy"]))
            psd_differs |= relerr(b["hessian_psd"], b["hessian_exact"]) > 1e-3
    assert min(active.values()) >= 10, active
    assert psd_differs


@pytest.mark.parametrize("seed", range(4))
def test_on_bound_joints_are_inactive(seed: int) -> None:
    """x lands on l or u exactly in float64: the core pays nothing; the reference x is within rounding of the bound."""
    rng = np.random.default_rng(20_000 + seed)
    sc = place_limits(random_scene(rng), rng, ("on_lower", "on_upper", "degenerate_on"))
    ev = evaluate(**sc.core_args())
    ref = reference_request(sc.request())
    for b, got, want in zip(sc.batches, ev.batches, ref):
        assert np.all((got.x == b.lower) | (got.x == b.upper))
        assert np.all(got.energy == 0.0) and not got.gradient.any() and not got.hessian.any()
        # The exact x is off the bound by rounding only: its energy is negligible against the strength.
        assert relerr(got.energy, want["energy"], floor=float(b.strength.max())) <= 1e-30
        assert relerr(got.x, want["x"], floor=1.0) <= TOL


@pytest.mark.parametrize("seed", range(3))
def test_http_matches_reference(seed: int) -> None:
    from fastapi.testclient import TestClient  # imported here: the core tests do not depend on the HTTP layer

    from jointlimits.service.app import app

    sc, ref = reference_of("random", seed)
    with TestClient(app) as client:
        r = client.post("/v1/evaluate", json=sc.request(hessian_mode="psd"))
    assert r.status_code == 200, r.text
    for got, want in zip(r.json()["batches"], ref):
        assert relerr(got["energy"], want["energy"]) <= TOL
        assert relerr(got["gradient"], want["gradient"]) <= TOL
        assert relerr(got["hessian"], want["hessian_psd"]) <= TOL


# ---------------------------------------------------------------- the reference checks itself


def _reference_fd(sc: Scene) -> tuple[Any, list, list]:
    """50-digit central differences of the reference energy in the 24 current DOFs of joint 0.

    Steps: 1e-15 for the gradient (truncation h^2 ~ 1e-30, rounding 1e-50 / h ~ 1e-35), 1e-12 for the
    Hessian (truncation ~ 1e-24, rounding 1e-50 / h^2 ~ 1e-26).
    """
    b = sc.batches[0]
    i, j = b.body_ids[0]
    jr = JointRef(b.uid, sc.q_ref[i], sc.q_ref[j], b.edges[0])
    res = jr.evaluate((sc.q[i], sc.q[j]), (sc.q_prev[i], sc.q_prev[j]), (sc.q_ref[i], sc.q_ref[j]), b.lower[0], b.upper[0], b.strength[0])
    with mp.workdps(ref_mod.DPS):
        x_prev = jr.x((sc.q_prev[i], sc.q_prev[j]), (sc.q_prev[i], sc.q_prev[j]), (sc.q_ref[i], sc.q_ref[j]))
        F_prev = jr.frames(sc.q_prev[i], sc.q_prev[j])
        q0 = [mpf(float(v)) for v in np.concatenate([sc.q[i], sc.q[j]])]
        hg, hh = mpf("1e-15"), mpf("1e-12")

        def E(*steps: tuple[int, int]) -> Any:
            q = list(q0)
            for a, sgn in steps:
                q[a] += sgn * (hh if len(steps) == 2 else hg)
            return jr.energy_at(q, x_prev, F_prev, b.lower[0], b.upper[0], b.strength[0])

        g = [(E((a, 1)) - E((a, -1))) / (2 * hg) for a in range(24)]
        H = [[mpf(0)] * 24 for _ in range(24)]
        for a in range(24):
            for c in range(a, 24):
                H[a][c] = H[c][a] = (E((a, 1), (c, 1)) - E((a, 1), (c, -1)) - E((a, -1), (c, 1)) + E((a, -1), (c, -1))) / (4 * hh * hh)
    return res, g, H


@pytest.mark.parametrize("seed", range(2))
def test_reference_derivatives_are_its_energys(seed: int) -> None:
    """Gradient and exact Hessian of the reference = 50-digit differences of its energy."""
    sc, _ = reference_of("pair", seed)  # seed 0: revolute, 1: prismatic; both active
    res, g, H = _reference_fd(sc)
    with mp.workdps(ref_mod.DPS):
        scale_g = max(abs(v) for v in res.gradient)
        scale_h = max(abs(v) for row in res.hessian_exact for v in row)
        assert scale_g > 0 and scale_h > 0
        assert max(abs(a - b) for a, b in zip(res.gradient, g)) / scale_g < mpf("1e-25")
        assert max(abs(res.hessian_exact[a][c] - H[a][c]) for a in range(24) for c in range(24)) / scale_h < mpf("1e-20")


def test_reference_psd_projection_is_the_projection() -> None:
    """P = proj(C) iff P >= 0, P - C >= 0 and P (P - C) = 0 (the Jordan decomposition of C)."""
    rng = np.random.default_rng(7)
    with mp.workdps(ref_mod.DPS):
        for n in (3, 12):
            for _ in range(3):
                S = rng.normal(size=(n, n))
                C = [[mpf(float(v)) for v in row] for row in (S + S.T)]
                P = ref_mod._psd(C)
                Pm, Cm = mp.matrix(P), mp.matrix(C)
                tiny = mpf(10) ** (-40)
                assert min(mp.eigsy(Pm)[0]) > -tiny
                assert min(mp.eigsy(Pm - Cm)[0]) > -tiny
                assert mp.mnorm(Pm * (Pm - Cm), 1) < tiny
                assert mp.mnorm(Pm - Cm, 1) > 1  # a random symmetric matrix is indefinite: something was clamped


@pytest.mark.parametrize("case", range(10))
def test_reference_sign_convention(case: int) -> None:
    """The reference's own x = +phi / +d (turn or slide of body j relative to i; half at q_prev)."""
    uid, motion = [(670, 0.7), (670, -2.9), (670, 4.0), (669, 1.3), (669, -0.4)][case % 5]
    axis = ("random", "e_x")[case // 5]
    rng = np.random.default_rng(30_000 + case)
    t = E_X if axis == "e_x" else random_unit(rng)
    sc = axis_pair_scene(rng, uid, t, motion / 2, motion)
    b = sc.batches[0]
    jr = JointRef(uid, sc.q_ref[0], sc.q_ref[1], b.edges[0])
    x = jr.x(sc.q, sc.q_prev, sc.q_ref)
    assert abs(float(x) - motion) <= 1e-14 * max(1.0, abs(motion))
