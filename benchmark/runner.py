"""The runs table: one task (scene × integrator × setting, `benchmark.sweep.Task`) -> one row
of status, cost and metrics, and a list of tasks -> the table, on the engine.

Each task runs in a worker process (or a Dask worker, or this process): one solve for the
errors, then a separate timing pass (minimum wall time over repeats, compilation excluded). A
failed or diverged run becomes a row with its status; an exception inside a task becomes a row
with status "error"; a crashed worker becomes a row with status "crashed". The sweep goes on.
Rows of an earlier run with the same `run_key` are kept (`benchmark.store`), the rest computed.
"""

from __future__ import annotations

import functools
import os
import time
import traceback
from pathlib import Path
from typing import Callable, Hashable, Iterable

import numpy as np
import pandas as pd

from benchmark import engine
from benchmark.metrics import ACCURACY, COLUMNS, run_metrics, work_evals
from benchmark.reference import CACHE_DIR, ReferenceProblem, get_reference, prepare_reference
from benchmark.store import code_version, frame, kept_rows, run_key
from benchmark.sweep import EXECUTORS, TIMING_BUDGET, Task

#: Step statistics some integrators report (`Trajectory.stats`), copied into the row when present.
STEP_STATS = ("rejected_steps", "min_step", "median_step", "max_step", "max_newton_iterations")


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


def _run_columns(traj, ny: int) -> dict:
    """The status, counters and cost of one solve, in the runs table's columns."""
    st = traj.stats
    cols = dict(
        status=traj.status, reason=traj.reason, rhs=st.get("rhs", traj.settings.get("rhs", "")),
        steps=st.get("steps", np.nan), rhs_evals=st.get("rhs_evals", np.nan),
        jac_evals=st.get("jac_evals", np.nan), lu_decompositions=st.get("lu_decompositions", np.nan),
        newton_iterations=st.get("newton_iterations", np.nan), work_evals=work_evals(st, ny),
        compile_time=st.get("compile_time", np.nan), run_time=st.get("wall_time", np.nan),
        t_reached=float(traj.t[-1]) if len(traj.t) else 0.0,
    )
    cols.update({k: st[k] for k in STEP_STATS if k in st})
    return cols


def _timing(first: float, repeat: Callable[[], float], repeats: int) -> dict:
    """The timing pass: the first solve (compiled beforehand, compile time excluded) is one
    sample; repeats are added while they fit in `TIMING_BUDGET`; the minimum is reported."""
    times = [first]
    spent = first if np.isfinite(first) else 0.0
    while len(times) <= repeats and spent < TIMING_BUDGET:
        t0 = time.perf_counter()
        times.append(repeat())
        spent += time.perf_counter() - t0
    return {"run_time": float(np.nanmin(times)), "run_time_median": float(np.nanmedian(times)),
            "timing_samples": len(times)}


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
        kw = {**task.solve_kwargs(), "t_end": t_end}
        traj = integ.solve(scene, **kw)
        row.update(_run_columns(traj, build_model(scene).layout.ny))
        row.update(run_metrics(scene, traj, ref, task.save_every, finished))
        if traj.ok and repeats > 0:  # timing pass, separate from the error computation
            again = lambda: integ.solve(scene, **kw).stats.get("wall_time", np.nan)  # noqa: E731
            row.update(_timing(row["run_time"], again, repeats))
        return row
    except Exception as exc:  # a bug in one task must not lose the other rows
        row = _empty_row(task, scene)
        row.update(status="error", reason=f"{type(exc).__name__}: {exc}".splitlines()[0][:300])
        row["traceback"] = traceback.format_exc()[-2000:]
        return row


def describe_run(row: dict) -> str:
    """A finished run in the progress log: scene, integrator, setting, run time or status."""
    extra = f"{row['run_time']:.3g} s" if row["status"] == "ok" else f"{row['status']}: {row['reason']}"[:120]
    return f"{row['scene']} {row['integrator']} {row['setting']}: {extra}"


def runs_frame(rows: Iterable[dict]) -> pd.DataFrame:
    """Rows -> the runs table: `COLUMNS` first, then any other keys of the rows; a number not
    backed by a finished run (status "ok") is not reported."""
    df = frame(rows, COLUMNS)
    df.loc[df["status"] != "ok", ACCURACY] = np.nan
    return df


def execute(
    tasks: list[Task],
    *,
    jobs: int | None = None,
    executor: str = "process",
    scheduler: str | None = None,
    repeats: int = 3,
    cache_dir: str = str(CACHE_DIR),
    on_row: Callable[[list[dict]], None] | None = None,
    log: Callable[[str], None] = engine.log_stderr,
    group: Callable[[Task], Hashable] | None = None,
    previous: Iterable[dict] | None = None,
    cost: Callable[[Task], float] | None = None,
) -> pd.DataFrame:
    """Run ``tasks`` on the engine and return the runs table (task order). ``on_row`` gets the
    rows so far after each completion (used to write partial results atomically).

    ``previous``: rows of an earlier run (`benchmark.store.read_previous`); a task whose
    `run_key` is among them keeps that row and is not run again.

    ``executor``: "process" (``jobs`` worker processes), "serial" (this process) or "dask" (the
    cluster at ``scheduler``). ``group``: tasks with the same ``group(task)`` run in one worker,
    one after another, so what that worker compiled for the first (JAX solves are cached per
    model and solver) serves the others; e.g. ``lambda t: (t.scene, t.integrator)``. ``cost``:
    a task's expected seconds; the groups start longest first."""
    if executor not in EXECUTORS:
        raise ValueError(f"executor = {executor!r} is invalid (allowed: {', '.join(EXECUTORS)})")
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs = {jobs!r} is invalid (allowed: >= 1)")
    if executor == "dask" and not scheduler:
        raise ValueError("executor 'dask' needs --scheduler ADDRESS (e.g. tcp://host:8786)")
    code = code_version()
    keys = [run_key(t, code) for t in tasks]
    kept = kept_rows(keys, previous)
    if kept:
        log(f"resuming: {len(kept)} of {len(tasks)} runs already done (kept); "
            f"computing the other {len(tasks) - len(kept)}")
    todo = [t for i, t in enumerate(tasks) if i not in kept]
    problems = sorted({ReferenceProblem(t.scene, t.overrides, t.t_end, t.save_every) for t in todo}, key=str)
    if todo:
        log(f"references for {len(problems)} scene(s) ...")

    def finish(i: int, row: dict) -> None:
        row["run_key"] = keys[i]

    def crashed(i: int, exc: BaseException) -> dict:
        return {**_empty_row(tasks[i]), "status": "crashed", "reason": engine.crash_reason(exc)}

    rows = engine.run_jobs(
        functools.partial(run_task, cache_dir=cache_dir, repeats=repeats), tasks,
        workers=0 if executor == "serial" else (jobs or min(len(todo), os.cpu_count() or 1) or 1),
        scheduler=scheduler if executor == "dask" else None, crash_row=crashed,
        group=(lambda i: group(tasks[i])) if group else None, cost=(lambda i: cost(tasks[i])) if cost else None,
        setup=[functools.partial(prepare_reference, p, cache_dir) for p in problems],
        done=kept, finish=finish, describe=describe_run, on_row=on_row, log=log)
    return runs_frame(rows)
