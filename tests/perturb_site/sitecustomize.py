"""Under `pytest --perturb-ulps N` (tests/conftest.py puts this folder first on PYTHONPATH and sets JL_PERTURB_ULPS):
a Python process the tests start (a live server, the console script) computes with the same simulated kernels as
the test process (tests/perturb.py), as it would on the same machine."""

import os
import sys

if int(os.environ.get("JL_PERTURB_ULPS", "0") or 0) > 0:
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    from tests.perturb import perturbed

    _PERTURBED = perturbed(int(os.environ["JL_PERTURB_ULPS"]), int(os.environ.get("JL_PERTURB_SEED", "0")))
    _PERTURBED.__enter__()  # kept: a context manager collected would restore NumPy
    del sys.path[0]
