"""Recorded v1 answers, to pin that v1 requests keep their numbers across core changes.

`python -m tests.v1_answers` rewrites `tests/v1_answers.npz` from the current core: run it only on
a core whose v1 numbers are the reference, and say why in the commit. What is kept per case and
batch: `index`, `x` and `energy` whole, `gradient` and `hessian` on every `SAMPLE`-th row (the two
synthetic scenes' Hessians in full would be 12 MB).

History: until issue 27 these were sha256 digests of every bit of the answers, recorded on one
CPU. Last bits are not the same on another: OpenBLAS and NumPy pick kernels by CPU, and a
reassociated sum rounds differently (`OPENBLAS_CORETYPE=Sandybridge` against this project's AMD
EPYC moved x by 4.1e-15, the energy by 2.5e-15, gradient and Hessian by 1.2e-15 of each array's
largest entry). The answers are now compared to `TOLERANCE` (tests/core/test_v1_answers.py argues it).
Recorded at commit 4be56b1 (the core whose digests they replace, on an AMD EPYC).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from bench.scenes import make_scene
from jointlimits.service.core import Bodies, Evaluation, Joints, evaluate
import orjson

from jointlimits.service.http.convert import read

PATH = Path(__file__).with_name("v1_answers.npz")
GOLDEN = json.loads(Path(__file__).with_name("golden_cases.json").read_text())["cases"]
WHOLE = ("index", "x", "energy")
SAMPLED = ("gradient", "hessian")
SAMPLE = 16
"""Every 16th row of a batch's gradient and Hessian is kept (the golden cases' batches are shorter: all of row 0)."""


def cases() -> Iterator[tuple[str, Bodies, list[Joints], dict]]:
    """(name, bodies, batches, options): the golden cases in both Hessian modes, with and without
    active_only, and two synthetic scenes (both constitutions, a tenth of the joints outside)."""
    for c in GOLDEN:
        args = read(orjson.dumps(c["request"]))
        for mode in ("exact", "psd"):
            for active_only in (False, True):
                yield (
                    f"{c['name']}/{mode}/{active_only}",
                    args["bodies"],
                    args["batches"],
                    dict(hessian_mode=mode, active_only=active_only),
                )
    for n, seed in ((1000, 1), (257, 2)):
        bodies, batches = make_scene(n, outside=0.1, seed=seed)
        for mode in ("exact", "psd"):
            yield f"scene{n}/{mode}", bodies, batches, dict(hessian_mode=mode)


def kept(name: str, ev: Evaluation) -> dict[str, np.ndarray]:
    """The arrays of `ev` that are recorded, keyed `name|batch|field` (a field that is None is left out)."""
    out = {f"{name}|total_energy": np.float64(ev.total_energy)}
    for k, b in enumerate(ev.batches):
        for f in WHOLE + SAMPLED:
            a = getattr(b, f)
            if a is not None:
                out[f"{name}|{k}|{f}"] = np.asarray(a)[::SAMPLE] if f in SAMPLED else np.asarray(a)
    return out


def answers() -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for name, bodies, batches, options in cases():
        out.update(kept(name, evaluate(bodies, batches, **options)))
    return out


if __name__ == "__main__":
    np.savez_compressed(PATH, **answers())
