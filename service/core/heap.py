"""Keep freed memory in the process heap instead of giving it back to the OS after every call.

An evaluation allocates tens to hundreds of MB of short-lived arrays; glibc maps blocks over its mmap threshold
afresh and returns them on free, so every call page-faults all of it in again (~4 us per 4 KiB page here, half of
an energy evaluation at 1e5 joints). Raised thresholds keep and reuse those pages, as JAX's allocator does; the
price is that a process keeps its high-water mark of memory (a worker's peak request).
"""

from __future__ import annotations

import ctypes
import sys

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8  # glibc's mallopt options
MMAP_THRESHOLD = 1 << 30
"""Blocks over 1 GiB (a 2e5-joint Hessian) still get their own mapping, returned on free."""
TRIM_THRESHOLD = 1 << 31


def keep_heap() -> bool:
    """Set glibc's thresholds for this process; False where there is no glibc `mallopt` (musl, macOS, Windows)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    # One arena: the pages kept by one of the core's threads serve the others (a thread's own
    # arena is a capped mapping of its own, trimmed as it frees).
    settings = ((_M_ARENA_MAX, 1), (_M_MMAP_THRESHOLD, MMAP_THRESHOLD), (_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return all([bool(mallopt(option, value)) for option, value in settings])
