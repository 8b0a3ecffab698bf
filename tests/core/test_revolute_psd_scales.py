"""The revolute psd Hessian at every scale of the bodies' `A` (issue 27): right and PSD, or the overflow error.

The angle depends only on the directions of each body's frame vectors: `A_i`, `A_j` scaled by
`lambda_i`, `lambda_j` leave `x` alone, and the Hessian of both bodies scaled by `lambda` is the
unscaled one over `lambda^2`. Frames whose `hypot(cos, sin)` leaves `2^+-240` are differentiated from
per-body scaled frames (`Revolute.derivatives`); their projection once took `r` at the old scale
(1e40: max|H| 2.8e3 for 1.1e-76; 1e-40: min eigenvalue -0.043 x the norm, 11% off; one body 1e75:
21% off). Checked here: the closed form against `numpy.linalg.eigh` on frames scaled per body, and the
whole chain against the 50-digit reference (`bench/reference.py`, mpmath eigen-decomposition of
`E' d2x/dF2`): exactly scaled by `4^-k` for both bodies' `A` times `2^k` (the float64 input is then
scaled exactly, so is the true answer), and afresh at the issue's decimal scales.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from bench.reference import reference_request
from jointlimits.service.core import evaluate
from jointlimits.service.core.errors import InputError
from tests.conftest import relerr
from tests.scenes import Batch, Scene, pack, place_limits, random_affine, random_unit, rotation_about
from tests.core.test_psd_revolute import check, slopes

STATES = ("q", "q_prev", "q_ref")

TOL = 1e-13
"""Normwise against the 50-digit reference. The float64 answer's own error: the polar factor of `A_ref`
(~5e-15), the frames' 3-term dots (a few u = 1.1e-16 each, relative to each body's own frames: per-body
scales cost nothing), `x` (~1e-15 over its two steps) into E' = 3 s g^2 / w^3 through a gap g >= 0.05
(2 dx / g <= 4e-14), then the projection's closed form, whose terms are each at most twice the
projection's norm (a few u each), and the chain rule's 12-term sums: <= ~5e-14 in all. Measured
<= 1.7e-14 (at scale 1, the unscaled path), <= 8.8e-15 at the other scales. 1e-13 is the golden
cases' bound; the bug was off by 1e-2 ... 1e79."""

PSD_TOL = 1e-13
"""Smallest eigenvalue of a 24 x 24 psd Hessian >= -PSD_TOL x its largest |eigenvalue|: `eigvalsh`'s
backward error (a few u x the norm) and the closed form's roundings (each term <= 2 x the norm, a few u
each); measured >= -3.5e-16. The bug's was -0.043."""


def _pairs_scene(seed: int, n: int, scale_i: float = 1.0, scale_j: float = 1.0) -> Scene:
    """n revolute joints, each on its own two stretched bodies (body j turned about the axis against
    body i), every state's `A_i` times `scale_i` and `A_j` times `scale_j`; limits still to be placed."""
    rng = np.random.default_rng(seed)
    rows = {s: [] for s in STATES}
    edges = []
    for _ in range(n):
        t = random_unit(rng)
        p0 = rng.normal(size=3)
        edges.append([p0, p0 + t])
        for s in STATES:
            A_i = random_affine(rng) * scale_i
            A_j = rotation_about(t, rng.uniform(-1.5, 1.5)) @ random_affine(rng) * scale_j
            rows[s] += [pack(rng.normal(size=3), A_i), pack(rng.normal(size=3), A_j)]
    ids = np.arange(2 * n).reshape(n, 2)
    zeros = np.zeros(n)
    batch = Batch(670, ids, np.array(edges), zeros, zeros, np.ones(n))
    return Scene(np.array(rows["q"]), np.array(rows["q_prev"]), np.array(rows["q_ref"]), [batch])


def _limited(sc: Scene, seed: int) -> Scene:
    """Every joint active, above and below in turn (E' of both signs)."""
    return place_limits(sc, np.random.default_rng(seed), ("above", "below"))


def _core_psd(sc: Scene) -> np.ndarray:
    return evaluate(**sc.core_args(hessian_mode="psd")).batches[0].hessian


def _reference_psd(sc: Scene) -> np.ndarray:
    return reference_request(sc.request(hessian_mode="psd"))[0]["hessian_psd"]


def _assert_psd_hessian(H: np.ndarray, want: np.ndarray) -> None:
    """Per joint: normwise within TOL of `want`, bitwise symmetric, PSD to PSD_TOL."""
    assert np.isfinite(H).all()
    for k in range(H.shape[0]):
        assert relerr(H[k], want[k]) <= TOL, (k, relerr(H[k], want[k]))
    assert np.array_equal(H, H.transpose(0, 2, 1))
    lam = np.linalg.eigvalsh(H)
    top = np.abs(lam).max(axis=1, keepdims=True)
    assert (lam >= -PSD_TOL * top).all(), (lam.min(axis=1) / top[:, 0])


# ---------------------------------------------------------------- the closed form, against eigh


# Per-body factors of F (body i, body j): both alike (r ~ 1e+-80 ... 1e+-200, beyond 2^+-240), one body
# alone (r ~ 1e+-75), opposite (r ~ 1, the plain path with rho^2 >> r) and powers of two far apart.
FACTORS = [
    (1e-100, 1e-100), (1e-40, 1e-40), (1e40, 1e40), (1e100, 1e100),
    (1e75, 1.0), (1.0, 1e75), (1e-75, 1.0), (1.0, 1e-75),
    (1e150, 1e-150), (1e-150, 1e150), (1e200, 1e-100), (1e-100, 1e200),
    (2.0**133, 2.0**133), (2.0**-133, 2.0**-133), (2.0**400, 2.0**-100), (2.0**-300, 2.0**250),
]


@pytest.mark.parametrize("scale_i,scale_j", FACTORS, ids=[f"{a:.3g}-{b:.3g}" for a, b in FACTORS])
def test_closed_form_on_frames_scaled_per_body(scale_i: float, scale_j: float) -> None:
    """`projected_curvature` against eigh of the exact `E' d2x/dF2` at the true frames (both representable
    at these scales): normwise, eigenvalues, PSD, symmetric (tests/core/test_psd_revolute.check, 1e-13)."""
    rng = np.random.default_rng(int(np.log2(scale_i) * 7 + np.log2(scale_j)) % 2**32)
    n = 200
    F = rng.normal(size=(n, 4, 3)) * 10.0 ** rng.uniform(-1, 1, size=(n, 4, 1))
    F[:, :2] *= scale_i
    F[:, 2:] *= scale_j
    with np.errstate(all="ignore"):  # as the pipeline calls it (prepared.py): scaled rows overflow, then are redone
        check(F, slopes(rng, n))


def test_closed_form_on_rows_of_mixed_scales() -> None:
    """One call whose rows are at their own per-body scales 2^-300 ... 2^300: the scaled rows and the
    plain ones side by side, each its own projection."""
    rng = np.random.default_rng(27)
    n = 400
    F = np.ldexp(rng.normal(size=(n, 4, 3)), np.repeat(rng.integers(-300, 301, size=(n, 2)), 2, axis=1)[:, :, None])
    with np.errstate(all="ignore"):  # as the pipeline calls it (prepared.py)
        check(F, slopes(rng, n))


# ---------------------------------------------------------------- the whole chain, against 50 digits

N = 4
SEED = 2700


@lru_cache(maxsize=None)
def _unscaled() -> tuple[Scene, np.ndarray]:
    """The joints at scale 1 with their limits, and their 50-digit psd Hessians."""
    sc = _limited(_pairs_scene(SEED, N), SEED)
    return sc, _reference_psd(sc)


def _times(sc: Scene, k: int) -> Scene:
    """Every body's `A` in every state times 2^k (exact), the limits kept: the true x is the same."""
    def scaled(q: np.ndarray) -> np.ndarray:
        out = q.copy()
        out[:, 3:] = np.ldexp(q[:, 3:], k)
        return out

    return Scene(scaled(sc.q), scaled(sc.q_prev), scaled(sc.q_ref), sc.batches)


@pytest.mark.parametrize("k", [-332, -133, -66, 0, 66, 133, 332, -505, 505])
def test_psd_hessian_at_power_of_two_scales(k: int) -> None:
    """Both bodies' `A` times 2^k (~1e+-100, 1e+-40, 1e+-20; 2^-505: max|H| near 2^1015): the reference
    scaled by 4^-k, exactly (its input is scaled exactly). The issue's 1e40 answered 2.8e3 for 1.1e-76."""
    sc, want = _unscaled()
    _assert_psd_hessian(_core_psd(_times(sc, k)), np.ldexp(want, -2 * k))


def test_psd_hessian_beyond_float64_is_refused_naming_each_joint() -> None:
    """2^-532: the true Hessian is 2^1064 x the unscaled one (>= 1e-1 here): the overflow error on `strength`
    for every joint, no number."""
    sc, want = _unscaled()
    assert (np.abs(want).max(axis=(1, 2)) >= 0.1).all()
    with pytest.raises(InputError) as err:
        _core_psd(_times(sc, -532))
    assert sorted(f.loc for f in err.value.faults) == [("batches", 0, "strength", j) for j in range(N)]


def test_one_body_far_below_the_other_is_refused() -> None:
    """One body's `A` at 1e-300, the other's at 1: the Hessian in the small body's entries is ~1e600
    (the reference's rounds to inf); the overflow error, as for the exact Hessian."""
    sc = _limited(_pairs_scene(SEED + 1, 2, 1e-300, 1.0), SEED + 1)
    assert np.isinf(_reference_psd(sc)).any(axis=(1, 2)).all()
    for mode in ("psd", "exact"):
        with pytest.raises(InputError) as err:
            evaluate(**sc.core_args(hessian_mode=mode))
        assert sorted(f.loc for f in err.value.faults) == [("batches", 0, "strength", j) for j in range(2)]



F32_TOL = 5e-5
"""float32 against float64, normwise: the same algorithm after the polar factors (float64), so ~100 roundings
of u = 6e-8 as TOL argues for float64, ~6e-6; measured <= 4.2e-6 (the bug's 1.6e-2 ... 4e38)."""


@pytest.mark.parametrize("scale_i,scale_j", [(1e3, 1e3), (1e-3, 1e-3), (1e10, 1.0), (1.0, 1e-10), (1e20, 1e20)])
def test_float32_psd_hessian_past_its_own_threshold(scale_i: float, scale_j: float) -> None:
    """float32 rescales from hypot(cos, sin) beyond 2^+-16: both bodies at 1e3 already (`dtype=np.float32`)."""
    sc = _limited(_pairs_scene(SEED + 2, N, scale_i, scale_j), SEED + 2)
    want = _core_psd(sc)
    got = evaluate(**sc.core_args(hessian_mode="psd", dtype=np.float32)).batches[0].hessian
    assert got.dtype == np.float32
    for k in range(N):
        assert relerr(got[k], want[k]) <= F32_TOL, (k, relerr(got[k], want[k]))

# The issue's scales: both bodies at each, one body at 1e+-75, and bodies far apart (1e150 and 1e-150:
# |F|^2 / 4 near 1e300 beside r ~ 1; 1e160 and 1e-140: |F|^2 overflows, the Hessian ~1e280 does not).
ISSUE_SCALES = [(s, s) for s in (1e-100, 1e-40, 1e-20, 1.0, 1e20, 1e40, 1e100)] + [
    (1e75, 1.0), (1.0, 1e75), (1e-75, 1.0), (1.0, 1e-75), (1e150, 1e-150), (1e160, 1e-140), (1e-100, 1e200),
]


@pytest.mark.slow  # a fresh 50-digit reference per scale (~6 s)
@pytest.mark.parametrize("scale_i,scale_j", ISSUE_SCALES, ids=[f"{a:g}-{b:g}" for a, b in ISSUE_SCALES])
def test_psd_hessian_at_the_issues_scales(scale_i: float, scale_j: float) -> None:
    """Against the 50-digit reference of the scaled input itself (decimal factors round: no exact relation)."""
    seed = SEED + 10 + ISSUE_SCALES.index((scale_i, scale_j))
    sc = _limited(_pairs_scene(seed, 3, scale_i, scale_j), seed)
    _assert_psd_hessian(_core_psd(sc), _reference_psd(sc))
