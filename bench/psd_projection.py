"""`python -m bench.psd_projection`: the prismatic psd projection alone, v1's 12-quantity form (as it was
before contract v1.2) against v1.2's 9-quantity form (`Prismatic.projected_curvature`), calls alternated."""

from __future__ import annotations

import argparse

import numpy as np

from bench.ab import medians, pairs
from jointlimits.service.core.constitution import Curvature
from jointlimits.service.core.heap import keep_heap
from jointlimits.service.core.prismatic import _D, _S, PRISMATIC

_U_PLUS, _U_MINUS = 0.5 * (_D + _S), 0.5 * (_D - _S)


def v1_projection(dE: np.ndarray, curvature: Curvature) -> Curvature:
    """v1's projection, as the core had it: `|E'| u u^T` in the 12 quantities, K formed."""
    u = np.where((dE >= 0)[:, None], _U_PLUS, _U_MINUS)
    kron = np.abs(dE)[:, None, None] * (u[:, :, None] * u[:, None, :])
    n = dE.shape[0]
    return Curvature(kron=kron, basis=curvature.basis, coef=np.zeros((n, 1, 1), dE.dtype), dx_coef=curvature.dx_coef,
                     kron_factors=(np.abs(dE)[:, None], u[:, None]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.psd_projection", description=__doc__.split("\n\n")[0])
    ap.add_argument("--joints", type=int, default=50_000, help="joints (default 5e4, the bench's #669 half at 1e5)")
    ap.add_argument("--pairs", type=int, default=41, help="alternated pairs (default 41)")
    args = ap.parse_args(argv)
    keep_heap()
    rng = np.random.default_rng(0)
    F, dE = rng.normal(size=(args.joints, 4, 3)), rng.normal(size=args.joints)
    _, curvature = PRISMATIC.derivatives(F, True)
    t_new, t_old = pairs(lambda: PRISMATIC.projected_curvature(dE, curvature), lambda: v1_projection(dE, curvature),
                         args.pairs)
    a, b, wins = medians(t_new, t_old)
    print(f"projection alone, {args.joints} joints: v1.2 {a * 1e3:.2f} ms, v1 {b * 1e3:.2f} ms, ratio {a / b:.3f}, "
          f"v1.2 faster in {wins} of {args.pairs}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
