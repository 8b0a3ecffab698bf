import time, numpy as np, sys
from bench.scenes import make_scene
from service.core import evaluate
frac = float(sys.argv[1]) if len(sys.argv) > 1 else 0.1
b, j = make_scene(100_000, frac)
modes = {"e": dict(outputs=("energy",)), "eg": dict(outputs=("energy","gradient")),
         "egh": dict(outputs=("energy","gradient","hessian")), "psd": dict(outputs=("energy","gradient","hessian"), hessian_mode="psd")}
for name, kw in modes.items():
    evaluate(b, j, **kw)
    ts = []
    for _ in range(5):
        t = time.perf_counter(); evaluate(b, j, **kw); ts.append(time.perf_counter() - t)
    print(name, f"{np.median(ts)*1e3:.1f} ms")
