"""Another machine's math kernels, simulated: `pytest --perturb-ulps N` (tests/conftest.py) runs the tests with
NumPy's vectorisable transcendental ufuncs and its BLAS/LAPACK-backed calls replaced by versions whose results
differ from this machine's as another CPU's could.

Why: on a CPU with AVX-512 (AVX512_SKX and up) NumPy 2.x computes float64 `arctan2`, `cbrt`, `log2`, `exp`, `log`,
`power`, `arctan`, ... with Intel's SVML (numpy/_core/src/umath/loops_umath_fp.dispatch.c.src, the `8_ha` kernels;
loops_exponent_log.dispatch.c.src for exp/log), not glibc; and OpenBLAS picks its GEMM/LAPACK kernels by CPU
(`OPENBLAS_CORETYPE`), which sum in another order. This machine has no AVX-512; so here:

- each listed ufunc's finite nonzero results move by up to N ulps (`np.nextafter` steps away from or towards 0);
- `matmul` and `einsum` sum their products in the reverse order (a reassociated sum, as another kernel's; its
  error bound is the same `K u sum|a_i b_i|`, K the summed length, u = 2^-53);
- `linalg.eigh`/`eigvalsh`/`svd`/`solve` factor the matrix with its rows and columns (unknowns for `solve`) in
  the reverse order and map the factors back: the same answer, another elimination order's rounding, as another
  LAPACK's kernels would give (exact where any order is: a diagonal matrix stays exact); `linalg.norm(x)` of a
  whole array (a BLAS dot) sums in the reverse order.

Every move is a fixed function of the values (the ufuncs': a hash of the result's bits and the seed), never of a
call's order or position: like a real kernel, the same inputs give the same outputs, so two paths that compute the same thing stay
bitwise equal (and `X^T X` with equal terms stays symmetric), while the answers move off this machine's last bits.
`ndarray.__matmul__` (the `@` operator) and ndarray methods cannot be reached this way and are left as they are.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

import numpy as np

# The float64 ufuncs NumPy 2.4 sends to SVML on AVX512_SKX (loops_umath_fp.dispatch.c.src: 15 unary, `power`,
# `arctan2`; loops_exponent_log.dispatch.c.src: `exp`, `log`). sin/cos/tanh are listed too: their float64 loops
# are libm's today (loops_trigonometric.dispatch.cpp, "Disable SIMD code sin/cos f64") or NumPy's own SIMD
# polynomial (tanh, loops_hyperbolic), either of which may change with a NumPy release. hypot (libm), sqrt (IEEE
# exact), frexp/ldexp (exact) are not perturbed.
UFUNCS = (
    "arctan2", "cbrt", "log2", "exp", "log", "power", "exp2", "log10", "expm1", "log1p", "tan", "arcsin", "arccos",
    "arctan", "sinh", "cosh", "tanh", "arcsinh", "arccosh", "arctanh", "sin", "cos",
)
GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _hash(bits: np.ndarray, seed: int) -> np.ndarray:
    """A mixed uint64 per element of `bits` (splitmix64's finaliser, seeded)."""
    with np.errstate(over="ignore"):
        z = bits.astype(np.uint64) + np.uint64(seed) * GOLDEN
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def _bits(a: np.ndarray) -> np.ndarray:
    return a.view(np.uint64 if a.dtype.itemsize == 8 else np.uint32)


def ulp_steps(r: np.ndarray, n: int, seed: int) -> None:
    """Move the finite nonzero floats of `r` in place by a number of ulps in [-n, n], a function of |r|'s bits:
    -x moves as x does, towards or away from 0 (a kernel keeps atan2's oddness)."""
    if n <= 0 or r.dtype.kind != "f" or r.size == 0:
        return
    mag = np.abs(r)
    steps = (_hash(_bits(np.ascontiguousarray(mag)), seed) % np.uint64(2 * n + 1)).astype(np.int64) - n
    steps[~(np.isfinite(r) & (r != 0))] = 0
    out = mag
    for k in range(n):
        up, down = steps > k, steps < -k
        if not (up.any() or down.any()):
            break
        out = np.where(up, np.nextafter(out, np.inf), np.where(down, np.nextafter(out, 0), out))
    r[...] = np.copysign(out, r)


def _as_array(r):  # noqa: ANN001, ANN202 (ufunc results: an array or a NumPy scalar)
    return r if isinstance(r, np.ndarray) else np.array(r)


def _back(r, a: np.ndarray):  # noqa: ANN001, ANN202
    return a if isinstance(r, np.ndarray) else a[()]


class _Ufunc:
    """A ufunc's stand-in: calls perturbed, its attributes (`nin`, `reduce`, ...) the ufunc's own."""

    def __init__(self, orig: np.ufunc, call: Callable) -> None:
        self._orig, self._call, self.__name__, self.__doc__ = orig, call, orig.__name__, orig.__doc__

    def __call__(self, *args, **kwargs):  # noqa: ANN002, ANN003, ANN204
        return self._call(*args, **kwargs)

    def __getattr__(self, name: str):  # noqa: ANN204
        return getattr(self._orig, name)


def _ufunc(orig: np.ufunc, n: int, seed: int) -> Callable:
    def wrapped(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        r = orig(*args, **kwargs)
        if isinstance(r, tuple):
            return r
        a = _as_array(r)
        if a.dtype.kind == "f":
            where = kwargs.get("where", True)
            before = a.copy() if where is not True else None
            ulp_steps(a, n, seed)
            if before is not None:  # only the written elements
                np.copyto(a, before, where=~np.asarray(where, dtype=bool))
        return _back(r, a)

    return _Ufunc(orig, wrapped)


def _matmul(orig: np.ufunc) -> Callable:
    """`a @ b` summed over k in the reverse order: the same products, another association (any BLAS kernel's
    order is as good as another's; X^T X stays bitwise symmetric, its entries summing equal terms alike)."""

    def wrapped(a, b, /, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        A, B = np.asarray(a), np.asarray(b)
        if A.ndim < 2 or B.ndim < 2 or A.shape[-1] < 3 or "f" not in (A.dtype.kind, B.dtype.kind):
            return orig(a, b, *args, **kwargs)
        return orig(np.ascontiguousarray(A[..., ::-1]), np.ascontiguousarray(B[..., ::-1, :]), *args, **kwargs)

    return _Ufunc(orig, wrapped)


def _einsum(orig: Callable) -> Callable:
    """`einsum` with every operand reversed along its summed indices: the same terms, added in another order."""

    def wrapped(*operands, **kwargs):  # noqa: ANN002, ANN003, ANN202
        if not isinstance(operands[0], str) or "->" not in operands[0] or "." in operands[0]:
            return orig(*operands, **kwargs)  # the sublist form, ellipses, implicit output: not used here
        spec, arrays = operands[0].replace(" ", ""), [np.asarray(o) for o in operands[1:]]
        ins, out = spec.split("->")
        summed = set(ins) - set(out) - {","}
        flipped = [
            np.flip(a, axis=tuple(k for k, c in enumerate(term) if c in summed)) if a.dtype.kind == "f" else a
            for term, a in zip(ins.split(","), arrays, strict=True)
        ]
        return orig(spec, *flipped, **kwargs)

    return wrapped


def _eigh(orig: Callable) -> Callable:
    """`eigh` of P A P^T (P reverses the order): the same eigenpairs, another reduction order's rounding (and
    perhaps other signs of the eigenvectors, as another LAPACK's)."""

    @functools.wraps(orig)
    def wrapped(a, UPLO="L"):  # noqa: ANN001, ANN202, N803
        A = np.asarray(a)
        low = np.tril(A) if UPLO.upper() == "L" else np.swapaxes(np.triu(A), -1, -2)  # the triangle eigh reads
        full = low + np.swapaxes(np.tril(low, -1), -1, -2)
        r = orig(np.ascontiguousarray(full[..., ::-1, ::-1]), "L")
        if isinstance(r, np.ndarray):  # eigvalsh
            return r
        return type(r)(r[0], np.ascontiguousarray(r[1][..., ::-1, :]))

    return wrapped


def _svd(orig: Callable) -> Callable:
    """`svd` of the matrix with rows and columns reversed, its factors mapped back: U Vt, the polar factor, is
    the same up to rounding."""

    @functools.wraps(orig)
    def wrapped(a, full_matrices=True, compute_uv=True, hermitian=False):  # noqa: ANN001, ANN202, FBT002
        if not compute_uv or hermitian:
            return orig(a, full_matrices, compute_uv, hermitian)
        A = np.asarray(a)
        r = orig(np.ascontiguousarray(A[..., ::-1, ::-1]), full_matrices, compute_uv, hermitian)
        U, S, Vt = r
        return type(r)(np.ascontiguousarray(U[..., ::-1, :]), S, np.ascontiguousarray(Vt[..., :, ::-1]))

    return wrapped


def _solve(orig: Callable) -> Callable:
    """`solve` with the unknowns in the reverse order: another elimination order (exact where it is exact)."""

    @functools.wraps(orig)
    def wrapped(a, b):  # noqa: ANN001, ANN202
        A, B = np.asarray(a), np.asarray(b)
        y = orig(np.ascontiguousarray(A[..., :, ::-1]), B)
        return np.flip(y, axis=0 if B.ndim == 1 else -2).copy()

    return wrapped


def _norm(orig: Callable) -> Callable:
    """Only `norm(x)` of the whole array is BLAS's (`x.dot(x)`, numpy/linalg/_linalg.py); with `axis` or `ord`
    it is `add.reduce`, whose order is NumPy's own on every machine. That dot, summed in the reverse order."""

    @functools.wraps(orig)
    def wrapped(x, ord=None, axis=None, keepdims=False):  # noqa: A002, ANN001, ANN202, FBT002
        X = np.asarray(x)
        if axis is not None or ord not in (None, "fro") or keepdims or X.dtype.kind != "f" or X.size < 3:
            return orig(x, ord, axis, keepdims)
        flat = np.ascontiguousarray(X.ravel()[::-1])
        return np.sqrt(flat.dot(flat))

    return wrapped


_LINALG = ("eigh", "eigvalsh", "svd", "solve", "norm")
ORIGINALS = {**{name: getattr(np, name) for name in (*UFUNCS, "matmul", "einsum")},
             **{f"linalg.{name}": getattr(np.linalg, name) for name in _LINALG}}
"""NumPy's own, taken when this module is first imported (before any replacement): a second installation (pytest's,
in a process whose sitecustomize installed one) replaces the first rather than perturbing its results again."""


def replacements(n: int, seed: int = 0) -> Iterator[tuple[object, str, Callable]]:
    """(owner, attribute, replacement) for every call perturbed at `n` ulps (`JL_PERTURB_ONLY`, a comma list of
    these names, keeps only those: to find which one moves a failing test)."""
    o = ORIGINALS
    for name in UFUNCS:
        yield np, name, _ufunc(o[name], n, seed)
    yield np, "matmul", _matmul(o["matmul"])
    yield np, "einsum", _einsum(o["einsum"])
    yield np.linalg, "eigh", _eigh(o["linalg.eigh"])
    yield np.linalg, "eigvalsh", _eigh(o["linalg.eigvalsh"])
    yield np.linalg, "svd", _svd(o["linalg.svd"])
    yield np.linalg, "solve", _solve(o["linalg.solve"])
    yield np.linalg, "norm", _norm(o["linalg.norm"])


@contextmanager
def perturbed(n: int, seed: int = 0) -> Iterator[None]:
    """Within: NumPy's attributes replaced as above (every module calling `np.arctan2` etc. sees them)."""
    only = os.environ.get("JL_PERTURB_ONLY")
    with _installed((o, name, fn) for o, name, fn in replacements(n, seed) if not only or name in only.split(",")):
        yield


@contextmanager
def plain() -> Iterator[None]:
    """Within: NumPy's own functions, whatever is installed outside (the harness' tests' baselines)."""
    owners = ((np.linalg, key[7:]) if key.startswith("linalg.") else (np, key) for key in ORIGINALS)
    with _installed((owner, name, fn) for (owner, name), fn in zip(owners, ORIGINALS.values(), strict=True)):
        yield


@contextmanager
def _installed(replaced: Iterable[tuple[object, str, Callable]]) -> Iterator[None]:
    """Within: each `owner.name` set to its replacement; afterwards, what each was before, in reverse order."""
    saved = []
    try:
        for owner, name, fn in replaced:
            saved.append((owner, name, getattr(owner, name)))
            setattr(owner, name, fn)
        yield
    finally:
        for owner, name, fn in reversed(saved):
            setattr(owner, name, fn)
