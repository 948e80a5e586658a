"""How many methods the ego fuses at once (`perception.fusion_threads`).

The ego's fusions are independent of one another and most of their time is inside torch ops, which release
the GIL: two methods on two threads use two cores where one method at a time leaves the second core to the
CAVs' idle waits. Each method still runs its ops one after another on one thread (torch's intra-op pool is
one thread in every agent process), so its prediction is bit-identical to a serial run's.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor


def fusion_threads(setting: int, methods: int, cpus: int | None = None) -> int:
    """The ego's fusion threads: `setting` when given (> 0), else (auto) one per core of this host, at most one
    per method."""
    if setting > 0:
        return min(setting, max(methods, 1))
    n = cpus if cpus is not None else (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                                       else os.cpu_count() or 1)
    return max(1, min(n, methods))


def fusion_pool(threads: int) -> ThreadPoolExecutor | None:
    """A pool of `threads` fusion threads, or None for one (the methods run in the ego's main thread)."""
    return ThreadPoolExecutor(threads, thread_name_prefix="fusion") if threads > 1 else None
