"""The cubic limit penalty shared by every joint-limit constitution.

    E(x) = s (g / w)^3,   g = x - u above the range, l - x below it, 0 inside,
    w = u - l, or 1 for a degenerate range (u == l: the fallback s |x - l|^3).

Boundary points are in range. All arrays are (N,).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def gap(x: Array, lower: Array, upper: Array) -> tuple[Array, Array]:
    """Distance outside the range and the side: `(g >= 0, side in {-1, 0, +1})`."""
    above = x > upper
    below = x < lower
    side = above.astype(np.float64) - below.astype(np.float64)
    return _distance(x, lower, upper, above, below), side


def _distance(x: Array, lower: Array, upper: Array, above: NDArray[np.bool_], below: NDArray[np.bool_]) -> Array:
    """`gap`'s g (N,) from its sides `above` (x > upper) and `below` (x < lower): `x - upper` where
    above, else `lower - x` where below, else +0 (a NaN `x` too).

    The very bits `np.where` would select, blended with integer masks: `np.where` branches per element
    and mispredicts on the random sides of a scene with every joint out of range (3x slower there).
    """
    a, b = np.asarray(np.subtract(x, upper)), np.asarray(np.subtract(lower, x))
    if a.dtype.kind != "f" or b.dtype != a.dtype:
        return np.where(above, a, np.where(below, b, 0.0))
    bits = np.dtype(f"i{a.dtype.itemsize}")
    take_a = np.negative(above, dtype=bits)  # all ones where above, else 0
    take_b = np.negative(below & ~above, dtype=bits)
    g = np.bitwise_and(a.view(bits), take_a, out=a.view(bits))
    g |= np.bitwise_and(b.view(bits), take_b, out=b.view(bits))
    return a


def width(lower: Array, upper: Array) -> Array:
    return np.where(upper > lower, upper - lower, 1.0)


def distance(x: Array, lower: Array, upper: Array) -> Array:
    """`gap`'s g (N,) alone (the side is not needed): `x - upper` above, `lower - x` below, else +0."""
    return _distance(x, lower, upper, x > upper, x < lower)


def energy(x: Array, lower: Array, upper: Array, strength: Array) -> Array:
    return energy_of_gap(distance(x, lower, upper), lower, upper, strength)


def energy_of_gap(g: Array, lower: Array, upper: Array, strength: Array) -> Array:
    """`s (g / w)^3` (N,) of the gaps `g` (N,) (`distance`)."""
    r = g / width(lower, upper)
    return strength * (r * r * r)


def derivatives(
    x: Array, lower: Array, upper: Array, strength: Array
) -> tuple[Array, Array, Array]:
    """`(E, dE/dx, d2E/dx2)`, each (N,)."""
    g, side = gap(x, lower, upper)
    w = width(lower, upper)
    r = g / w
    sw = strength / w
    return strength * (r * r * r), side * 3.0 * sw * (r * r), 6.0 * (sw / w) * r
