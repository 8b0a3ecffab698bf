"""`python -m bench.psd_projection`: the prismatic psd projection alone, the v1 12-quantity form (as in 20f13e8) against v1.2's 9-quantity form, 5e4 joints, calls alternated."""
import time, numpy as np
from service.core.constitution import Curvature
from service.core.prismatic import PRISMATIC, _D, _S
from service.core.heap import keep_heap
keep_heap()
_U_PLUS, _U_MINUS = 0.5 * (_D + _S), 0.5 * (_D - _S)
def old(dE, curvature):
    u = np.where((dE >= 0)[:, None], _U_PLUS, _U_MINUS)
    kron = np.abs(dE)[:, None, None] * (u[:, :, None] * u[:, None, :])
    n = dE.shape[0]
    return Curvature(kron=kron, basis=curvature.basis, coef=np.zeros((n, 1, 1), dE.dtype), dx_coef=curvature.dx_coef,
                     kron_factors=(np.abs(dE)[:, None], u[:, None]))
rng = np.random.default_rng(0); n = 50_000
F = rng.normal(size=(n, 4, 3)); dE = rng.normal(size=n)
_, cv = PRISMATIC.derivatives(F, True)
t_new, t_old = [], []
for i in range(41):
    for fn, out in ((PRISMATIC.projected_curvature, t_new), (old, t_old))[:: 1 if i % 2 else -1]:
        t = time.perf_counter(); fn(dE, cv); out.append(time.perf_counter() - t)
a, b = np.median(t_new), np.median(t_old)
print(f"projection alone, 5e4 joints: v1.2 {a*1e3:.2f} ms, v1 {b*1e3:.2f} ms, ratio {a/b:.3f}, v1.2 faster in {sum(x<y for x,y in zip(t_new,t_old))} of 41")
