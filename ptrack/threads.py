"""Splitting torch's work over threads: one intra-op thread for loops of small ops, two Python threads for
two independent halves of a sequence.

    with one_thread(): ...                 # torch on one intra-op thread inside (restored after)
    parallel_halves(device) -> bool        # whether the caller may run two halves on two threads
    on_two_threads(fn, first, second)      # (fn(*first), fn(*second)), the first on a worker thread

`one_thread` remembers the count it replaced (the outermost one's), the thread budget
`parallel_halves` reads. Used by `ptrack.optim.banded` (its sequential sweeps), the batch estimator
(its whole solve; the linearisation's two halves) and the kjs trackers.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import torch

_OUTER = threading.local()  # .threads: torch's thread count outside the outermost `one_thread`


@contextmanager
def one_thread() -> Iterator[None]:
    """Run torch on one intra-op thread inside the block (restored after). The sequential sweeps of
    `ptrack.optim.banded` run on it: their products are small (n x n per frame), multithreaded BLAS
    gains nothing on them and, on a loaded machine, its spinning threads made a 40-frame sweep 370x
    slower (2.3 s against 6 ms, measured on 2 shared cores); `method: batch` runs its whole solve inside
    it. The count it replaced stays the thread budget that `parallel_halves` reads (the batch
    linearisation runs the two halves of a sequence on two Python threads, one intra-op thread each,
    when it is 2 or more)."""
    n = torch.get_num_threads()
    outer = getattr(_OUTER, "threads", None)
    if outer is None:
        _OUTER.threads = n
    try:
        if n == 1:
            yield
            return
        torch.set_num_threads(1)
        try:
            yield
        finally:
            torch.set_num_threads(n)
    finally:
        if outer is None:
            del _OUTER.threads


_POOL: ThreadPoolExecutor | None = None


def _forget_pool() -> None:  # a forked child has the pool object but not its thread
    global _POOL
    _POOL = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def parallel_halves(device: torch.device) -> bool:
    """Whether two halves of a sequence run on two threads (`on_two_threads`): a thread budget
    (`one_thread`) of 2 or more, on the CPU."""
    return device.type == "cpu" and getattr(_OUTER, "threads", torch.get_num_threads()) >= 2


def on_two_threads(fn: Callable, first: tuple, second: tuple) -> tuple:
    """(fn(*first), fn(*second)), the first on a second thread (one worker for the process, one
    intra-op thread; torch ops release the GIL, so the two run at once when each op is big enough for
    the GIL's handoffs not to matter: not the banded sweeps, ~1,000 small ops a half). Callers ask
    `parallel_halves` first."""
    global _POOL
    if _POOL is None:  # one worker, for the process's life, on one intra-op thread
        _POOL = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="ptrack-banded", initializer=torch.set_num_threads, initargs=(1,)
        )
    job = _POOL.submit(fn, *first)
    last = fn(*second)
    return job.result(), last
