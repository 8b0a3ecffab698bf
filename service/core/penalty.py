"""The cubic limit penalty of every joint-limit constitution: `E(x) = s (g / w)^3`, with `g = x - u` above the
range, `l - x` below it, 0 inside, and `w = u - l`, or 1 for a degenerate range (u == l: `s |x - l|^3`).

`g / w` is finite wherever the true ratio is: where `u - l` or `x - u` overflows float64 both are taken from
halves (`_relative`), never `5e307 / inf = 0`. An energy or derivative beyond float64 is inf, which the core
reports as a 422 naming the joint. Boundary points are in range. All arrays are (N,).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from jointlimits.service.core.kinematics import finfo

Array = NDArray[np.float64]


def gap(x: Array, lower: Array, upper: Array) -> tuple[Array, Array]:
    """Distance outside the range and the side: `(g >= 0, side in {-1, 0, +1})`."""
    above = x > upper
    below = x < lower
    side = above.astype(np.float64) - below.astype(np.float64)
    return _distance(x, lower, upper, above, below), side


def _distance(x: Array, lower: Array, upper: Array, above: NDArray[np.bool_], below: NDArray[np.bool_]) -> Array:
    """`gap`'s g (N,) from its sides `above` (x > upper) and `below` (x < lower): `x - upper` where above, else
    `lower - x` where below, else +0 (a NaN `x` too). The very bits `np.where` would select, blended with integer
    masks: `np.where` branches per element and mispredicts on random sides (3x slower with every joint out)."""
    a, b = np.asarray(np.subtract(x, upper)), np.asarray(np.subtract(lower, x))
    if a.dtype.kind != "f" or b.dtype != a.dtype or a.size <= 256:  # a few joints: two calls, not eight
        return np.where(above, a, np.where(below, b, 0.0))
    bits = np.dtype(f"i{a.dtype.itemsize}")
    take_a = np.negative(above, dtype=bits)  # all ones where above, else 0
    take_b = np.negative(below & ~above, dtype=bits)
    g = np.bitwise_and(a.view(bits), take_a, out=a.view(bits))
    g |= np.bitwise_and(b.view(bits), take_b, out=b.view(bits))
    return a


def distance(x: Array, lower: Array, upper: Array) -> Array:
    """`gap`'s g (N,) alone (the side is not needed): `x - upper` above, `lower - x` below, else +0."""
    return _distance(x, lower, upper, x > upper, x < lower)


def energy(x: Array, lower: Array, upper: Array, strength: Array) -> Array:
    return energy_and_relative(distance(x, lower, upper), x, lower, upper, strength)[0]


def energy_and_relative(g: Array, x: Array, lower: Array, upper: Array, strength: Array,
                        w: Array | None = None) -> tuple[Array, Array, Array, bool]:
    """`s (g / w)^3` of the gaps `g` (`distance`) of `x`, with the relative gap `g / w`, the width `w` (`width`, if
    already taken), and whether either overflowed somewhere (then `derivatives`, from halves, not `slopes`)."""
    r, w, (wide, _) = _relative(g, x, lower, upper, w)
    return strength * (r * r * r), r, w, bool(wide.size)


def slopes(r: Array, w: Array, side: Array, strength: Array) -> tuple[Array, Array]:
    """`derivatives`' `dE/dx`, `d2E/dx2` from the `r`, `w` that `energy_and_relative` took where nothing
    overflowed and `gap`'s side: the very operations, so the very bits."""
    sw = strength / w
    sww = sw / w
    return side * 3.0 * sw * (r * r), 6.0 * sww * r


def derivatives(x: Array, lower: Array, upper: Array, strength: Array) -> tuple[Array, Array, Array]:
    """`(E, dE/dx, d2E/dx2)`, each (N,)."""
    g, side = gap(x, lower, upper)
    r, w, (wide, half_w) = _relative(g, x, lower, upper)
    sw = strength / w
    sww = sw / w
    if wide.size:  # w overflowed there: s / w = (s / 2) / (w / 2), s / w^2 = (s / w / 2) / (w / 2)
        s = np.broadcast_to(strength, r.shape)[wide]
        sw[wide] = (s * 0.5) / half_w
        sww[wide] = (sw[wide] * 0.5) / half_w
    return strength * (r * r * r), side * 3.0 * sw * (r * r), 6.0 * sww * r


def scale_up(dE: Array, d2E: Array, x: Array, lower: Array, upper: Array, strength: Array) -> NDArray[np.int_] | None:
    """Exponents `k >= 0` (N,), with `dE`, `d2E` (`derivatives` of joints outside their range) replaced in place
    by `2^k E'`, `2^k E''` where either is below `2^(minexp + 22)` (2^-1000 in float64); None where no joint is.

    E'' alone underflows where the Hessian's `E'' dx dx^T` need not (1e300 outside a range 1e300 wide: E'' ~
    1e-600; with a frame of 1e150 the term is ~1e-300). So 2^k E', 2^k E'' are formed from the exponents of s,
    g and w (k the least that lifts the smaller), and the caller scales the derivatives back by 2^-k.
    """
    target = finfo(dE.dtype).minexp + 22
    rows = ((np.abs(dE) < 2.0**target) | (d2E < 2.0**target)).nonzero()[0]
    if rows.shape[0] == 0:
        return None
    xs, lo, up, s = (np.broadcast_to(a, dE.shape)[rows] for a in (x, lower, upper, strength))
    above, below = xs > up, xs < lo
    g = _distance(xs, lo, up, above, below)
    r, w, (wide, half_w) = _relative(g, xs, lo, up)
    (mg, eg), (mw, ew), (ms, es) = np.frexp(g), np.frexp(w), np.frexp(s)
    mr, er = mg / mw, eg - ew  # r = mr 2^er from g and w themselves: r alone may be subnormal
    if wide.shape[0]:  # g or w overflowed: r from their halves (normal: g >= ulp(u) there), w = 2 (w / 2)
        mr[wide], er[wide] = np.frexp(r[wide])
        mw[wide], ew[wide] = np.frexp(half_w)
        ew[wide] += 1
    e2, e1 = es + er - 2 * ew, es + 2 * er - ew  # E'' = 6 s r / w^2, |E'| = 3 s r^2 / w: mantissas in [3/8, 48)
    k = np.maximum(0, target - np.minimum(e1, e2))
    d2E[rows] = np.ldexp(6.0 * ms * mr / (mw * mw), e2 + k)
    dE[rows] = np.ldexp((above.astype(dE.dtype) - below) * 3.0 * ms * mr * mr / mw, e1 + k)
    shift = np.zeros(dE.shape[0], dtype=np.int32)
    shift[rows] = k
    return shift


def width(lower: Array, upper: Array) -> Array:
    """`w` (N,): `upper - lower`, or 1 for a degenerate range (it does not depend on `x`: a prepared scene keeps it)."""
    return np.where(upper > lower, upper - lower, 1.0)


def _relative(g: Array, x: Array, lower: Array, upper: Array,
              w: Array | None = None) -> tuple[Array, Array, tuple[NDArray[np.intp], Array]]:
    """`(g / w, w, (wide, w / 2 at wide))` of the gaps `g`: the relative gap, the width and the joints `wide`
    where `g` or `w` overflowed from finite inputs, there from halves (exact for such magnitudes: 1.5e308 against
    [-1e308, 1e308] is 0.25, not 5e307 / inf = 0). Every other joint keeps the plain quotient's bits.
    """
    w = width(lower, upper) if w is None else w
    r = np.asarray(g / w)
    # The usual case: two reductions, no temporaries (g >= 0 and w > 0 are never NaN: only +inf can be there).
    wide = np.zeros(0, dtype=np.intp)
    if g.size and not (g.max() < np.inf and w.max() < np.inf):  # overflowed differences of finite inputs
        wide = np.flatnonzero((np.isinf(g) | np.isinf(w)) & np.isfinite(x) & np.isfinite(lower) & np.isfinite(upper))
    if not wide.size:
        return r, w, (wide, w[:0])
    x_w, l_w, u_w = (np.asarray(a)[wide] for a in (x, lower, upper))
    xs, ls, us = x_w * 0.5, l_w * 0.5, u_w * 0.5
    ab, be = x_w > u_w, x_w < l_w  # the sides from the inputs themselves
    half_g = np.where(ab, xs - us, np.where(be, ls - xs, 0.0))
    half_w = np.where(us > ls, us - ls, 0.5).astype(w.dtype, copy=False)
    r[wide] = half_g / half_w  # a ratio beyond float64 stays inf: the core's overflow check names the joint
    return r, w, (wide, half_w)
