"""The batch engine: many runs, each one config + overrides + one input -> one run folder.

    Item(name, config, overrides, run_dir)     one run to make (its input is among the overrides)
    run_item(item, progress) -> dict | str     the run: its metrics.json, or the one-line error that stopped it
    open_executor(kind, workers, address)      serial, local worker processes, or Ray tasks (a context manager)
    run_items(items, executor, ...) -> list    every item's outcome, in the items' order

The flow: a front end (`ptrack evaluate`: CMU clips x seeds, `ptrack.pipeline.evaluate`; `ptrack batch`: real
inputs x settings, `ptrack.pipeline.batch_run`) makes the items and opens an executor before it writes anything
(a Ray cluster that cannot be reached is a user error, nothing written); the executor calls `run_item` on each
item where it runs, and that call writes the item's run folder atomically (`ptrack.pipeline.run.execute`: a
hidden `.NAME.partial` sibling renamed at the end), so an item is either a complete folder or nothing; the
outcomes come back to the front end as each finishes (`report`: the status file, the progress) and in order
at the end (the tables).

Executors:
- serial (`workers=1`, local): one item after another in this process.
- local (`workers=N`): N worker processes (spawn), each on one torch intra-op thread, fed one item at a time by
  this process (a supervised pool: each worker pays torch's import once, not once per item, and is replaced
  by a fresh process after `RECYCLE_AFTER` items, which bounds its memory). A worker that
  dies (killed, out of memory) costs only its item, a failed row "worker process died (...)", and is replaced;
  what it left half-written is removed.
- ray: one Ray task per item (one CPU, no retry) on the cluster at `address` ("auto", "HOST:PORT") or on a
  local Ray runtime of `workers` CPUs. The task calls the same `run_item`, so on a cluster the run folders land
  in the output path as the node sees it: a path shared by every node. Leaving (the end, Ctrl-C, SIGTERM)
  shuts Ray down (`ray.shutdown`), which ends a local runtime's processes. Ray too replaces a worker process
  after `RECYCLE_AFTER` tasks (`max_calls`).

An item's failure (a user error in its input, an estimator failure, a worker that died, a bug met on one
input) is its outcome, a one-line message; the sweep goes on. Ctrl-C or SIGTERM (raised as an exception by
the command line) stops every worker and removes the half-written folders, leaving the finished ones.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import os
import signal
import socket
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

from ptrack.errors import EstimationError, InputError, log_to_stderr

log = logging.getLogger(__name__)

#: a run's outcome: its metrics.json (a dict), or the one-line message of what stopped it
Outcome = dict | str
EXECUTORS = ("local", "ray")
#: items a local worker runs before a fresh process takes its place: what runs leave behind in a process stays
#: bounded (the rerun SDK keeps about 1.2 MB per recording written, measured on 10-frame runs: 1 GB in 1,000 items)
RECYCLE_AFTER = 100
RAY_CONNECT_S = 3.0  # how long to wait for a Ray cluster's address to answer before calling it unreachable


@dataclass(frozen=True)
class Item:
    """One run of a batch. `overrides` (dotted.key=value) apply to `config` in order and name the input
    (observations.file=..., data.amc=...); `run_dir` (absolute) is the folder the run writes; `name` is what
    progress lines and failure warnings call it."""

    name: str
    config: str
    overrides: tuple[str, ...]
    run_dir: str


def one_line(e: BaseException) -> str:
    """An exception as one line: its message with the whitespace folded (the type's name when it has none)."""
    text = " ".join(str(e).split())
    return text or type(e).__name__


def run_item(item: Item, progress: bool | None = False) -> Outcome:
    """Run `item` into its folder: -> its metrics.json, or the one-line message of what stopped it. A user error
    (bad input file, config value), an estimation failure or an OS error is that message; any other exception
    (a library's error on a corrupt input, a bug) is logged with its traceback and is `Type: message`, so that
    one bad item never stops a sweep. progress: as `execute`'s (per-frame progress of this run)."""
    from ptrack.pipeline.config import load_config
    from ptrack.pipeline.run import execute

    try:
        cfg = load_config(item.config, [*item.overrides, f"out_dir={item.run_dir}"])
        done = execute(cfg, progress=progress)
        return json.loads((done / "metrics.json").read_text(encoding="utf-8"))
    except (InputError, EstimationError, OSError) as e:
        return one_line(e)
    except Exception as e:  # the item fails, the sweep goes on
        log.error("%s: unexpected %s", item.name, type(e).__name__, exc_info=True)
        return f"{type(e).__name__}: {one_line(e)}"


#: the per-item function an executor calls: (item, progress) -> outcome (a module-level function: it is sent
#: by name to worker processes and Ray tasks)
RunFn = Callable[[Item, "bool | None"], Outcome]
#: called in this process as each item finishes: (index, outcome, seconds the item took where it ran)
ReportFn = Callable[[int, Outcome, float], None]


def timed(run: RunFn, item: Item, progress: bool | None) -> tuple[Outcome, float]:
    """(run(item, progress), its wall seconds)."""
    t0 = time.perf_counter()
    outcome = run(item, progress)
    return outcome, time.perf_counter() - t0


# ---------------------------------------------------------------- executors


class Serial:
    """Items one after another in this process (`progress` passed to each run)."""

    workers = 1

    def map(self, items: Sequence[Item], run: RunFn, report: ReportFn, progress: bool | None = False) -> None:
        for i, item in enumerate(items):
            report(i, *timed(run, item, progress))


class Local:
    """A supervised pool of `workers` spawned processes, one item at a time each (module docstring)."""

    def __init__(self, workers: int, recycle_after: int = RECYCLE_AFTER) -> None:
        self.workers, self.recycle_after = workers, recycle_after
        self.ctx = multiprocessing.get_context("spawn")
        self.idle: list[_Worker] = []

    def map(self, items: Sequence[Item], run: RunFn, report: ReportFn, progress: bool | None = False) -> None:
        pending = deque(range(len(items)))
        busy: dict[_Worker, int] = {}
        sent: dict[int, float] = {}  # when each item went to its worker
        try:
            while pending or busy:
                while pending and len(busy) < self.workers:
                    worker = self._idle_worker() or _Worker(self.ctx, run)
                    i = pending.popleft()
                    busy[worker] = i  # before sending: an interruption now stops it too
                    sent[i] = time.perf_counter()
                    worker.conn.send((i, items[i]))
                ready = set(wait([w.conn for w in busy] + [w.process.sentinel for w in busy]))
                for worker in [w for w in busy if w.conn in ready or w.process.sentinel in ready]:
                    i = busy.pop(worker)
                    answer = worker.answer()
                    if answer is None:  # it died inside the item
                        answer = (
                            f"worker process died ({worker.death()}) while running it",
                            time.perf_counter() - sent[i],
                        )
                        _remove_partial(items[i])
                    else:
                        worker.done += 1
                        if worker.done >= self.recycle_after:
                            worker.stop()  # a fresh process takes the next item
                        else:
                            self.idle.append(worker)
                    report(i, *answer)
        except BaseException:
            for worker in [*busy, *self.idle]:
                worker.process.terminate()
            for worker in [*busy, *self.idle]:
                worker.process.join()
                worker.conn.close()
            self.idle = []
            for i in busy.values():
                _remove_partial(items[i])
            raise

    def _idle_worker(self) -> _Worker | None:
        """An idle worker still alive (one that died between items is let go), or None."""
        while self.idle:
            worker = self.idle.pop()
            if worker.process.is_alive():
                return worker
            worker.process.join()
            worker.conn.close()
        return None

    def close(self) -> None:
        """Let the idle workers end (those still busy were stopped by `map`)."""
        for worker in self.idle:
            worker.stop()
        self.idle = []


class _Worker:
    """A worker process of `Local` and the pipe it takes items on and answers through."""

    def __init__(self, ctx: Any, run: RunFn) -> None:
        self.done = 0  # items answered
        self.conn, theirs = ctx.Pipe()
        self.process = ctx.Process(target=_worker_main, args=(theirs, run), daemon=True)
        self.process.start()
        theirs.close()

    def answer(self) -> tuple[Outcome, float] | None:
        """(outcome, seconds) of the item it was sent, or None when it died first."""
        try:
            if self.conn.poll():
                _, answer = self.conn.recv()
                return answer
        except (EOFError, OSError):
            pass
        return None

    def death(self) -> str:
        """How it ended: "killed by SIGKILL (out of memory?)", "exit status 3"."""
        self.process.join()
        code = self.process.exitcode
        self.conn.close()
        if code is not None and code < 0:
            name = signal.Signals(-code).name if -code in signal.valid_signals() else f"signal {-code}"
            return f"killed by {name}" + (", out of memory?" if -code == getattr(signal, "SIGKILL", 9) else "")
        return f"exit status {code}"

    def stop(self) -> None:
        with suppress(OSError):
            self.conn.send(None)
        self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join()
        self.conn.close()


def _worker_main(conn: Connection, run: RunFn) -> None:
    """A `Local` worker: one intra-op thread (the workers share the cores), the command line's message format,
    Ctrl-C left to the parent (which stops the workers); runs the items it is sent until it is sent None or
    the parent is gone."""
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)
    log_to_stderr()
    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        if task is None:
            return
        i, item = task
        conn.send((i, timed(run, item, False)))


def _remove_partial(item: Item) -> None:
    """Remove what a stopped or killed run of `item` left half-written beside its folder."""
    from ptrack.pipeline.run import remove_partial

    parent = Path(item.run_dir).parent
    if parent.is_dir():
        remove_partial(parent, recursive=False)


class Ray:
    """One Ray task per item (module docstring); `address` None: a local runtime of `workers` CPUs."""

    def __init__(self, workers: int, address: str | None) -> None:
        self.workers, self.address = workers, address
        ray = import_ray()
        if address and address != "auto" and not address.startswith("ray://"):
            check_reachable(address)
        handlers = _python_handlers()
        try:
            if address:
                with _quiet_stderr(), _env(RAY_gcs_server_port_wait_time_s=str(int(RAY_CONNECT_S))):
                    ray.init(address=address, log_to_driver=False, logging_level=logging.ERROR)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
        except (ConnectionError, RuntimeError, ValueError) as e:
            ray.shutdown()
            where = f"at {address}" if address else "(a local runtime)"
            raise InputError(f"cannot start or join the Ray cluster {where}: {one_line(e)}") from None
        finally:
            _restore(handlers)
        self.ray = ray

    def map(self, items: Sequence[Item], run: RunFn, report: ReportFn, progress: bool | None = False) -> None:
        ray = self.ray
        task = ray.remote(num_cpus=1, max_retries=0, max_calls=RECYCLE_AFTER)(_ray_task)  # fresh workers too
        refs = {task.remote(run, item): i for i, item in enumerate(items)}
        raised: list[BaseException] = []  # what this process's signal handlers raised (Ray's wait swallows it)
        handlers = _python_handlers()
        for signum, handler in handlers.items():
            if callable(handler):
                signal.signal(signum, _recording(handler, raised))
        try:
            while refs:
                done, _ = ray.wait(list(refs), num_returns=1)
                for ref in done:
                    i = refs.pop(ref)
                    try:
                        outcome, seconds = ray.get(ref)
                    except ray.exceptions.RayError as e:  # its worker died (killed, out of memory), ...
                        outcome, seconds = f"Ray task failed: {_first_line(e)}", math.nan
                        _remove_partial(items[i])
                    report(i, outcome, seconds)
        except BaseException:  # Ctrl-C, SIGTERM: stop the tasks, a local runtime, and remove what they left
            for ref in refs:
                ray.cancel(ref, force=True)
            ray.shutdown()
            for i in refs.values():
                _remove_partial(items[i])
            if raised and sys.exc_info()[1] is not raised[0]:
                raise raised[0] from None  # the command line's Terminated, not Ray's KeyboardInterrupt
            raise
        finally:
            _restore(handlers)

    def close(self) -> None:
        self.ray.shutdown()


@contextmanager
def _env(**values: str) -> Iterator[None]:
    """Environment variables set inside the block, unless the user set them (then theirs stay)."""
    added = [k for k in values if k not in os.environ]
    os.environ.update({k: values[k] for k in added})
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


@contextmanager
def _quiet_stderr() -> Iterator[None]:
    """File descriptor 2 into a temporary file inside the block, its text then logged at DEBUG: Ray's C++ client
    writes a warning a second while it looks for a cluster (the error that follows says it in one line)."""
    import tempfile

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode(errors="replace").strip()
            if text:
                log.debug("Ray: %s", text)


def _python_handlers() -> dict[int, Any]:
    """This process's Python handlers of SIGINT, SIGTERM and SIGHUP (the main thread's to set)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}
    wanted = [getattr(signal, s) for s in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, s)]
    return {int(s): signal.getsignal(s) for s in wanted}


def _restore(handlers: dict[int, Any]) -> None:
    """Put `handlers` back: ray.init installs its own for SIGTERM (it aborts the process, leaving the runtime and
    the half-written folders), where the command line's raises `Terminated` and cleans up."""
    for signum, handler in handlers.items():
        if handler is not None:
            signal.signal(signum, handler)


def _recording(handler: Callable, raised: list[BaseException]) -> Callable:
    """`handler`, keeping in `raised` what it raises: Ray's wait turns an exception raised by a signal handler
    into a plain KeyboardInterrupt (the command line tells SIGTERM from Ctrl-C by its exception)."""

    def record(signum: int, frame: Any) -> None:
        try:
            handler(signum, frame)
        except BaseException as e:
            raised.append(e)
            raise

    return record


def _first_line(e: BaseException) -> str:
    """A long error (Ray's hold a traceback) as its first non-empty line, at most 300 characters."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return (lines[0] if lines else type(e).__name__)[:300]


def _ray_task(run: RunFn, item: Item) -> tuple[Outcome, float]:
    """A Ray task: the item on one intra-op thread -> (outcome, seconds)."""
    import torch

    torch.set_num_threads(1)
    return timed(run, item, False)


def import_ray() -> Any:
    """The `ray` module; InputError naming the extra when it is not installed."""
    try:
        import ray
    except ImportError:
        raise InputError('--executor ray needs Ray: pip install -e ".[ray]"') from None
    return ray


def check_reachable(address: str, timeout: float = RAY_CONNECT_S) -> None:
    """InputError unless something listens at `address` ("HOST:PORT") within `timeout` seconds: ray.init would
    wait much longer for a cluster that is not there."""
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        raise InputError(f"--ray-address {address!r} is not auto, HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as e:
        reason = "no answer" if isinstance(e, TimeoutError) else (e.strerror or one_line(e))
        raise InputError(f"cannot reach the Ray cluster at {address} ({reason} within {timeout:.0f} s)") from None


def check_workers(workers: object, flag: str = "--workers") -> int:
    """`workers` as a whole number >= 1 (InputError otherwise)."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"{flag} must be a whole number >= 1, got {workers!r}")
    return workers


@contextmanager
def open_executor(kind: str = "local", workers: int = 1, address: str | None = None) -> Iterator[Any]:
    """The executor `kind` ("local": serial when `workers` is 1, else worker processes; "ray"), closed on
    leaving: idle workers end, Ray is shut down. InputError (before anything runs) for a bad kind, an
    `address` without Ray, Ray not installed or a cluster that cannot be reached."""
    if kind not in EXECUTORS:
        raise InputError(f"--executor must be one of {', '.join(EXECUTORS)}, got {kind!r}")
    if address is not None and kind != "ray":
        raise InputError("--ray-address needs --executor ray")
    executor: Serial | Local | Ray = (
        Ray(workers, address) if kind == "ray" else Serial() if workers == 1 else Local(workers)
    )
    try:
        yield executor
    finally:
        if not isinstance(executor, Serial):
            executor.close()


def run_items(
    items: Sequence[Item],
    executor: Serial | Local | Ray,
    progress: Progress,
    run: RunFn = run_item,
    report: ReportFn | None = None,
    run_progress: bool | None = False,
) -> list[Outcome]:
    """Every item's outcome (in the items' order) through `executor`, each also passed to `report` (this
    process, as it finishes) and counted by `progress`. run: the per-item function (tests inject failures
    through it). run_progress: each run's own progress (serial executor only)."""
    outcomes: list[Outcome] = ["not run"] * len(items)

    def finished(i: int, outcome: Outcome, seconds: float) -> None:
        outcomes[i] = outcome
        if isinstance(outcome, str):
            progress.log.warning("%s failed: %s", items[i].name, outcome)
        if report is not None:
            report(i, outcome, seconds)
        progress.finished(items[i].name, isinstance(outcome, str), line=not isinstance(executor, Serial))

    if isinstance(executor, Serial):

        def started(i: int, outcome: Outcome, seconds: float) -> None:
            finished(i, outcome, seconds)
            if i + 1 < len(items):
                progress.started(i + 1, items[i + 1].name)

        if items:
            progress.started(0, items[0].name)
        executor.map(items, run, started, run_progress)
    else:
        executor.map(items, run, finished)
    return outcomes


# ---------------------------------------------------------------- progress


class Progress:
    """A batch's progress over its items: on a terminal one bar (done / failed / left, the time left), elsewhere
    one log line per item through `log` at INFO (run one after another: as each starts; at once: as each
    finishes); nothing when not shown. unit: what an item is called ("clip", "run", "item")."""

    def __init__(self, show: bool, total: int, unit: str, log: logging.Logger, clock=time.monotonic) -> None:
        self.total, self.unit, self.log, self.clock = total, unit, log, clock
        self.count = self.failed = 0
        self.start = clock()
        self.lines = show and not sys.stderr.isatty()
        self.bar = None
        if show and not self.lines:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, desc=f"{unit}s", unit=unit)

    def _left(self) -> str:
        """The end of a line: ", 1 failed, 7 left, about 03:20 left" (the failures only if any, the time once an
        item is done)."""
        from tqdm import tqdm

        parts = [f"{self.failed} failed"] if self.failed else []
        left = self.total - self.count
        parts.append(f"{left} left")
        if self.count and left:
            parts.append(f"about {tqdm.format_interval(left * (self.clock() - self.start) / self.count)} left")
        return ", " + ", ".join(parts)

    def started(self, i: int, name: str) -> None:
        if self.lines:
            self.log.info("%s %d of %d: %s%s", self.unit, i + 1, self.total, name, self._left() if i else "")

    def finished(self, name: str, failed: bool = False, line: bool = True) -> None:
        """Count an item as finished; line: log it (items run at once; one after another, `started` logs)."""
        self.count += 1
        self.failed += failed
        if self.bar is not None:
            self.bar.set_postfix_str(f"done {self.count - self.failed}, failed {self.failed}", refresh=False)
            self.bar.update()
        if self.lines and line:
            what = "failed" if failed else "done"
            self.log.info("%s %d of %d %s: %s%s", self.unit, self.count, self.total, what, name, self._left())

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def default_workers() -> int:
    """The default number of local workers: the cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1
