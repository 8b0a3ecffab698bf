import time, numpy as np, sys
from bench.scenes import make_scene
from bench.peer_jax import JaxPeer
from service.core import evaluate
b, j = make_scene(100_000, 0.1)
for sw in (True, False):
    for psd in (False, True):
        p = JaxPeer(b, j, same_work=sw, psd=psd)
        for mode in (("e", "eg", "egh") if not psd else ("egh",)):
            p(mode)
            ts = []
            for _ in range(5):
                t = time.perf_counter(); p(mode); ts.append(time.perf_counter() - t)
            print("same_work" if sw else "pre", "psd" if psd else "", mode, f"{np.median(ts)*1e3:.1f} ms")
# correctness quick
b, j = make_scene(200, 0.5)
p = JaxPeer(b, j, same_work=True)
ev = evaluate(b, j)
out = p("egh")
for r, (e, g, h) in zip(ev.batches, out):
    print(np.abs(r.energy - e).max()/np.abs(e).max(), np.abs(r.gradient-g).max()/np.abs(g).max(), np.abs(r.hessian-h).max()/np.abs(h).max())
p = JaxPeer(b, j, same_work=True, psd=True)
ev = evaluate(b, j, hessian_mode="psd")
out = p("egh")
for r, (e, g, h) in zip(ev.batches, out):
    print(np.abs(r.hessian-h).max()/np.abs(h).max())
