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
    g = _distance(x, lower, upper, above, below)
    side = np.subtract(above, below, dtype=np.float64)  # 1.0 - 0.0, 0.0 - 1.0 or 0.0 - 0.0
    return g, side


def _distance(x: Array, lower: Array, upper: Array, above: NDArray[np.bool_], below: NDArray[np.bool_]) -> Array:
    """`g` (N,): `x - upper` where `above`, else `lower - x` where `below`, else 0 (a NaN `x` too).

    Masked subtractions into zeros: the same numbers as nested `np.where`s, in a third of the time."""
    g = np.zeros(np.broadcast_shapes(np.shape(x), np.shape(lower), np.shape(upper)), dtype=np.result_type(x, lower, upper))
    np.subtract(lower, x, out=g, where=below)
    np.subtract(x, upper, out=g, where=above)
    return g


def width(lower: Array, upper: Array) -> Array:
    w = np.ones(np.broadcast_shapes(np.shape(lower), np.shape(upper)), dtype=np.result_type(lower, upper))
    np.subtract(upper, lower, out=w, where=upper > lower)
    return w


def energy(x: Array, lower: Array, upper: Array, strength: Array) -> Array:
    g = _distance(x, lower, upper, x > upper, x < lower)
    r = np.divide(g, width(lower, upper), out=g)
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
