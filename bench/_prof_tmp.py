import cProfile, pstats, sys
from bench.scenes import make_scene
from service.core import evaluate
b, j = make_scene(100_000, float(sys.argv[1]))
outs = sys.argv[2].split(",")
mode = sys.argv[3] if len(sys.argv) > 3 else "exact"
evaluate(b, j, outputs=outs, hessian_mode=mode)
cProfile.run("evaluate(b, j, outputs=outs, hessian_mode=mode)", "/tmp/prof")
pstats.Stats("/tmp/prof").sort_stats("tottime").print_stats(18)
