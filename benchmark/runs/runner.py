"""The runs table: one task (scene × integrator × setting, `benchmark.runs.sweep.Task`) -> one row
of status, cost and metrics, and a list of tasks -> the table, on the engine.

Each task runs in a worker process (or a Dask worker, or this process): one solve for the
errors, within a step and wall-clock budget (`SolveBudget`: a run past it ends with status
``max_steps`` / ``time_limit`` and the sweep goes on), then a separate timing pass (compilation
excluded) of `timing_repeats` solves within `benchmark.runs.sweep.TIMING_BUDGET`, without the budget
(the first solve showed the run ends, and a wall-clock budget would split a fixed-step loop into
chunks, so the solves timed would not be the same work as the other methods'): ``run_time`` is their median, ``run_time_low`` the fastest,
``run_time_high`` the 90th percentile (10 or more solves) or the slowest, ``timing_repeats``
their count and ``load_avg`` the machine's 1-minute load when the row finished (timings on a
loaded machine are inflated). ``us_per_eval`` is the run time per right-hand-side evaluation
(``run_time / rhs_evals``; empty where a method counts none, e.g. the LGVI, which evaluates no
right-hand side), ``implementation`` the method's declared kind ("jax-compiled" or
"scipy-python"), ``flops`` the run's floating-point operations from XLA's cost model times its
counts (`benchmark.work.flops`; the one-unit work axis) and ``flops_note`` how they were counted,
or why a row has none.

A failed or diverged run becomes a row with its status; a run that finished with an error
beyond a sanity bound becomes a row with status "inaccurate" (`benchmark.runs.metrics.INACCURATE`:
no accuracy values, not timed again, no point of any curve); an exception inside a task becomes a row
with status "error"; a crashed worker becomes a row with status "crashed". The sweep goes on.
Rows of an earlier run with the same `run_key` that pass `benchmark.runs.table.check_row` are kept,
the rest computed.
"""

from __future__ import annotations

import functools
import math
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Hashable, Iterable

import numpy as np
import pandas as pd

from reelbench.benchmark.core import engine
from reelbench.benchmark.work.flops import run_flops
from reelbench.benchmark.core.policy import SOLVE_MAX_STEPS, SOLVE_TIME_LIMIT
from reelbench.benchmark.runs.metrics import ACCURACY, COLUMNS, INACCURATE, inaccurate_reason, run_metrics, work_evals
from reelbench.benchmark.core.reference import CACHE_DIR, ReferenceProblem, get_reference, prepare_reference
from reelbench.benchmark.core.report import one_minute_load, shorten
from reelbench.benchmark.core.store import code_version, frame, key_of
from reelbench.benchmark.runs.table import row_digest, run_key
from reelbench.benchmark.runs.sweep import DEFAULT_EXECUTOR, EXECUTORS, MAX_REPEATS, MIN_REPEATS, TIMING_BUDGET, Task
from reelbench.integrators.base import CRASHED, ERROR, FINISHED_STATUSES, is_finished

#: Step statistics some integrators report (`Trajectory.stats`), copied into the row when present.
STEP_STATS = ("rejected_steps", "min_step", "median_step", "max_step", "max_newton_iterations")
#: Columns after `benchmark.runs.metrics.COLUMNS`: the timing spread and the implementation ...
TIMING_COLUMNS = ["implementation", "run_time_low", "run_time_high", "timing_repeats", "load_avg", "us_per_eval",
                  "flops", "flops_note", "task_time"]
#: ... and a row's identity: the scene's physics hash, the resume key and the row's digest, and
#: whose method it is: its package and version and the code digest its resume key covers
#: (`provenance`).
IDENTITY_COLUMNS = ["scene_key", "run_key", "row_digest", "package", "package_version", "code_digest"]
RUN_COLUMNS = COLUMNS + TIMING_COLUMNS + IDENTITY_COLUMNS


@dataclass(frozen=True)
class SolveBudget:
    """The budget of a run's first solve (`integrators.base.Integrator.solve`'s ``max_steps`` and
    ``time_limit``); `benchmark.core.policy` holds the defaults, the commands' --max-steps and
    --time-limit raise them."""

    max_steps: int = SOLVE_MAX_STEPS
    time_limit: float = SOLVE_TIME_LIMIT

    def solve_kwargs(self) -> dict:
        return {"max_steps": self.max_steps, "time_limit": self.time_limit}


def _scene(task: Task):
    from reelbench.models import load_scene

    return load_scene(task.scene, **dict(task.overrides))


def empty_row(task: Task, scene=None) -> dict:
    row = {c: np.nan for c in COLUMNS}
    row.update(scene=scene.name if scene is not None else task.scene, integrator=task.integrator,
               setting=task.setting, dt=task.dt, rtol=task.rtol, atol=task.atol,
               t_end=task.t_end if task.t_end is not None else (scene.t_end if scene is not None else np.nan),
               reason="", implementation=implementation(task.integrator),
               scene_key=scene.key() if scene is not None else "")
    return row


def implementation(name: str) -> str:
    """The integrator's declared implementation ("jax-compiled", "scipy-python"), "" when it
    declares none (or is not registered)."""
    from reelbench.integrators import get_integrator

    try:
        return str(getattr(get_integrator(name), "implementation", "") or "")
    except ValueError:
        return ""


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


def timing_repeats(first: float, least: int = MIN_REPEATS, budget: float = TIMING_BUDGET,
                   most: int = MAX_REPEATS) -> int:
    """How many timed solves a run gets: clamp(floor(budget / first), least, most), and one
    (the first) when the first solve alone takes the budget or is not a number."""
    if not (np.isfinite(first) and first < budget):
        return 1
    if first <= 0:
        return max(least, most)
    fits = math.floor(budget / first * (1 + 1e-12))  # 2 / 0.1 is 20 solves, not 2 // 0.1 = 19
    return int(min(max(most, least), max(least, fits)))


def timing_summary(times) -> dict:
    """The timing columns of a run from its timed solves (s): median, min, the 90th percentile
    (10 or more solves) or the max, and their count."""
    t = np.asarray([v for v in times if np.isfinite(v)], float)
    if not len(t):
        return {"run_time": np.nan, "run_time_low": np.nan, "run_time_high": np.nan, "timing_repeats": 0}
    high = float(np.percentile(t, 90)) if len(t) >= 10 else float(t.max())
    return {"run_time": float(np.median(t)), "run_time_low": float(t.min()), "run_time_high": high,
            "timing_repeats": len(t)}


def _timing(first: float, repeat: Callable[[], float], least: int) -> dict:
    """The timing pass: the first solve (compiled beforehand, compile time excluded, run within
    its budget) sets how many, then `timing_repeats` solves of the same work are the samples. A
    first solve as long as the whole timing budget is its own sample: nothing is solved twice to
    be timed (its budget checks cost nothing next to it: `integrators.lifecycle`)."""
    n = timing_repeats(first, least)
    if n == 1 and np.isfinite(first) and first > 0:
        return timing_summary([first])
    return timing_summary([repeat() for _ in range(n)])


def us_per_eval(run_time: float, evals: float) -> float:
    """Microseconds of run time per right-hand-side evaluation; NaN without a count."""
    if np.isfinite(run_time) and np.isfinite(evals) and evals > 0:
        return 1e6 * run_time / evals
    return np.nan


def run_task(task: Task, cache_dir: str = str(CACHE_DIR), repeats: int = MIN_REPEATS, *, reference: bool = True,
             finished=FINISHED_STATUSES, budget: SolveBudget = SolveBudget()) -> dict:
    """Run one task; always returns a row (never raises for a failed run).

    ``repeats``: the least timed solves of a run (`timing_repeats`); 0 times the first solve
    only. ``reference=False`` skips the reference solution (no position/attitude errors);
    ``finished`` are the statuses whose runs get conservation metrics (default: "ok" only);
    ``budget`` bounds the first solve.
    """
    started = time.perf_counter()
    loaded = []  # the scene, once it loaded (an error row still names it)
    try:
        row = _solved_row(task, cache_dir, repeats, reference, finished, loaded, budget)
    except Exception as exc:  # a bug in one task must not lose the other rows
        row = empty_row(task, loaded[0] if loaded else None)
        row.update(status=ERROR, reason=shorten(f"{type(exc).__name__}: {exc}".splitlines()[0], 300))
        row["traceback"] = traceback.format_exc()[-2000:]
    row.update(load_avg=one_minute_load(), task_time=time.perf_counter() - started)
    return row


def _solved_row(task: Task, cache_dir: str, repeats: int, reference: bool, finished, loaded: list,
                budget: SolveBudget) -> dict:
    from reelbench.integrators import get_integrator
    from reelbench.models import build_model

    scene = _scene(task)
    loaded.append(scene)
    row = empty_row(task, scene)
    t_end = task.t_end if task.t_end is not None else scene.t_end
    ref = get_reference(scene, t_end, task.save_every, Path(cache_dir)) if reference else None
    integ = get_integrator(task.integrator)
    kw = {**task.solve_kwargs(), "t_end": t_end}
    traj = integ.solve(scene, **kw, **budget.solve_kwargs())
    model = build_model(scene)
    row.update(_run_columns(traj, model.layout.ny))
    row["flops"], row["flops_note"] = run_flops(task.integrator, model, traj.stats, row["rhs"], adaptive=task.dt is None)
    row.update(run_metrics(scene, traj, ref, task.save_every, finished))
    inaccurate = inaccurate_reason(row, scene) if traj.ok else ""
    if inaccurate:  # finished, but no solution: no curve point, so not timed again
        row.update(status=INACCURATE, reason=inaccurate)
    if traj.ok and repeats > 0 and not inaccurate:  # timing pass, separate from the error computation
        again = lambda: integ.solve(scene, **kw).stats.get("wall_time", np.nan)  # noqa: E731
        row.update(_timing(row["run_time"], again, repeats))
    else:
        row.update(timing_summary([row["run_time"]]))
    row["us_per_eval"] = us_per_eval(row["run_time"], row["rhs_evals"])
    return row


def describe_run(row: dict) -> str:
    """A finished run in the progress log: scene, integrator, setting, run time or status (its
    reason shortened at a clause boundary; runs.csv has it in full)."""
    if is_finished(row["status"]):
        extra = f"{row['run_time']:.3g} s"
        if row.get("timing_repeats", 0) and row["timing_repeats"] > 1:
            extra += f" (median of {row['timing_repeats']}, {row['run_time_low']:.3g}–{row['run_time_high']:.3g})"
    else:
        extra = shorten(f"{row['status']}: {row['reason']}", 140)
    return f"{row['scene']} {row['integrator']} {row['setting']}: {extra}"


def runs_frame(rows: Iterable[dict]) -> pd.DataFrame:
    """Rows -> the runs table: `RUN_COLUMNS` first, then any other keys of the rows; a number
    not backed by a finished run (status "ok") is not reported."""
    df = frame(rows, RUN_COLUMNS)
    df.loc[~df["status"].isin(FINISHED_STATUSES), ACCURACY] = np.nan
    return df


#: Seconds of one explicit Runge-Kutta step at N = 10 (the unit of `Integrator.cost_hint`'s
#: per-step cost), and steps per simulated second of an adaptive run at rtol 1e-4 (order 5): a
#: rough first guess the progress line's ETA corrects with the measured rows.
STEP_SECONDS = 2e-5
ADAPTIVE_STEPS_PER_S = 50.0
#: A step of a "scipy-python" method costs this many compiled ones (the interpreter between the
#: right-hand-side calls: a --quick sweep at load 2.5-3.8 measured 280-1070 µs per evaluation for
#: scipy's DOP853 against 9-27 µs for diffrax's Tsit5).
PYTHON_STEP_FACTOR = 20.0


def method_cost(integrator: str) -> tuple[float, float]:
    """(seconds to compile, cost of a step relative to one of `STEP_SECONDS`) the method declares
    (`Integrator.cost_hint`; scipy's interpreted steps × `PYTHON_STEP_FACTOR`); an unknown or
    undeclared method is guessed dear (30 s, 1)."""
    from reelbench.integrators import get_integrator

    try:
        integ = get_integrator(integrator)
        compile_s, per_step = integ.cost_hint
        if getattr(integ, "implementation", "") == "scipy-python":
            per_step *= PYTHON_STEP_FACTOR
    except (ValueError, AttributeError, TypeError):
        compile_s, per_step = 30.0, 1.0
    return compile_s, per_step


def task_costs(tasks: list[Task]) -> list[float]:
    """Predicted seconds of each task in its worker: its method's declared compile time
    (`Integrator.cost_hint`) on the first task of each (scene, integrator), plus its steps at
    the declared per-step cost, times the timed solves (`timing_repeats`)."""
    seen, out = set(), []
    for t in tasks:
        compile_s, per_step = method_cost(t.integrator)
        horizon = t.t_end if t.t_end is not None else 10.0
        steps = horizon / t.dt if t.dt else horizon * ADAPTIVE_STEPS_PER_S * (1e-4 / t.rtol) ** 0.2
        solve = steps * per_step * STEP_SECONDS
        timed = solve * timing_repeats(solve)
        first = (t.scene, t.integrator) not in seen
        seen.add((t.scene, t.integrator))
        out.append((compile_s if first else 0.0) + solve + timed)
    return out


def provenance(name: str, code: str) -> dict:
    """Whose method ``name`` is: {"package", "package_version", "code_digest"}. The digest is
    the project's code version (`benchmark.core.store.code_version`, given as ``code``) and, for a
    plugin, that of the source file defining it too (`models.origin.source_digest`): a changed
    plugin's rows are recomputed on resume, like the project's."""
    from reelbench.integrators import origin, registry
    from reelbench.models.origin import source_digest

    try:
        where = origin(name)
    except ValueError:  # not registered: the task becomes an error row of its own
        return {"package": "", "package_version": "", "code_digest": code}
    digest = code if where.own else key_of(code, source_digest(registry._REGISTRY[name]))[:12]
    return {"package": where.package, "package_version": where.version, "code_digest": digest}


def finish_row(row: dict, key: str, origin: dict | None = None) -> dict:
    """A row as the table keeps it: no accuracy without a finished run, its resume key, the
    method's provenance and the digest of its deterministic columns (`benchmark.runs.table.row_digest`)."""
    if not is_finished(row.get("status")):
        row.update({k: np.nan for k in ACCURACY})
    row["run_key"] = key
    row.update(origin or {})
    row["row_digest"] = row_digest(row)
    return row


def execute(
    tasks: list[Task],
    *,
    jobs: int | None = None,
    executor: str = DEFAULT_EXECUTOR,
    scheduler: str | None = None,
    repeats: int = MIN_REPEATS,
    cache_dir: str = str(CACHE_DIR),
    on_row: Callable[[list[dict]], None] | None = None,
    log: Callable[[str], None] = engine.log_stderr,
    group: Callable[[Task], Hashable] | None = None,
    cost: Callable[[Task], float] | None = None,
    budget: SolveBudget = SolveBudget(),
) -> pd.DataFrame:
    """Run ``tasks`` on the engine and return the runs table (task order). ``on_row`` gets the
    rows so far after each completion (used to write partial results atomically). It keeps
    nothing of an earlier run: a study that resumes runs its tasks on the study runner
    (`benchmark.studies.grid`).

    ``executor``: "process" (``jobs`` worker processes), "serial" (this process) or "dask" (the
    cluster at ``scheduler``). ``group``: tasks with the same ``group(task)`` run in one worker,
    one after another, so what that worker compiled for the first (JAX solves are cached per
    model and solver) serves the others; e.g. ``lambda t: (t.scene, t.integrator)``. ``cost``:
    a task's expected seconds (default `task_costs`); the groups start longest first, and the
    progress line's ETA weighs the tasks by it. ``budget`` bounds each run's first solve
    (`SolveBudget`)."""
    if executor not in EXECUTORS:
        raise ValueError(f"executor = {executor!r} is invalid (allowed: {', '.join(EXECUTORS)})")
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs = {jobs!r} is invalid (allowed: >= 1)")
    if executor == "dask" and not scheduler:
        raise ValueError("executor 'dask' needs --scheduler ADDRESS (e.g. tcp://host:8786)")
    code = code_version()
    origins = {name: provenance(name, code) for name in dict.fromkeys(t.integrator for t in tasks)}
    keys = [run_key(t, origins[t.integrator]["code_digest"]) for t in tasks]
    problems = sorted({ReferenceProblem(t.scene, t.overrides, t.t_end, t.save_every) for t in tasks}, key=str)
    if tasks:
        log(f"references for {len(problems)} scene(s) ...")
    costs = [cost(t) for t in tasks] if cost else task_costs(tasks)

    def crashed(i: int, exc: BaseException) -> dict:
        return {**empty_row(tasks[i]), "status": CRASHED, "reason": engine.crash_reason(exc)}

    rows = engine.run_jobs(
        functools.partial(run_task, cache_dir=cache_dir, repeats=repeats, budget=budget), tasks,
        workers=0 if executor == "serial" else (jobs or engine.default_workers(len(tasks))),
        scheduler=scheduler if executor == "dask" else None, crash_row=crashed,
        group=(lambda i: group(tasks[i])) if group else None, cost=lambda i: costs[i],
        setup=[functools.partial(prepare_reference, p, cache_dir) for p in problems],
        setup_labels=[f"reference {Path(p.scene).stem}" + (f" to t = {p.t_end:g} s" if p.t_end else "")
                      for p in problems],
        finish=lambda i, row: finish_row(row, keys[i], origins[tasks[i].integrator]), describe=describe_run, on_row=on_row, log=log)
    return runs_frame(rows)
