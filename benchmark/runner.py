"""The runner only composes: scenes × integrators × settings -> metrics rows.

Each task runs in a worker process (or a Dask worker): one solve for the errors, then a
separate timing pass (minimum wall time over repeats, compilation excluded). A failed or
diverged run becomes a row with its status; an exception inside a task becomes a row with
status "error"; a crashed worker becomes a row with status "crashed". The sweep goes on.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Callable, Hashable, Iterable

import numpy as np
import pandas as pd

from benchmark.metrics import ACCURACY, COLUMNS, run_metrics, work_evals
from benchmark.reference import CACHE_DIR, get_reference
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


def worker_pool(workers: int) -> cf.ProcessPoolExecutor:
    """The process pool every sweep uses: spawned workers (JAX does not survive fork), one XLA
    thread each (`_worker_env`)."""
    _worker_env()
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))


def crash_reason(exc: BaseException) -> str:
    """The `reason` of a row whose worker died (status "crashed")."""
    return f"{type(exc).__name__}: {exc}"[:300]


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
) -> pd.DataFrame:
    """Run ``tasks`` and return the runs table (task order). ``on_row`` gets the rows so far
    after each completion (used to write partial results atomically).

    ``group`` (process executor): tasks with the same ``group(task)`` run in one worker, one
    after another, so what that worker compiled for the first (JAX solves are cached per
    model and solver) serves the others; e.g. ``lambda t: (t.scene, t.integrator)``."""
    if executor not in ("process", "serial", "dask"):
        raise ValueError(f"executor = {executor!r} is invalid (allowed: process, serial, dask)")
    jobs = jobs or min(len(tasks), os.cpu_count() or 1) or 1
    refs = sorted({(t.scene, t.overrides, t.t_end, t.save_every) for t in tasks}, key=str)
    rows: dict[int, dict] = {}
    start = time.perf_counter()

    def done(i: int, row: dict) -> None:
        rows[i] = row
        status = row["status"]
        extra = f"{row['run_time']:.3g} s" if status == "ok" else f"{status}: {row['reason']}"[:120]
        log(f"[{len(rows)}/{len(tasks)}] {row['scene']} {row['integrator']} {row['setting']}: {extra}"
            f"  ({time.perf_counter() - start:.0f} s elapsed)")
        if on_row:
            on_row([rows[k] for k in sorted(rows)])

    if executor == "serial":
        for ref in refs:
            log(f"reference: {ref[0]} ...")
            _reference_task(*ref, cache_dir)
        for i, t in enumerate(tasks):
            done(i, run_task(t, cache_dir, repeats))
    elif executor == "process":
        with worker_pool(jobs) as pool:
            log(f"references for {len(refs)} scene(s) ...")
            for fut in [pool.submit(_reference_task, *ref, cache_dir) for ref in refs]:
                fut.result()
            batches: dict = {}
            for i, t in enumerate(tasks):
                batches.setdefault(group(t) if group else i, []).append(i)
            futures = {pool.submit(run_tasks, [tasks[i] for i in idx], cache_dir, repeats): idx
                       for idx in batches.values()}
            for fut in cf.as_completed(futures):
                idx = futures[fut]
                try:
                    batch_rows = fut.result()
                except Exception as exc:  # the worker process died
                    batch_rows = [{**_empty_row(tasks[i]), "status": "crashed", "reason": crash_reason(exc)} for i in idx]
                for i, row in zip(idx, batch_rows):
                    done(i, row)
    else:
        try:
            from distributed import Client, as_completed
        except ImportError:
            raise ValueError("executor 'dask' needs the optional dependency: pip install 'reelbench[dask]'") from None
        if not scheduler:
            raise ValueError("executor 'dask' needs --scheduler ADDRESS (e.g. tcp://host:8786)")
        client = Client(scheduler)
        for fut in [client.submit(_reference_task, *ref, cache_dir, pure=False) for ref in refs]:
            fut.result()
        futures = {client.submit(run_task, t, cache_dir, repeats, pure=False): i for i, t in enumerate(tasks)}
        index = {f.key: i for f, i in futures.items()}
        for fut in as_completed(list(futures)):
            i = index[fut.key]
            try:
                row = fut.result()
            except Exception as exc:
                row = _empty_row(tasks[i])
                row.update(status="crashed", reason=crash_reason(exc))
            done(i, row)
    return to_frame([rows[k] for k in sorted(rows)])


def to_frame(rows: Iterable[dict]) -> pd.DataFrame:
    df = pd.DataFrame(list(rows))
    for c in COLUMNS:
        if c not in df:
            df[c] = np.nan
    df = df[COLUMNS + [c for c in df.columns if c not in COLUMNS]]
    # a number that is not backed by a finished run is not reported
    df.loc[df["status"] != "ok", ACCURACY] = np.nan
    return df
