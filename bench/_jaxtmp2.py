import faulthandler, sys
faulthandler.dump_traceback_later(150, exit=True)
import time, numpy as np
from bench.scenes import make_scene
from bench.peer_jax import JaxPeer
print("import ok", flush=True)
b, j = make_scene(int(sys.argv[1]), 0.1)
p = JaxPeer(b, j, same_work=False)
print("peer ok", flush=True)
t=time.time(); p("e"); print("e", time.time()-t, flush=True)
t=time.time(); p("egh"); print("egh", time.time()-t, flush=True)
p = JaxPeer(b, j, same_work=True)
t=time.time(); p("e"); print("e sw", time.time()-t, flush=True)
