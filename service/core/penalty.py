"""The cubic limit penalty of every joint-limit constitution: `E(x) = s (g / w)^3`, with `g = x - u` above the
range, `l - x` below it, 0 inside, and `w = u - l`, or 1 for a degenerate range (u == l: `s |x - l|^3`).

`g / w` is finite wherever the true ratio is: where `u - l` or `x - u` overflows float64 both are taken from
halves (`_relative`), never `5e307 / inf = 0`. Where a step of the plain products (`r^3`, `s / w`, `s / w^2`)
leaves the normal range while the result need not (`1e-300 (1e110)^3 = 1e30`), those joints' E, E', E'' are formed
from the exponents of s, r, w (`_parts`), within a few ulps of the true value. An energy or derivative beyond
float64 is inf, which the core reports as a 422 naming the joint. Boundary points are in range. All arrays are (N,).
"""

from __future__ import annotations

from functools import cache

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
    already taken), and whether either overflowed or some `r^3` left the normal range (then `derivatives`, from
    halves and exponents, not `slopes`)."""
    r, w, (wide, _) = _relative(g, x, lower, upper, w)
    E, odd = _cube(r, x, lower, upper, strength)
    return E, r, w, bool(wide.size) or odd


def _cube(r: Array, x: Array, lower: Array, upper: Array, strength: Array) -> tuple[Array, bool]:
    """`s r^3` (N,) and whether the cube of some `r > 0` is not normal (`_limits`): E is formed from exponents
    there. Three passes and two counts when none is."""
    c = r * r * r
    E = strength * c
    out = _outside(c, CUBE)
    if np.count_nonzero(out) == r.size - np.count_nonzero(r):  # the zeros of r alone (inside their range)
        return E, False
    rows = (out & (r > 0)).nonzero()[0]
    _, (ms, es), (mr, er), _ = _parts(*(np.broadcast_to(a, E.shape)[rows] for a in (x, lower, upper, strength)))
    E[rows] = np.ldexp(ms * (mr * mr * mr), es + 3 * er)
    return E, True


CUBE, SLOPE, CURVE = range(3)  # `_limits`' windows
Window = tuple[np.unsignedinteger, np.unsignedinteger]


@cache
def _limits(dtype: np.dtype) -> tuple[Window, Window, Window]:
    """The windows (`_outside`) of the plain products' checks: `r^3` in [tiny, 2^1023) (float64) keeps r, r^2 and
    r^3 normal (r < 2^341); then `|E'|` in [2^-338, 2^1000) and `E''` in [2^-678, 2^1000) only if `s / w` and
    `s / w^2` were normal (3 tiny (2^341)^2 < 2^-338, 6 tiny 2^341 < 2^-678); larger ones are scaled down
    (`scale_up`), as the Hessian's factors take them."""
    f = finfo(dtype)
    e, hi = (f.maxexp - 1) // 3, 2.0 ** (f.maxexp - 24)
    bounds = (f.tiny, 2.0 ** (3 * e)), (2.0 ** (f.minexp + 2 * e + 2), hi), (2.0 ** (f.minexp + e + 3), hi)
    bits = lambda v: np.array(v, dtype).view(f"u{dtype.itemsize}")[()]  # noqa: E731
    return tuple((bits(lo), bits(hi) - bits(lo)) for lo, hi in bounds)


def _outside(a: Array, window: int) -> NDArray[np.bool_]:
    """`~(lo <= a < hi)` of `a >= +0` (N,), NaN outside too, for `_limits(a.dtype)[window]` = `(bits(lo),
    bits(hi) - bits(lo))`: read as unsigned integers, the bits of such floats keep their order, and below `lo`
    the difference wraps."""
    base, span = _limits(a.dtype)[window]
    return (a.view(base.dtype) - base) >= span


def slopes(r: Array, w: Array, side: Array, strength: Array) -> tuple[Array, Array]:
    """`derivatives`' plain `dE/dx`, `d2E/dx2` from the `r`, `w` that `energy_and_relative` took where it flagged
    nothing and `gap`'s side: the very operations, so the very bits (`scale_up` forms those out of range again)."""
    sw = strength / w
    sww = sw / w
    return side * 3.0 * sw * (r * r), 6.0 * sww * r


def derivatives(x: Array, lower: Array, upper: Array, strength: Array) -> tuple[Array, Array, Array]:
    """`(E, dE/dx, d2E/dx2)`, each (N,): the plain products, formed from exponents where one left the normal
    range (`_cube`, `scale_up` without a shift)."""
    g, side = gap(x, lower, upper)
    r, w, (wide, half_w) = _relative(g, x, lower, upper)
    sw = strength / w
    sww = sw / w
    if wide.size:  # w overflowed there: s / w = (s / 2) / (w / 2), s / w^2 = (s / w / 2) / (w / 2)
        s = np.broadcast_to(strength, r.shape)[wide]
        sw[wide] = (s * 0.5) / half_w
        sww[wide] = (sw[wide] * 0.5) / half_w
    dE, d2E = side * 3.0 * sw * (r * r), 6.0 * sww * r
    scale_up(dE, d2E, x, lower, upper, strength, r, lift=False)
    return _cube(r, x, lower, upper, strength)[0], dE, d2E


def scale_up(dE: Array, d2E: Array, x: Array, lower: Array, upper: Array, strength: Array, r: Array | None = None,
             lift: bool = True) -> NDArray[np.int_] | None:
    """Exponents `k` (N,), with `dE`, `d2E` (`derivatives` or `slopes` of joints outside their range) formed again
    from exponents, in place, as `2^k E'`, `2^k E''` where a plain product may have left the normal range: outside
    [dE_lo, hi), [d2E_lo, hi) (`_limits`), or, given `r` (their `g / w`), where `r^3` is not normal. k = 0 where
    both are in [2^(minexp + 22), 2^(maxexp - 24)] ([2^-1000, 2^1000] in float64), else the shift that brings both
    in (`lift` False: 0, so E', E'' themselves: subnormal, 0 or inf where they are); None where no joint is.

    E'' alone underflows where the Hessian's `E'' dx dx^T` need not (1e300 outside a range 1e300 wide: E'' ~
    1e-600; with a frame of 1e150 the term is ~1e-300), and E' overflows where `E' J^T dx` need not. So 2^k E',
    2^k E'' are formed from the exponents of s, g and w (k the least that brings both into that range: their
    exponents are at most ~1100 apart, E''/E' = 2/g), and the caller scales the derivatives back by 2^-k.
    """
    dtype = d2E.dtype  # the products' own (float32 ones give a float64 dE: `gap`'s side is float64)
    bad = _outside(np.abs(dE).astype(dtype, copy=False), SLOPE) | _outside(d2E, CURVE)
    if r is not None:
        bad |= _outside(r * r * r, CUBE)
    rows = bad.nonzero()[0]
    if rows.shape[0] == 0:
        return None
    at = (np.broadcast_to(v, dE.shape)[rows] for v in (x, lower, upper, strength))
    side, (ms, es), (mr, er), (mw, ew) = _parts(*at)
    e2, e1 = es + er - 2 * ew, es + 2 * er - ew  # E'' = 6 s r / w^2, |E'| = 3 s r^2 / w: mantissas in [3/8, 48)
    f = finfo(dtype)
    low, high = f.minexp + 22, f.maxexp - 24
    k = np.zeros_like(e1)
    if lift:
        k = np.maximum(0, low - np.minimum(e1, e2)) + np.minimum(0, high - 6 - np.maximum(e1, e2))
    d2E[rows] = np.ldexp(6.0 * ms * mr / (mw * mw), e2 + k)
    dE[rows] = np.ldexp(side * 3.0 * ms * mr * mr / mw, e1 + k)
    shift = np.zeros(dE.shape[0], dtype=np.int32)
    shift[rows] = k
    return shift


def _parts(x: Array, lower: Array, upper: Array, strength: Array) -> tuple[Array, tuple[Array, Array], ...]:
    """`(side, (ms, es), (mr, er), (mw, ew))` (each (R,)): `gap`'s side and mantissas and exponents of s, r = g / w
    and w (`np.frexp`'s, but mr in (1/2, 2)), so that every product of them stays in range before one `np.ldexp`."""
    above, below = x > upper, x < lower
    g = _distance(x, lower, upper, above, below)
    r, w, (wide, half_w) = _relative(g, x, lower, upper)
    (mg, eg), (mw, ew), (ms, es) = np.frexp(g), np.frexp(w), np.frexp(strength)
    mr, er = mg / mw, eg - ew  # r = mr 2^er from g and w themselves: r alone may be subnormal
    if wide.shape[0]:  # g or w overflowed: r from their halves (normal: g >= ulp(u) there), w = 2 (w / 2)
        mr[wide], er[wide] = np.frexp(r[wide])
        mw[wide], ew[wide] = np.frexp(half_w)
        ew[wide] += 1
    return above.astype(x.dtype) - below, (ms, es), (mr, er), (mw, ew)


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
