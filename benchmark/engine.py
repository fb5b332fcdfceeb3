"""The experiment engine: run a list of jobs, one row (a dict) each, and give the rows back in
job order -- in this process, in spawned worker processes, or on a Dask cluster.

Every study is a list of jobs on this engine: the runs table, the stability map, the drift
check, the long-horizon energy study, the speed tables and the reel-reversal orders.

* Workers: each is a single-process pool (`worker_pool`): spawned (JAX does not survive fork),
  one XLA thread (the workers are the parallelism, and timings stay per-core), Ctrl-C left to
  the parent, and an exit of its own once the parent is gone (killed with -9).
* Grouping: jobs with the same ``group`` run one after another in one worker, so what it
  compiled for the first (JAX solves are cached per model and solver) serves the others; the
  groups start longest first by ``cost``, so no worker is left with a long tail.
* Failures: a worker that dies gives its job a crash row (``crash_row``) and is replaced.
* Stopping: Ctrl-C or SIGTERM (`install_stop_handlers`) raises KeyboardInterrupt in the main
  thread; the pools terminate their workers, a Dask run withdraws its tasks, and every row
  finished so far has been handed to ``on_row`` (a stopped run keeps them).
* Progress: one line per finished job, ``[done/total] <describe(row)>  (elapsed, ETA)``.
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import signal
import sys
import threading
import time
from typing import Callable, Hashable, Iterable


def log_stderr(msg: str) -> None:
    """The default log of every study: progress and warnings go to stderr, results elsewhere."""
    print(msg, file=sys.stderr, flush=True)


# ------------------------------------------------------------------------------------------
# Worker processes
# ------------------------------------------------------------------------------------------
def worker_env() -> None:
    """One XLA thread per worker: the workers are the parallelism, and timings stay per-core.
    Appended: XLA_FLAGS already holds reelbench's own options (models._jax) and maybe a user's."""
    from models._jax import append_xla_flags  # imports JAX: only where jobs run

    append_xla_flags(("--xla_cpu_multi_thread_eigen=false", "intra_op_parallelism_threads=1"))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


#: How often (s) a worker checks that its parent is still alive.
PARENT_POLL = 0.5


def _watch_parent(parent: int) -> None:
    while True:
        time.sleep(PARENT_POLL)
        if os.getppid() != parent:  # re-parented: the study's process is gone (e.g. kill -9)
            os._exit(3)


def _worker_init(parent: int) -> None:
    """Runs first in every pool worker: Ctrl-C is the parent's to handle (it terminates the
    workers; a worker that also caught it would print a traceback), and the worker exits on
    its own once the parent is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True, name="watch-parent").start()


class _Pool(cf.ProcessPoolExecutor):
    """A process pool that, when its ``with`` block ends by an exception (Ctrl-C, SIGTERM, an
    error), terminates its workers instead of waiting for their tasks to finish."""

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            return super().__exit__(exc_type, exc, tb)
        self.terminate()
        return False

    def terminate(self, grace: float = 2.0) -> None:
        procs = list((getattr(self, "_processes", None) or {}).values())
        for p in procs:
            if p.is_alive():
                p.terminate()
        self.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + grace
        for p in procs:
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(1.0)


def worker_pool(workers: int) -> cf.ProcessPoolExecutor:
    """A pool of spawned workers with one XLA thread each (`worker_env`), which ignore Ctrl-C,
    exit when the parent dies, and are terminated when the ``with`` block is left by an exception."""
    worker_env()
    return _Pool(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                 initializer=_worker_init, initargs=(os.getpid(),))


# ------------------------------------------------------------------------------------------
# Stopping
# ------------------------------------------------------------------------------------------
def install_stop_handlers() -> None:
    """SIGTERM stops the process like Ctrl-C does (KeyboardInterrupt in the main thread), so
    one ``except KeyboardInterrupt`` handles both and the pools' workers are terminated.

    SIGINT gets Python's own handler back too: a process started from a background job of a
    script (``python -m benchmark run ... &``) inherits SIGINT *ignored*, and Python then never
    raises KeyboardInterrupt, so Ctrl-C / ``kill -INT`` would not stop the study."""

    def stop(signum, frame):
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, signal.default_int_handler)


def stop_cause(exc: KeyboardInterrupt) -> str:
    """What stopped a study, in words: "SIGTERM" or "Ctrl-C"."""
    return "SIGTERM" if "SIGTERM" in str(exc) else "Ctrl-C"


def stop_status(exc: KeyboardInterrupt) -> int:
    """Exit status of a stopped command: 143 for SIGTERM, 130 for Ctrl-C (as a shell reports)."""
    return 143 if "SIGTERM" in str(exc) else 130


def stopped(exc: KeyboardInterrupt, what: str, log: Callable[[str], None] = log_stderr) -> int:
    """Say in one line what stopped the study and what it saved; returns the exit status."""
    log(f"stopped by {stop_cause(exc)}: {what}")
    return stop_status(exc)


def crash_reason(exc: BaseException) -> str:
    """The `reason` of a row whose worker died (status "crashed")."""
    return f"{type(exc).__name__}: {exc}"[:300]


# ------------------------------------------------------------------------------------------
# Progress
# ------------------------------------------------------------------------------------------
class Progress:
    """Collects the rows of a list of jobs as they finish, in any order, and gives them back in
    job order. Each finished row is logged (``[done/total] <describe(row)>  (elapsed, ETA)``) and
    ``on_row`` gets the rows so far (to write partial results atomically), so a stopped run keeps
    every finished row. ``rows`` are jobs already done (resumed); they count in the total."""

    def __init__(self, total: int, *, rows: dict[int, dict] | None = None, finish: Callable | None = None,
                 describe: Callable[[dict], str] = str, on_row: Callable[[list[dict]], None] | None = None,
                 log: Callable[[str], None] = log_stderr):
        self.total, self.rows = total, dict(rows or {})
        self.todo = total - len(self.rows)
        self.finish, self.describe, self.on_row, self.log = finish, describe, on_row, log
        self.new = 0
        self.start = time.perf_counter()

    def done(self, i: int, row: dict) -> None:
        if self.finish:
            self.finish(i, row)
        self.rows[i] = row
        self.new += 1
        elapsed = time.perf_counter() - self.start
        left = self.todo - self.new
        eta = f", about {elapsed / self.new * left:.0f} s left" if left > 0 else ""
        self.log(f"[{len(self.rows)}/{self.total}] {self.describe(row)}  ({elapsed:.0f} s elapsed{eta})")
        self.saved()

    def saved(self) -> None:
        if self.on_row:
            self.on_row(self.ordered())

    def ordered(self) -> list[dict]:
        return [self.rows[k] for k in sorted(self.rows)]


class Heartbeat:
    """Progress of one long computation that reports nothing itself: a line every ``every``
    seconds with the time spent and what is left of the estimate (``estimate`` s)."""

    def __init__(self, what: str, estimate: float | None, every: float = 30.0,
                 log: Callable[[str], None] = log_stderr):
        self.what, self.estimate, self.every, self.log = what, estimate, every, log
        self._stop = threading.Event()
        self._t0 = time.perf_counter()

    def __enter__(self):
        if self.estimate is not None and self.estimate > self.every:
            threading.Thread(target=self._run, daemon=True).start()
        return self

    def _run(self):
        while not self._stop.wait(self.every):
            spent = time.perf_counter() - self._t0
            left = max(self.estimate - spent, 0.0)
            self.log(f"{self.what}: {spent:.0f} s so far; estimated {left:.0f} s left "
                     f"({min(spent / self.estimate, 0.99):.0%} by the estimate)")

    def __exit__(self, *exc):
        self._stop.set()


# ------------------------------------------------------------------------------------------
# The engine
# ------------------------------------------------------------------------------------------
def run_jobs(
    fn: Callable[[object], dict],
    jobs: list,
    *,
    workers: int,
    crash_row: Callable[[int, BaseException], dict] | None = None,
    scheduler: str | None = None,
    group: Callable[[int], Hashable] | None = None,
    cost: Callable[[int], float] | None = None,
    setup: Iterable[Callable[[], object]] = (),
    done: dict[int, dict] | None = None,
    finish: Callable[[int, dict], None] | None = None,
    describe: Callable[[dict], str] = str,
    on_row: Callable[[list[dict]], None] | None = None,
    log: Callable[[str], None] = log_stderr,
) -> list[dict]:
    """Run ``fn(jobs[i])`` (a row, a dict) for every job not in ``done`` and return all rows in
    job order. ``fn``, the jobs and the ``setup`` calls must pickle for the workers (module-level
    functions, `functools.partial` of them).

    ``workers`` = 0 runs the jobs in this process; otherwise in that many workers (see the
    module's docstring), or, with ``scheduler`` (a Dask address), on that cluster. ``setup``:
    calls that run first (spread over the workers), e.g. the reference solutions the jobs read
    from a cache. ``crash_row(i, exc)``: the row of a job whose worker died (without it, the
    death is raised). ``finish(i, row)`` completes a row before it is logged (`Progress`)."""
    if crash_row is None:
        crash_row = _raise
    progress = Progress(len(jobs), rows=done, finish=finish, describe=describe, on_row=on_row, log=log)
    todo = [i for i in range(len(jobs)) if i not in progress.rows]
    if progress.rows:
        progress.saved()
    if not todo:
        return progress.ordered()
    setup = list(setup)
    if scheduler:
        _run_on_dask(fn, jobs, todo, scheduler, setup, crash_row, progress)
    elif workers == 0:
        for call in setup:
            call()
        for batch in _batches(todo, group, cost):
            for i in batch:
                progress.done(i, fn(jobs[i]))
    else:
        _run_in_workers(fn, jobs, _batches(todo, group, cost), workers, setup, crash_row, progress)
    return progress.ordered()


def _raise(i: int, exc: BaseException) -> dict:
    raise exc


def _batches(todo: list[int], group, cost) -> list[list[int]]:
    """The jobs to run, in groups (one per ``group`` value, in the order of their first job),
    the longest first when ``cost`` is known (stable: ties keep their order)."""
    batches: dict = {}
    for i in todo:
        batches.setdefault(group(i) if group else ("job", i), []).append(i)
    queue = list(batches.values())
    if cost is not None:
        queue.sort(key=lambda b: -sum(cost(i) for i in b))
    return queue


def _run_in_workers(fn, jobs, batches, workers: int, setup, crash_row, progress: Progress) -> None:
    """Each worker a single-process pool that takes one group at a time; a dead worker's job
    gets its crash row and the worker is replaced before its next group."""
    queue = collections.deque(batches)
    with contextlib.ExitStack() as stack:
        pools = [stack.enter_context(worker_pool(1)) for _ in range(min(workers, len(queue)))]
        for fut in [pools[k % len(pools)].submit(call) for k, call in enumerate(setup)]:
            fut.result()
        running: dict = {}  # future -> (pool index, job index)
        broken: set = set()

        def feed(k: int) -> None:
            if k in broken:  # its worker died: the next group gets a fresh one
                pools[k] = stack.enter_context(worker_pool(1))
                broken.discard(k)
            if queue:
                for i in queue.popleft():
                    running[pools[k].submit(fn, jobs[i])] = (k, i)

        for k in range(len(pools)):
            feed(k)
        while running:
            finished, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
            for fut in finished:
                k, i = running.pop(fut)
                try:
                    row = fut.result()
                except Exception as exc:  # the worker process died
                    if isinstance(exc, cf.process.BrokenProcessPool):
                        broken.add(k)
                    row = crash_row(i, exc)
                progress.done(i, row)
                if all(kk != k for kk, _ in running.values()):
                    feed(k)


def _run_on_dask(fn, jobs, todo: list[int], scheduler: str, setup, crash_row, progress: Progress) -> None:
    """The jobs as tasks of a Dask cluster (the scheduler places them; no grouping). A stopped
    run withdraws its tasks: the cluster's workers are not ours to kill."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ValueError("executor 'dask' needs the optional dependency: pip install 'reelbench[dask]'") from None
    client = Client(scheduler)
    futures = {}
    try:
        _dask_worker_env(client)
        for fut in [client.submit(call, pure=False) for call in setup]:
            fut.result()
        futures = {client.submit(fn, jobs[i], pure=False): i for i in todo}
        index = {f.key: i for f, i in futures.items()}
        for fut in as_completed(list(futures)):
            i = index[fut.key]
            try:
                row = fut.result()
            except Exception as exc:
                row = crash_row(i, exc)
            progress.done(i, row)
    except BaseException:
        client.cancel(list(futures), force=True)
        raise
    finally:
        client.close()


def _dask_worker_env(client) -> None:
    """The pool's one-XLA-thread setting (`worker_env`) on every Dask worker, also on workers
    that join or restart later (a worker plugin). It takes effect where JAX is not yet imported
    in the worker, i.e. before its first task."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class OneXlaThread(WorkerPlugin):
        name = "reelbench-one-xla-thread"

        def setup(self, worker):
            worker_env()

    register = getattr(client, "register_plugin", None) or client.register_worker_plugin
    register(OneXlaThread())
    client.run(worker_env)
