"""The runner only composes: scenes × integrators × settings -> metrics rows.

Each task runs in a worker process (or a Dask worker): one solve for the errors, then a
separate timing pass (minimum wall time over repeats, compilation excluded). A failed or
diverged run becomes a row with its status; an exception inside a task becomes a row with
status "error"; a crashed worker becomes a row with status "crashed". The sweep goes on.

Stopping and resuming: Ctrl-C or SIGTERM (`install_stop_handlers`) stops a sweep at once; the
pool's workers are terminated (`worker_pool`), and each worker also exits by itself when its
parent disappears (killed with -9), so none is left running. Every row carries a `run_key`
(scene physics hash, integrator, setting, horizon, code version); `execute(previous=...)`
keeps the rows of earlier runs with the same key and computes only the rest. `OutputLock`
keeps two sweeps from writing into one directory.

The engine (`run_jobs`, `Progress`, `to_frame`) is not specific to runs: the stability map
(`benchmark.stability`) runs its ladders on it too.
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import contextlib
import hashlib
import json
import multiprocessing
import os
import signal
import socket
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Callable, Hashable, Iterable

import numpy as np
import pandas as pd

from benchmark.metrics import ACCURACY, COLUMNS, run_metrics, work_evals
from benchmark.reference import CACHE_DIR, get_reference, source_hash
from benchmark.sweep import Task
from models._jax import append_xla_flags

#: s of repeated solves per task, at most. The first solve is always a sample; a run longer than
#: this gets no repeat (its timing noise is small next to its length), shorter ones up to `repeats`.
#: (10 s made the default job's tight-tolerance scipy runs twice as long for no ranking change.)
TIMING_BUDGET = 2.0


def _scene(task: Task):
    from models import load_scene

    return load_scene(task.scene, **dict(task.overrides))


def _empty_row(task: Task, scene=None) -> dict:
    row = {c: np.nan for c in COLUMNS}
    row.update(scene=scene.name if scene is not None else task.scene, integrator=task.integrator,
               setting=task.setting, dt=task.dt, rtol=task.rtol, atol=task.atol,
               t_end=task.t_end if task.t_end is not None else (scene.t_end if scene is not None else np.nan),
               reason="")
    return row


#: Step statistics some integrators report (`Trajectory.stats`), copied into the row when present.
STEP_STATS = ("rejected_steps", "min_step", "median_step", "max_step", "max_newton_iterations")


def run_task(task: Task, cache_dir: str = str(CACHE_DIR), repeats: int = 3, *, reference: bool = True,
             finished=("ok",)) -> dict:
    """Run one task; always returns a row (never raises for a failed run).

    ``reference=False`` skips the reference solution (no position/attitude errors);
    ``finished`` are the statuses whose runs get conservation metrics (default: "ok" only).
    """
    scene = None
    try:
        from integrators import get_integrator
        from models import build_model

        scene = _scene(task)
        row = _empty_row(task, scene)
        t_end = task.t_end if task.t_end is not None else scene.t_end
        ref = get_reference(scene, t_end, task.save_every, Path(cache_dir)) if reference else None
        integ = get_integrator(task.integrator)
        kw = task.solve_kwargs()
        kw["t_end"] = t_end
        traj = integ.solve(scene, **kw)
        st = traj.stats
        row.update(
            status=traj.status, reason=traj.reason, rhs=st.get("rhs", traj.settings.get("rhs", "")),
            steps=st.get("steps", np.nan), rhs_evals=st.get("rhs_evals", np.nan),
            jac_evals=st.get("jac_evals", np.nan), lu_decompositions=st.get("lu_decompositions", np.nan),
            newton_iterations=st.get("newton_iterations", np.nan),
            work_evals=work_evals(st, build_model(scene).layout.ny),
            compile_time=st.get("compile_time", np.nan), run_time=st.get("wall_time", np.nan),
            t_reached=float(traj.t[-1]) if len(traj.t) else 0.0,
        )
        row.update({k: st[k] for k in STEP_STATS if k in st})
        row.update(run_metrics(scene, traj, ref, task.save_every, finished))
        if traj.ok and repeats > 0:  # timing pass, separate from the error computation
            # The first solve (compiled beforehand, compile time excluded) is one sample;
            # repeats are added while they fit in the budget, and the minimum is reported.
            times = [row["run_time"]]
            spent = times[0] if np.isfinite(times[0]) else 0.0
            while len(times) <= repeats and spent < TIMING_BUDGET:
                t0 = time.perf_counter()
                times.append(integ.solve(scene, **kw).stats.get("wall_time", np.nan))
                spent += time.perf_counter() - t0
            row["run_time"] = float(np.nanmin(times))
            row["run_time_median"] = float(np.nanmedian(times))
            row["timing_samples"] = len(times)
        return row
    except Exception as exc:  # a bug in one task must not lose the other rows
        row = _empty_row(task, scene)
        row.update(status="error", reason=f"{type(exc).__name__}: {exc}".splitlines()[0][:300])
        row["traceback"] = traceback.format_exc()[-2000:]
        return row


def run_tasks(tasks: list[Task], cache_dir: str = str(CACHE_DIR), repeats: int = 3) -> list[dict]:
    """Run ``tasks`` one after another in this process (one row each)."""
    return [run_task(t, cache_dir, repeats) for t in tasks]


def _reference_task(scene_name: str, overrides: tuple, t_end, save_every: float, cache_dir: str) -> str:
    from models import load_scene

    scene = load_scene(scene_name, **dict(overrides))
    get_reference(scene, t_end if t_end is not None else scene.t_end, save_every, Path(cache_dir))
    return scene_name


def _worker_env() -> None:
    # One XLA thread per worker: the workers are the parallelism, and timings stay per-core.
    # appended: XLA_FLAGS already holds reelbench's own options (models._jax) and maybe a user's
    append_xla_flags(("--xla_cpu_multi_thread_eigen=false", "intra_op_parallelism_threads=1"))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


#: How often (s) a worker checks that its parent is still alive.
PARENT_POLL = 0.5


def _watch_parent(parent: int) -> None:
    while True:
        time.sleep(PARENT_POLL)
        if os.getppid() != parent:  # re-parented: the sweep's process is gone (e.g. kill -9)
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
    """The process pool every sweep uses: spawned workers (JAX does not survive fork), one XLA
    thread each (`_worker_env`), which ignore Ctrl-C, exit when the parent dies, and are
    terminated when the ``with`` block is left by an exception."""
    _worker_env()
    return _Pool(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                 initializer=_worker_init, initargs=(os.getpid(),))


def install_stop_handlers() -> None:
    """SIGTERM stops the process like Ctrl-C does (KeyboardInterrupt in the main thread), so
    one ``except KeyboardInterrupt`` handles both and the pool's workers are terminated.

    SIGINT gets Python's own handler back too: a process started from a background job of a
    script (``python -m benchmark run ... &``) inherits SIGINT *ignored*, and Python then never
    raises KeyboardInterrupt, so Ctrl-C / ``kill -INT`` would not stop the sweep (the Ctrl-C
    test waited out its 30 s timeout when pytest itself ran in such a job)."""

    def stop(signum, frame):
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, signal.default_int_handler)


# ------------------------------------------------------------------------------------------
# Resume: which rows of an earlier run belong to this sweep
# ------------------------------------------------------------------------------------------
_CODE_DIRS = ("models", "integrators")
_CODE_FILES = ("benchmark/runner.py", "benchmark/metrics.py", "benchmark/reference.py", "benchmark/sweep.py")


def code_version() -> str:
    """A hash of the source that determines a row (the model, the integrators, the metrics):
    rows computed by other code are recomputed on resume, never mixed in."""
    return source_hash(_CODE_DIRS, _CODE_FILES)


def run_key(task: Task, code: str | None = None) -> str:
    """Identity of a task's row: the scene's physics hash (not its name), the integrator, the
    setting, horizon and save interval, and the code version."""
    scene = _scene(task)
    what = {"scene": scene.key(), "integrator": task.integrator, "dt": task.dt, "rtol": task.rtol,
            "atol": task.atol, "t_end": task.t_end if task.t_end is not None else scene.t_end,
            "save_every": task.save_every, "code": code or code_version()}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


#: Rows with these statuses are recomputed on resume (the cause may have been transient).
RETRY_STATUSES = ("crashed", "error")


def read_previous(path: str | os.PathLike, log: Callable[[str], None] | None = None) -> list[dict]:
    """The rows of an earlier run's ``runs.csv`` that can be resumed from (none if the file is
    missing, unreadable or has no `run_key` column)."""
    path = Path(path)
    if not path.exists():
        return []
    try:
        df = pd.read_csv(path)
    except Exception as exc:  # a damaged table is not a reason to stop: start afresh
        if log:
            log(f"warning: {path} cannot be read ({type(exc).__name__}); its rows are recomputed")
        return []
    if "run_key" not in df or "status" not in df:
        return []
    df = df[~df["status"].isin(RETRY_STATUSES)]
    if "reason" in df:
        df["reason"] = df["reason"].fillna("")
    return df.to_dict("records")


# ------------------------------------------------------------------------------------------
# One writer per output directory
# ------------------------------------------------------------------------------------------
class LockedError(ValueError):
    """Another live process holds the output directory's lock."""


class OutputLock:
    """``with OutputLock(out):`` -- at most one sweep writes into ``out`` at a time.

    The lock is a file holding the owner's pid and host; a lock whose pid no longer runs on
    this host (a run killed with -9) is taken over."""

    NAME = ".reelbench.lock"

    def __init__(self, directory: str | os.PathLike, log: Callable[[str], None] | None = None):
        self.path = Path(directory) / self.NAME
        self.log = log
        self.held = False

    def _holder(self) -> dict | None:
        try:
            return json.loads(self.path.read_text())
        except (OSError, ValueError):
            return None

    @staticmethod
    def _alive(pid: int) -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # exists, owned by someone else
            return True
        return True

    def acquire(self) -> "OutputLock":
        me = {"pid": os.getpid(), "host": socket.gethostname(), "command": " ".join(sys.argv)}
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                holder = self._holder()
                if holder is None:  # half-written by a holder that is starting: give it a moment
                    time.sleep(0.2)
                    holder = self._holder() or {}
                pid, host = holder.get("pid"), holder.get("host")
                if isinstance(pid, int) and (host != socket.gethostname() or self._alive(pid)):
                    raise LockedError(
                        f"{self.path.parent}/ is in use by another run (pid {pid} on {host}: "
                        f"{holder.get('command', '?')}); lock file {self.path}. Wait for it to finish or "
                        f"use another --out; if that run is gone, delete the lock file") from None
                if self.log:
                    self.log(f"taking over the stale lock {self.path} (pid {pid} is not running)")
                try:
                    self.path.unlink()
                except FileNotFoundError:
                    pass
                continue
            with os.fdopen(fd, "w") as fh:
                json.dump(me, fh)
            self.held = True
            return self
        raise LockedError(f"could not take the lock {self.path}; delete it if no run is using {self.path.parent}/")

    def release(self) -> None:
        if self.held:
            holder = self._holder()
            if holder is None or holder.get("pid") == os.getpid():
                self.path.unlink(missing_ok=True)
            self.held = False

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def crash_reason(exc: BaseException) -> str:
    """The `reason` of a row whose worker died (status "crashed")."""
    return f"{type(exc).__name__}: {exc}"[:300]


class Progress:
    """Collects the rows of a list of jobs as they finish, in any order, and gives them back in
    job order. Each finished row is logged (``[done/total] <describe(row)>  (elapsed, ETA)``) and
    ``on_row`` gets the rows so far (to write partial results atomically), so a stopped run keeps
    every finished row. ``rows`` are jobs already done (resumed); they count in the total."""

    def __init__(self, total: int, *, rows: dict[int, dict] | None = None, finish: Callable | None = None,
                 describe: Callable[[dict], str] = str, on_row: Callable[[list[dict]], None] | None = None,
                 log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True)):
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


def run_jobs(
    fn: Callable[..., dict],
    jobs: list[tuple],
    *,
    workers: int,
    crash_row: Callable[[int, BaseException], dict],
    group: Callable[[int], Hashable] | None = None,
    cost: Callable[[int], float] | None = None,
    setup: Iterable[tuple] = (),
    done: dict[int, dict] | None = None,
    finish: Callable[[int, dict], None] | None = None,
    describe: Callable[[dict], str] = str,
    on_row: Callable[[list[dict]], None] | None = None,
    log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True),
) -> list[dict]:
    """The experiment engine the runs table and the stability map share: run ``fn(*jobs[i])``
    (a row, a dict) for every job not in ``done`` and return all rows in job order.

    ``workers`` = 0 runs the jobs in this process; otherwise each worker is a single-process pool
    (`worker_pool`: spawned, one XLA thread, terminated when the run is stopped). Jobs with the
    same ``group(i)`` go one after another to the same worker, so what it compiled for the first
    (JAX solves are cached per model and solver) serves the others; yet each job is its own future,
    so a row is saved (``on_row``) as soon as it is done and a stopped run keeps every finished row.
    Groups start longest first by the sum of ``cost(i)`` (so no worker is left with a long tail);
    without ``cost`` in the order of their first job. ``setup``: ``(function, *args)`` calls run
    first, spread over the workers, e.g. the reference solutions the jobs read from a cache.
    A worker that dies gives its job ``crash_row(i, exc)`` and is replaced for the next group.
    ``finish(i, row)`` completes a row before it is logged (`Progress`)."""
    progress = Progress(len(jobs), rows=done, finish=finish, describe=describe, on_row=on_row, log=log)
    todo = [i for i in range(len(jobs)) if i not in progress.rows]
    if progress.rows:
        progress.saved()
    batches: dict = {}
    for i in todo:
        batches.setdefault(group(i) if group else ("job", i), []).append(i)
    queue = list(batches.values())
    if cost is not None:
        queue.sort(key=lambda b: -sum(cost(i) for i in b))  # stable: ties keep their order
    setup = list(setup)
    if not todo:
        return progress.ordered()
    if workers == 0:
        for fn_args in setup:
            fn_args[0](*fn_args[1:])
        for batch in queue:
            for i in batch:
                progress.done(i, fn(*jobs[i]))
        return progress.ordered()
    queue = collections.deque(queue)
    with contextlib.ExitStack() as stack:
        pools = [stack.enter_context(worker_pool(1)) for _ in range(min(workers, len(queue)))]
        for fut in [pools[k % len(pools)].submit(*fn_args) for k, fn_args in enumerate(setup)]:
            fut.result()
        running: dict = {}  # future -> (pool index, job index)
        broken: set = set()

        def feed(k: int) -> None:
            if k in broken:  # its worker died: the next group gets a fresh one
                pools[k] = stack.enter_context(worker_pool(1))
                broken.discard(k)
            if queue:
                for i in queue.popleft():
                    running[pools[k].submit(fn, *jobs[i])] = (k, i)

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
    return progress.ordered()


def describe_run(row: dict) -> str:
    """A finished run in the progress log: scene, integrator, setting, run time or status."""
    extra = f"{row['run_time']:.3g} s" if row["status"] == "ok" else f"{row['status']}: {row['reason']}"[:120]
    return f"{row['scene']} {row['integrator']} {row['setting']}: {extra}"


def execute(
    tasks: list[Task],
    *,
    jobs: int | None = None,
    executor: str = "process",
    scheduler: str | None = None,
    repeats: int = 3,
    cache_dir: str = str(CACHE_DIR),
    on_row: Callable[[list[dict]], None] | None = None,
    log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True),
    group: Callable[[Task], Hashable] | None = None,
    previous: Iterable[dict] | None = None,
    cost: Callable[[Task], float] | None = None,
) -> pd.DataFrame:
    """Run ``tasks`` and return the runs table (task order). ``on_row`` gets the rows so far
    after each completion (used to write partial results atomically).

    ``previous``: rows of an earlier run (`read_previous`); a task whose `run_key` is among
    them keeps that row and is not run again.

    ``group`` (process executor): tasks with the same ``group(task)`` run in one worker, one
    after another, so what that worker compiled for the first (JAX solves are cached per
    model and solver) serves the others; e.g. ``lambda t: (t.scene, t.integrator)``.
    ``cost`` (process, serial): a task's expected seconds; the groups start longest first.
    The process and serial executors are `run_jobs`; the Dask one shares its `Progress`."""
    if executor not in ("process", "serial", "dask"):
        raise ValueError(f"executor = {executor!r} is invalid (allowed: process, serial, dask)")
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs = {jobs!r} is invalid (allowed: >= 1)")
    code = code_version()
    keys = [run_key(t, code) for t in tasks]
    kept_rows: dict[int, dict] = {}
    kept = {r["run_key"]: r for r in (previous or []) if r.get("run_key")}
    for i, k in enumerate(keys):
        if k in kept:
            kept_rows[i] = kept[k]
    if kept_rows:
        log(f"resuming: {len(kept_rows)} of {len(tasks)} runs already done (kept); "
            f"computing the other {len(tasks) - len(kept_rows)}")
    todo = [i for i in range(len(tasks)) if i not in kept_rows]
    jobs = jobs or min(len(todo), os.cpu_count() or 1) or 1
    refs = sorted({(tasks[i].scene, tasks[i].overrides, tasks[i].t_end, tasks[i].save_every) for i in todo}, key=str)

    def finish(i: int, row: dict) -> None:
        row["run_key"] = keys[i]

    def crashed(i: int, exc: BaseException) -> dict:
        return {**_empty_row(tasks[i]), "status": "crashed", "reason": crash_reason(exc)}

    common = dict(done=kept_rows, finish=finish, describe=describe_run, on_row=on_row, log=log)
    if executor in ("serial", "process"):
        if todo:
            log(f"references for {len(refs)} scene(s) ...")
        rows = run_jobs(run_task, [(t, cache_dir, repeats) for t in tasks], workers=0 if executor == "serial" else jobs,
                        crash_row=crashed, group=(lambda i: group(tasks[i])) if group else None,
                        cost=(lambda i: cost(tasks[i])) if cost else None,
                        setup=[(_reference_task, *ref, cache_dir) for ref in refs], **common)
        return to_frame(rows)
    progress = Progress(len(tasks), **{k: v for k, v in common.items() if k != "done"}, rows=kept_rows)
    if kept_rows:
        progress.saved()
    if not todo:
        return to_frame(progress.ordered())
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ValueError("executor 'dask' needs the optional dependency: pip install 'reelbench[dask]'") from None
    if not scheduler:
        raise ValueError("executor 'dask' needs --scheduler ADDRESS (e.g. tcp://host:8786)")
    client = Client(scheduler)
    futures = {}
    try:
        _dask_worker_env(client)
        for fut in [client.submit(_reference_task, *ref, cache_dir, pure=False) for ref in refs]:
            fut.result()
        futures = {client.submit(run_task, tasks[i], cache_dir, repeats, pure=False): i for i in todo}
        index = {f.key: i for f, i in futures.items()}
        for fut in as_completed(list(futures)):
            i = index[fut.key]
            try:
                row = fut.result()
            except Exception as exc:
                row = crashed(i, exc)
            progress.done(i, row)
    except BaseException:
        # a stopped sweep withdraws its tasks: the cluster's workers are not ours to kill
        client.cancel(list(futures), force=True)
        raise
    finally:
        client.close()
    return to_frame(progress.ordered())


def _dask_worker_env(client) -> None:
    """The pool's one-XLA-thread setting (`_worker_env`) on every Dask worker, also on workers
    that join or restart later (a worker plugin). It takes effect where JAX is not yet imported
    in the worker, i.e. before its first task."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class OneXlaThread(WorkerPlugin):
        name = "reelbench-one-xla-thread"

        def setup(self, worker):
            _worker_env()

    register = getattr(client, "register_plugin", None) or client.register_worker_plugin
    register(OneXlaThread())
    client.run(_worker_env)


def to_frame(rows: Iterable[dict], columns: list[str] | None = None, *, extra: bool = True) -> pd.DataFrame:
    """Rows -> a table with ``columns`` first, in that order (a column no row has is NaN), then
    (``extra``) any other keys of the rows. Without ``columns``: the runs table (`COLUMNS`), in
    which a number not backed by a finished run (status "ok") is not reported."""
    runs = columns is None
    columns = list(COLUMNS if runs else columns)
    df = pd.DataFrame(list(rows))
    for c in columns:
        if c not in df:
            df[c] = np.nan
    df = df[columns + ([c for c in df.columns if c not in columns] if extra else [])]
    if runs:
        df.loc[df["status"] != "ok", ACCURACY] = np.nan
    return df
