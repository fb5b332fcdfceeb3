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
* Progress: a line per finished setup call (e.g. each reference solution) and per finished
  job, ``[done/total] <describe(row)>  (elapsed, ETA)``, with a progress bar below them on a
  terminal; the ETA is measured, each job weighted by its predicted cost (`Progress`).
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import contextlib
import math
import multiprocessing
import os
import signal
import sys
import threading
import time
from typing import Callable, Hashable, Iterable


def log_stderr(msg: str) -> None:
    """The default log of every study: progress and warnings go to stderr, results elsewhere;
    above the progress bar while one is drawn (`Progress`)."""
    if _bar is not None:
        _bar.write(msg, file=sys.stderr)
    else:  # one write with its newline: a worker's line and this process's never interleave mid-line
        sys.stderr.write(f"{msg}\n")
        sys.stderr.flush()


# ------------------------------------------------------------------------------------------
# Worker processes
# ------------------------------------------------------------------------------------------
def worker_env() -> None:
    """One XLA thread per worker: the workers are the parallelism, and timings stay per-core.
    Appended: XLA_FLAGS already holds reelbench's own options (models._jax) and maybe a user's."""
    from reelbench.models._jax import append_xla_flags  # imports JAX: only where jobs run

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


def default_workers(units: int) -> int:
    """Every study's --jobs default: one worker per unit of work that compiles once (a method, a
    run, a scene and method), at most the CPU count, and at least one."""
    return max(1, min(units, os.cpu_count() or 1))


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

    SIGINT gets a handler too: a process started from a background job of a script
    (``python -m benchmark run ... &``) inherits SIGINT *ignored*, and Python then never raises
    KeyboardInterrupt, so Ctrl-C / ``kill -INT`` would not stop the study.

    A stop is never lost nor harmful: one that lands inside an import or the start of a worker
    waits for it to end (`_critical`; interrupted imports also had a library's fallback swallow
    the stop), and one that Python drops (raised in a gc callback or a finalizer: JAX runs one
    at every collection) is sent again."""

    def stop(signum, frame):
        if _critical(frame):
            _send_again(signum)
            return
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    if getattr(sys.unraisablehook, "redelivers_stops", False):
        return
    dropped = sys.unraisablehook

    def redeliver(unraisable) -> None:
        exc = unraisable.exc_value
        if isinstance(exc, KeyboardInterrupt):
            _send_again(signal.SIGTERM if stop_cause(exc) == "SIGTERM" else signal.SIGINT)
        else:
            dropped(unraisable)

    redeliver.redelivers_stops = True
    sys.unraisablehook = redeliver


#: Seconds after which a stop signal that could not be raised is sent again.
STOP_REDELIVERY = 0.05


def _send_again(signum: int) -> None:
    threading.Timer(STOP_REDELIVERY, os.kill, (os.getpid(), signum)).start()


def _critical(frame) -> bool:
    """Whether ``frame`` (the main thread's, where a signal handler runs) is inside an import or
    the start of a worker process, where a KeyboardInterrupt does harm: a module left
    half-initialised (JAX's C++ extensions aborted the interpreter at exit), or a spawned worker
    that reads a truncated start-up message and prints a traceback."""
    while frame is not None:
        name = frame.f_code.co_filename
        if name.startswith("<frozen importlib") or name == _SPAWN_FILE:
            return True
        frame = frame.f_back
    return False


#: Where multiprocessing hands a spawned worker its start-up message.
_SPAWN_FILE = os.path.join(os.path.dirname(multiprocessing.__file__), "popen_spawn_posix.py")


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
    from reelbench.benchmark.core.report import shorten

    return shorten(f"{type(exc).__name__}: {exc}", 300)


# ------------------------------------------------------------------------------------------
# Progress
# ------------------------------------------------------------------------------------------
#: The progress bar drawn on stderr, if any: `log_stderr` writes its lines above it.
_bar = None


class Progress:
    """Collects the rows of a list of jobs as they finish, in any order, and gives them back in
    job order. Each finished row is logged (``[done/total] <describe(row)>  (elapsed, ETA)``) and
    ``on_row`` gets the rows so far (to write partial results atomically), so a stopped run keeps
    every finished row. ``rows`` are jobs already done (resumed); they count in the total.

    The ETA is measured and weighted by each job's predicted cost ``cost(i)`` (s; e.g. a method's
    declared `cost_hint`, compilation on the first job of a group): the predicted cost left over
    the rate at which predicted cost has been done, in wall time since the jobs started
    (`restart_clock`: not the setup's). A job without a prediction counts as the mean of the
    others; without any, every job counts as one. A progress bar (tqdm, its total the predicted
    costs) is drawn below the lines when they go to a terminal (`log_stderr`); in a CI log or a
    file there are only the lines."""

    def __init__(self, total: int, *, rows: dict[int, dict] | None = None, finish: Callable | None = None,
                 describe: Callable[[dict], str] = str, on_row: Callable[[list[dict]], None] | None = None,
                 log: Callable[[str], None] = log_stderr, cost: Callable[[int], float] | None = None):
        self.total, self.rows = total, dict(rows or {})
        self.finish, self.describe, self.on_row, self.log = finish, describe, on_row, log
        predicted = [cost(i) for i in range(total)] if cost else [1.0] * total
        known = [c for c in predicted if math.isfinite(c) and c >= 0]
        fill = sum(known) / len(known) if known else 1.0
        self.weight = [c if math.isfinite(c) and c >= 0 else fill for c in predicted]
        if not sum(self.weight):  # no job predicted to take any time: count jobs
            self.weight = [1.0] * total
        self.bar = None
        self.restart_clock(draw=False)

    def restart_clock(self, draw: bool = True) -> None:
        """Count elapsed time and the rate from now (the jobs start: the setup is over), so the
        ETA is not the setup's; the bar is drawn from now on (the setup's workers write lines
        of their own, which a bar would break)."""
        global _bar
        from tqdm import tqdm

        self.close()
        drawn = draw and self.log is log_stderr and sys.stderr.isatty()
        # not drawn: an endless delay keeps the counts and never writes (no carriage returns in a log)
        self.bar = tqdm(total=sum(self.weight), initial=sum(self.weight[i] for i in self.rows), file=sys.stderr,
                        delay=0 if drawn else math.inf, desc=self._jobs(), leave=False, smoothing=0,
                        mininterval=0, miniters=1, bar_format="{desc} {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]")
        if drawn:
            _bar = self.bar
        self.start = time.perf_counter()

    def _jobs(self) -> str:
        return f"{len(self.rows)}/{self.total} jobs"

    def seconds_left(self) -> float | None:
        """The estimate of the wall time left (None until a job has finished since the clock started)."""
        done = self.bar.n - self.bar.initial
        return (self.bar.total - self.bar.n) * (time.perf_counter() - self.start) / done if done > 0 else None

    def done(self, i: int, row: dict) -> None:
        if self.finish:
            self.finish(i, row)
        self.rows[i] = row
        self.bar.set_description_str(self._jobs(), refresh=False)
        self.bar.update(self.weight[i])
        elapsed = time.perf_counter() - self.start
        left = self.seconds_left() if len(self.rows) < self.total else None
        eta = f", about {left:.0f} s left" if left is not None else ""
        self.saved()  # on disk first: a row printed as finished is never lost to a stop that follows
        self.log(f"[{len(self.rows)}/{self.total}] {self.describe(row)}  ({elapsed:.0f} s elapsed{eta})")

    def close(self) -> None:
        """Take the bar away (the lines stay)."""
        global _bar
        if self.bar is not None:
            if _bar is self.bar:
                _bar = None
            self.bar.close()

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
        if self.estimate is not None and self.estimate > self.every:  # a long run says at once that it started
            self.log(f"{self.what}: started; estimated {self.estimate:.0f} s, a line every {self.every:.0f} s")
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
    setup_labels: Iterable[str] | None = None,
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
    from a cache; each logs a line when it is done (``setup_labels``: what each is). ``crash_row(i,
    exc)``: the row of a job whose worker died (without it, the death is raised). ``finish(i,
    row)`` completes a row before it is logged. ``cost(i)``: a job's predicted seconds (the
    longest groups start first, and the ETA weighs the jobs by it: `Progress`)."""
    if crash_row is None:
        crash_row = _raise
    progress = Progress(len(jobs), rows=done, finish=finish, describe=describe, on_row=on_row, log=log, cost=cost)
    try:
        todo = [i for i in range(len(jobs)) if i not in progress.rows]
        if progress.rows:
            progress.saved()
        if not todo:
            return progress.ordered()
        setup = _Setup(list(setup), setup_labels, progress, log)
        if scheduler:
            _run_on_dask(fn, jobs, todo, scheduler, setup, crash_row, progress)
        elif workers == 0:
            for k, call in enumerate(setup.calls):
                call()
                setup.finished(k)
            setup.over()
            for batch in _batches(todo, group, cost):
                for i in batch:
                    progress.done(i, fn(jobs[i]))
        else:
            _run_in_workers(fn, jobs, _batches(todo, group, cost), workers, setup, crash_row, progress)
        return progress.ordered()
    finally:
        progress.close()


def _raise(i: int, exc: BaseException) -> dict:
    raise exc


class _Setup:
    """The setup calls of a list of jobs, and a progress line as each finishes."""

    def __init__(self, calls: list, labels, progress: Progress, log):
        self.calls, self.progress, self.log = calls, progress, log
        self.labels = list(labels) if labels is not None else [f"setup {k + 1}" for k in range(len(calls))]
        self.done = 0
        self.t0 = time.perf_counter()

    def finished(self, k: int) -> None:
        self.done += 1
        self.log(f"[{self.done}/{len(self.calls)}] {self.labels[k]} ready  ({time.perf_counter() - self.t0:.0f} s)")

    def over(self) -> None:
        """The jobs start now: their elapsed time and ETA count from here."""
        self.progress.restart_clock()


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
        futures = {pools[k % len(pools)].submit(call): k for k, call in enumerate(setup.calls)}
        for fut in cf.as_completed(futures):
            fut.result()
            setup.finished(futures[fut])
        setup.over()
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
        submitted = [client.submit(call, pure=False) for call in setup.calls]
        for k, fut in enumerate(submitted):
            fut.result()
            setup.finished(k)
        setup.over()
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
