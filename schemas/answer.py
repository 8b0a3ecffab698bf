"""The size of an answer, bounded from the request alone: joints x outputs x encoding (docs/deployment.md, "Limits").

Wire arithmetic, no numerics: the service admits requests by it (`service/http/limits.py`)
and the SDK splits requests by it, so that no part it sends is refused.
"""

from __future__ import annotations

from collections.abc import Sequence

JSON_FLOAT_BYTES = 25
"""Bound of one float in a JSON answer: the longest shortest-round-trip float64
(`-2.2250738585072014e-308`, 24 characters) and its separator."""
BINARY_FLOAT_BYTES = 8
FLOATS_PER_JOINT = {"energy": 3, "gradient": 24, "hessian": 24 * 24}
"""Floats one joint adds to the answer for each output; `energy` brings `x` and `coordinate` along."""
JSON_BRACKETS_PER_JOINT = {"energy": 0, "gradient": 3, "hessian": 3 * 24 + 3}
"""`[`, `]` and a separator around each row of a joint's gradient (one row) and Hessian (24 rows and itself)."""
BATCH_OVERHEAD_BYTES = 512
"""Keys, array headers and brackets of one batch in either encoding (the measured figure is < 300)."""


def answer_bytes(batch_joints: Sequence[int], outputs: Sequence[str], binary_answer: bool) -> int:
    """Upper bound of the answer's size, from the request alone (before any work).

    Every joint counts, `active_only` or not: which joints are active is known only
    after evaluating them, and the bound must hold before. `index` costs 8 bytes
    (binary) or its decimal digits and a separator (JSON); every output asked for adds
    `FLOATS_PER_JOINT` floats per joint. Unknown outputs cost nothing (they are a 422).
    """
    wanted = [o for o in FLOATS_PER_JOINT if o in outputs or o == "energy"]
    floats = sum(FLOATS_PER_JOINT[o] for o in wanted)
    total = BATCH_OVERHEAD_BYTES  # total_energy and the document's own keys
    for n in batch_joints:
        if binary_answer:
            per_joint = 8 + floats * BINARY_FLOAT_BYTES
        else:
            per_joint = len(str(max(n - 1, 0))) + 1 + floats * JSON_FLOAT_BYTES
            per_joint += sum(JSON_BRACKETS_PER_JOINT[o] for o in wanted)
        total += BATCH_OVERHEAD_BYTES + n * per_joint
    return total


def joints_within(max_answer_bytes: int, outputs: Sequence[str], binary_answer: bool, batches: int = 1) -> int:
    """The most joints, spread over `batches` batches, whose answer bound stays within `max_answer_bytes` (>= 0)."""
    fits = lambda n: answer_bytes([n] + [0] * (batches - 1), outputs, binary_answer) <= max_answer_bytes  # noqa: E731
    lo, hi = 0, 2**40
    while lo < hi:
        m = (lo + hi + 1) // 2
        lo, hi = (m, hi) if fits(m) else (lo, m - 1)
    return lo
