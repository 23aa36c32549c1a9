"""Splitting torch's work over the CPU's cores: one intra-op thread for loops of small ops, two Python threads
for two independent halves of a sequence, two processes for two independent loops of small ops.

    with one_thread(): ...                 # torch on one intra-op thread inside (restored after)
    parallel_halves(device) -> bool        # whether the caller may run two halves on two threads
    on_two_threads(fn, first, second)      # (fn(*first), fn(*second)), the first on a worker thread
    parallel_processes(device) -> bool     # whether the caller may run two jobs in two processes
    in_two_processes(first, second)        # (first(), second()), the first in a forked child

`one_thread` remembers the count it replaced (the outermost one's), the thread budget
`parallel_halves` and `parallel_processes` read. Used by `ptrack.optim.banded` (its sequential sweeps), the
batch estimator (its whole solve; the linearisation's two halves) and the kjs trackers (each pass on one
thread; the two passes after a tree start, and the halves of the stages' batched polishing, in two processes).
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import sys
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


def parallel_processes(device: torch.device) -> bool:
    """Whether two jobs may run in two processes (`in_two_processes`): on the CPU, inside `one_thread` (torch on one
    intra-op thread) with a thread budget of 2 or more, where this process can fork (POSIX). Outside `one_thread`
    torch's intra-op pool may be running, and a child forked then can wait forever on a lock the pool held: the
    recombination called on two threads (a test calling it directly) hung in its child so."""
    one = torch.get_num_threads() == 1
    return one and parallel_halves(device) and hasattr(os, "fork") and sys.platform != "darwin"


def in_two_processes(first: Callable[[], object], second: Callable[[], object]) -> tuple:
    """(first(), second()), at once: first() in a forked copy of this process, second() here.

    For jobs of many small torch ops, where two threads would wait on each other for the GIL (the kjs tracker's two
    passes: 1.4x on two threads, 2.0x in two processes, on 2 idle cores). The child runs on the same thread count as
    the caller, so its result is the one first() gives here. It comes back pickled through a pipe; an exception
    raised in the child is raised here (after second() is done). A child that dies without a whole answer (killed,
    out of memory) is not an error: first() then runs here. If this process stops (an exception in second(), Ctrl-C,
    SIGTERM) the child is killed first; on Linux it also dies with this process when that is killed outright."""
    parent = os.getpid()
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        os.close(read)
        _die_with(parent)
        try:
            answer: tuple = (True, first())
        except BaseException as e:  # handed to the parent, which raises it
            answer = (False, e)
        try:
            data = pickle.dumps(answer)
        except Exception as e:  # an exception that does not pickle
            data = pickle.dumps((False, RuntimeError(f"in a child process: {answer[1]!r} ({e})")))
        try:
            with os.fdopen(write, "wb") as pipe:
                pipe.write(data)
        finally:
            os._exit(0)  # no atexit handlers, no flushing of buffers copied from the parent
    os.close(write)
    try:
        mine = second()
        with os.fdopen(read, "rb") as pipe:
            read = -1
            data = pipe.read()
        _, status = os.waitpid(pid, 0)
    except BaseException:
        if read >= 0:
            os.close(read)
        _stop(pid)
        raise
    if status != 0 or not data:  # the child died without a whole answer
        return first(), mine
    ok, value = pickle.loads(data)
    if not ok:
        raise value
    return value, mine


def _die_with(parent: int) -> None:
    """In a forked child: be killed when the process `parent` dies (Linux's PR_SET_PDEATHSIG; elsewhere nothing),
    and exit now if it is gone already."""
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG = 1
    if os.getppid() != parent:
        os._exit(1)


def _stop(pid: int) -> None:
    """Kill the child `pid` and reap it."""
    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):
        pass
