"""Stability map: how large a step each integrator can take on each hard scene.

    python -m benchmark stability [--scenes ...] [--integrators ...] [--jobs N] [--out DIR]

* Fixed-step methods (the LGVI, diffrax Tsit5 at a constant step) walk a **ladder** of step
  sizes dt = DT_MAX / 2^k, largest first, and stop at the first rung whose run stays bounded
  over the horizon: its status is "ok" (or "length_limit" on the scenes that are meant to end
  at a length limit). That rung is the *largest stable dt* of the map (resolution: a factor 2;
  the rung above it is reported with the status that ended it). This assumes stability is
  monotone in dt, which holds for every ladder here (each rung above the stable one failed).
* Adaptive methods run once at ``ADAPTIVE_RTOL`` / ``ADAPTIVE_ATOL`` and report their step
  statistics: accepted and rejected steps, min / median / mean step, status, cost.

Every run is a `benchmark.runs.sweep.Task` executed by `benchmark.runs.runner.run_task` (no reference
solution: the map is about staying bounded, the conservation metrics come from the run itself),
so a failing run is a row with its status and reason, and an exception is a row with status
"error". One (scene, integrator, kind) row is one `Job` on the engine (`benchmark.core.engine`:
the jobs of one (scene, integrator) in one worker, so it compiles once; longest groups first by
`_cost_hint`; a dead worker's job is a "crashed" row; Ctrl-C / SIGTERM stop it and keep the rows
done). As a study on the one runner (`study`, `benchmark.core.study.run`) its rows merge into
``stability.csv`` atomically after each job (one row per scene, integrator and kind: the map's
other rows are kept); the table, plot and README of `benchmark.studies.stability_report` are
written from the whole map.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np
import pandas as pd

from reelbench.benchmark.core import engine
from reelbench.benchmark.runs.metrics import CONSERVATION
from reelbench.benchmark.core.store import frame
from reelbench.benchmark.core.study import KEY_COLUMN
from reelbench.benchmark.runs.sweep import Task
from reelbench.benchmark.studies import budget as _budget
from reelbench.integrators.base import CRASHED, ERROR, FINISHED_STATUSES, RETRY_STATUSES, Status

#: Largest step of the fixed-step ladder (s) and the number of halvings tried below it.
DT_MAX = 0.04
LADDER_RUNGS = 12  # down to 0.04 / 2^11 ≈ 2e-5 s
ADAPTIVE_RTOL = 1e-6
ADAPTIVE_ATOL = 1e-8
#: The status of a row the map does not run (`skip_reason`): a status of this table only.
SKIPPED = "skipped"
SAVED_POINTS = 100  # per run: the energy guard is checked at these (LGVI, scipy)

def implicit_baseline(integ) -> bool:
    """An implicit *baseline* (declares IMPLICIT, not VARIATIONAL): its Jacobian or Newton compiles
    through the ODE model per scene. The LGVIs are implicit too, but structured."""
    from reelbench.integrators import Capability

    return integ.has(Capability.IMPLICIT) and not integ.has(Capability.VARIATIONAL)


def default_integrators() -> list[str]:
    """The map's default methods: those of the default sweep (`benchmark.runs.sweep.default_names`:
    the project's own registered methods; a plugin joins when named), implicit baselines last
    (their jobs are the longest)."""
    from reelbench.benchmark.runs.sweep import default_names
    from reelbench.integrators import get_integrator

    return sorted(default_names(), key=lambda n: implicit_baseline(get_integrator(n)))


def adaptive_only(integ) -> bool:
    """An adaptive method that cannot take a constant step (declares ADAPTIVE, not FIXED_STEP)."""
    from reelbench.integrators import Capability

    return integ.has(Capability.ADAPTIVE) and not integ.has(Capability.FIXED_STEP)


def also_fixed_step(integ) -> bool:
    """An adaptive method that also takes a constant step (Tsit5): the map runs it both ways."""
    from reelbench.integrators import Capability

    return integ.has(Capability.ADAPTIVE) and integ.has(Capability.FIXED_STEP)


def kinds(name: str) -> list[str]:
    """The map's kinds of ``name`` from its declared capabilities: "fixed" (a dt ladder) for
    FIXED_STEP, "adaptive" (one tolerance) for ADAPTIVE; Tsit5 has both."""
    from reelbench.integrators import Capability, get_integrator

    integ = get_integrator(name)
    return [k for k, cap in (("fixed", Capability.FIXED_STEP), ("adaptive", Capability.ADAPTIVE)) if integ.has(cap)]


@dataclass(frozen=True)
class Case:
    """One hard scene in the map: horizon, overrides that keep it short, what counts as bounded."""

    scene: str
    horizon: float
    bounded: tuple[str, ...] = FINISHED_STATUSES
    overrides: tuple = ()
    #: s: a run that ends (with a bounded status) before this was thrown there by an instability,
    #: not carried there by the physics; 0: any end time
    earliest_end: float = 0.0
    #: shorter horizons for some methods: selector -> (s, reason), or (selector, kind) for one
    #: kind only; a selector is a function of the integrator (its declared capabilities, or this
    #: study's own table such as `EXPENSIVE`), true when it applies. The first that applies wins.
    short: dict = field(default_factory=dict)
    #: integrators left out of this scene: selectors, functions of the integrator returning the
    #: reason written into the table (or None), see `skip_reason`
    skip: tuple = ()
    #: left out of the default run only (``--integrators`` naming them runs them), same form
    default_skip: tuple = ()
    note: str = ""


_STEPS_500 = "adaptive-only baseline: 500 s at rtol 1e-6 is ~1e5 steps, minutes per run"
#: On the O(N) closed-form right-hand side the implicit baselines compile in seconds and run on
#: the hard scenes; on the 1,927-dimensional many_elements state each of their steps still
#: factorises a dense Jacobian (O(n^3)), so implicit baselines get a shorter horizon there, and a
#: method of `EXPENSIVE` (kvaerno5) stays out of the two stiff, large scenes.
_DENSE_LU = "implicit baseline: a dense LU of the 1,927 x 1,927 Jacobian per step (O(n^3))"
#: The methods whose cost is prohibitive on the two stiff, large scenes, and why (measured): the
#: default run leaves them out there; ``--integrators`` naming one runs it. Any other method,
#: a plugin included, runs on every scene.
EXPENSIVE = {
    # measured 2026-11-30 (one core): 0.2 s of stiff_string had not finished after 6 min
    "kvaerno5": "re-forms its Jacobian at every Newton iteration (0.2 s of stiff_string ran over 6 min here)",
}


def _expensive(integ) -> str | None:
    """Default run: leave out a method of `EXPENSIVE` on this scene."""
    why = EXPENSIVE.get(integ.name)
    return f"default run: {integ.name} {why}; run it with --integrators {integ.name}" if why else None


CASES = (
    Case("stiff_string", 0.2, note="EA = 20 kN, N = 40",
         short={implicit_baseline: (0.05, "implicit baseline: a Newton solve with LU per step on a stiff string")},
         default_skip=(_expensive,)),
    Case("many_elements", 1.0, note="N = 320", short={implicit_baseline: (0.05, _DENSE_LU)},
         default_skip=(_expensive,)),
    Case("fast_spin", 2.0, note="|Omega0| = 30 rad/s"),
    # every adaptive method at rtol 1e-6 reaches the 2 m limit at 1.10 s and the 39 m end at 2.10 s
    # (measured); a fixed-step run at an unstable step was seen "reaching" the limit at 0.05 s
    Case("retrieval_to_limit", 10.0, bounded=(Status.LENGTH_LIMIT.value,), overrides=(("deployed_length", 3.0),), earliest_end=0.55,
         note="started at 3 m (scene: 15 m) to reach the 2 m limit sooner; bounded = ends with length_limit at t >= 0.55 s"),
    Case("deployment_to_end", 10.0, bounded=(Status.LENGTH_LIMIT.value,), overrides=(("deployed_length", 36.0),), earliest_end=1.05,
         note="started at 36 m (scene: 3 m) to reach the 39 m limit sooner; bounded = ends with length_limit at t >= 1.05 s"),
    Case("long_horizon", 500.0, note="the scene's full 500 s for the fixed-step methods",
         short={implicit_baseline: (20.0, "implicit baseline: 500 s is ~1e5 steps with a Newton solve each"),
                adaptive_only: (20.0, _STEPS_500),
                (also_fixed_step, "adaptive"): (100.0, "adaptive at rtol 1e-6 it needs > 1e5 steps (its default "
                                                       "step budget) for 500 s")}),
    Case("near_slack", 2.0, note="string compressed by 5 % at t = 0"),
    # measured (dopri5): bounded at 10 ms without the water, diverged at 10 ms and bounded at 5 ms with it
    Case("strong_drag", 2.0, note="3 m/s current: drag rate rho d C_n |u| / mu ~ 500 1/s > the elastic 126 rad/s"),
)


def _horizon(case: Case, integrator: str, kind: str = "adaptive") -> tuple[float, str]:
    """(horizon, why it is shorter than the case's): the first `Case.short` selector (or
    (selector, kind)) that applies to the integrator's declared capabilities."""
    if case.short:
        from reelbench.integrators import get_integrator

        integ = get_integrator(integrator)
        for key, value in case.short.items():
            select, only = key if isinstance(key, tuple) else (key, kind)
            if only == kind and select(integ):
                return value
    return case.horizon, ""


def skip_reason(case: Case, integrator: str, default_run: bool = True) -> str | None:
    """Why ``integrator`` is left out of ``case`` (`Case.skip`, and `Case.default_skip` in the
    default run), or None when it runs."""
    selectors = case.skip + (case.default_skip if default_run else ())
    if not selectors:
        return None
    from reelbench.integrators import get_integrator

    integ = get_integrator(integrator)
    return next((r for r in (sel(integ) for sel in selectors) if r), None)


def ladder(case: Case, integrator: str) -> list[Task]:
    """The fixed-step ladder of one (scene, integrator), largest dt first."""
    horizon, _ = _horizon(case, integrator, "fixed")
    save_every = horizon / SAVED_POINTS
    dts = [DT_MAX / 2 ** k for k in range(LADDER_RUNGS)]
    dts = [dt for dt in dts if dt <= horizon / 10] or dts[-1:]  # at least 10 steps per run
    return [Task(case.scene, integrator, dt=dt, t_end=horizon, save_every=save_every, overrides=case.overrides)
            for dt in dts]


def adaptive_task(case: Case, integrator: str) -> Task:
    horizon, _ = _horizon(case, integrator)
    return Task(case.scene, integrator, rtol=ADAPTIVE_RTOL, atol=ADAPTIVE_ATOL, t_end=horizon,
                save_every=horizon / SAVED_POINTS, overrides=case.overrides)


def _base_row(case: Case, integrator: str, kind: str) -> dict:
    horizon, why = _horizon(case, integrator, kind)
    return {"scene": case.scene, "integrator": integrator, "kind": kind, "horizon": horizon,
            "horizon_note": why, "overrides": ", ".join(f"{k}={v}" for k, v in case.overrides)}


class Job(NamedTuple):
    """One row of the map: a case, an integrator, its kind ("fixed": a dt ladder; "adaptive": one
    tolerance), and whether it belongs to the default run (then `Case.default_skip` applies)."""

    case: Case
    integrator: str
    kind: str
    default_run: bool = True
    budget: "runner.SolveBudget | None" = None  # of each solve; None: the default (`runner.SolveBudget`)


def is_bounded(case: Case, r: dict) -> bool:
    """Whether a run stayed bounded on ``case``: a status it counts as bounded, reached no earlier
    than the physics allows (`Case.earliest_end`)."""
    return r["status"] in case.bounded and not (r.get("t_reached", np.inf) < case.earliest_end)


def _climb(case: Case, integrator: str, budget) -> tuple[dict, dict]:
    """Walk the ladder down to the first bounded rung: (the row's ladder columns, the run shown:
    that rung, or the last one tried when none stays bounded)."""
    tried, stable, above = 0, None, None
    from reelbench.benchmark.runs import runner  # JAX: only when a job runs

    for task in ladder(case, integrator):
        r = runner.run_task(task, repeats=0, reference=False, finished=case.bounded, budget=budget)
        tried += 1
        if is_bounded(case, r):
            stable = r
            break
        above = r
    cols = {"rungs_tried": tried, "largest_stable_dt": stable["dt"] if stable is not None else np.nan}
    if above is not None:
        cols.update(first_unstable_dt=above["dt"], unstable_status=above["status"], unstable_reason=above["reason"])
    return cols, stable if stable is not None else above


def run_job(job: Job) -> dict:
    """One row of the map: a whole ladder (kind "fixed") or one adaptive run. Never raises."""
    case, integrator, kind, default_run = job[:4]
    t0 = time.perf_counter()
    row = _base_row(case, integrator, kind)
    why = skip_reason(case, integrator, default_run)
    if why:
        row.update(status=SKIPPED, reason=why, bounded=False)
        return row
    try:
        if kind == "fixed":
            cols, r = _climb(case, integrator, _budget.of(job.budget))
            row.update(cols)
        else:
            from reelbench.benchmark.runs import runner  # JAX: only when a job runs

            r = runner.run_task(adaptive_task(case, integrator), repeats=0, reference=False, finished=case.bounded,
                                budget=_budget.of(job.budget))
        row.update({k: r.get(k, np.nan) for k in (
            "setting", "status", "reason", "steps", "rejected_steps", "min_step", "median_step", "newton_iterations",
            "run_time", "compile_time", *CONSERVATION, "t_reached")})
        row["bounded"] = is_bounded(case, r)
        steps = row.get("steps")
        if steps is not None and np.isfinite(steps) and steps > 0:
            row["mean_step"] = row["t_reached"] / steps
    except Exception as exc:  # one bad job must not lose the other rows
        row.update(status=ERROR, reason=f"{type(exc).__name__}: {exc}".splitlines()[0][:300], bounded=False)
    row["job_time"] = time.perf_counter() - t0
    return row


#: the map's table; its metrics are the registry's that need no reference (`metrics.CONSERVATION`)
COLUMNS = ["scene", "integrator", "kind", "horizon", "bounded", "largest_stable_dt", "first_unstable_dt",
           "unstable_status", "setting", "status", "steps", "rejected_steps", "min_step", "median_step", "mean_step",
           "newton_iterations", *CONSERVATION, "run_time", "compile_time", "job_time",
           "rungs_tried", "t_reached", "overrides", "horizon_note", "reason", "unstable_reason", KEY_COLUMN]


def to_frame(rows: list[dict]) -> pd.DataFrame:
    return frame(rows, COLUMNS, extra=False)


def jobs_for(scenes=None, integrators=None) -> list[Job]:
    from reelbench.integrators import get_integrator

    names = list(integrators) if integrators else default_integrators()
    for n in names:
        get_integrator(n)  # unknown names raise before any work
    cases = [c for c in CASES if scenes is None or c.scene in scenes]
    if scenes is not None:
        unknown = set(scenes) - {c.scene for c in CASES}
        if unknown:
            raise ValueError(f"no stability case for scene(s) {', '.join(sorted(unknown))} "
                             f"(allowed: {', '.join(c.scene for c in CASES)})")
    out = []
    for case in cases:
        for n in names:
            out += [Job(case, n, kind, not integrators) for kind in kinds(n)]
    return out


def describe(row: dict) -> str:
    """A finished job in the progress log."""
    what = (f"largest stable dt {row.get('largest_stable_dt'):.3g} s" if row.get("kind") == "fixed"
            and np.isfinite(row.get("largest_stable_dt", np.nan)) else f"{row.get('status')}")
    return (f"{row['scene']} {row['integrator']} ({row['kind']}): {what}, "
            f"{row.get('steps', float('nan')):.0f} steps, job {row.get('job_time', float('nan')):.0f} s")


def crash_row(job: Job, exc: BaseException) -> dict:
    """The row of a job whose worker died."""
    return {**_base_row(job.case, job.integrator, job.kind), "status": CRASHED, "reason": engine.crash_reason(exc),
            "bounded": False}


def execute(jobs: list[Job], *, workers: int | None = None, on_rows: Callable | None = None,
            log: Callable[[str], None] = engine.log_stderr) -> pd.DataFrame:
    """Run the jobs on the engine (``workers`` = 0: in this process); rows in job order. The
    jobs of one (scene, integrator) run in one worker, so it compiles that method on that scene
    once (Tsit5's ladder and adaptive run share it); the longest groups start first (`_cost_hint`).
    ``workers`` None: one per group (`engine.default_workers`)."""
    if workers is None:
        workers = engine.default_workers(len({_group(j) for j in jobs}))
    rows = engine.run_jobs(run_job, jobs, workers=workers, crash_row=lambda i, exc: crash_row(jobs[i], exc),
                           group=lambda i: _group(jobs[i]), cost=lambda i: _cost_hint(jobs[i]),
                           describe=describe, on_row=on_rows, log=log)
    return to_frame(rows)


#: A row of the map: one per scene, integrator and kind (a dt ladder or one tolerance).
IDENTITY = ("scene", "integrator", "kind")


def key(job: Job) -> str:
    """What determines a row of the map: the case's scene physics (its overrides applied) and
    horizon, the method, its kind and run, the budget (`budget.key_settings`), the code."""
    from reelbench.benchmark.core.study import job_key
    from reelbench.models import load_scene

    case = job.case
    return job_key({"scene": load_scene(case.scene, **dict(case.overrides)).key(), "case": case.scene,
                    "horizon": case.horizon, "integrator": job.integrator, "kind": job.kind,
                    "default_run": job.default_run, **_budget.key_settings(job.budget)},
                   "benchmark/studies/stability.py")


def _reusable(row: dict) -> bool:
    """A row of the map is a result whatever its run's status, unless the cause may have been
    transient (`RETRY_STATUSES`: a crash, an error, a wall-clock budget on a loaded machine)."""
    return str(row.get("status", "")) not in RETRY_STATUSES


def study(scenes=None, integrators=None, *, workers: int | None = None, budget=None):
    """The stability map as a study of `benchmark.core.study.run`: stability.csv (merged with the
    map already in the output, written after every job; a rerun keeps a row of the same `key`),
    stability.md, stability.png and README.md
    from the whole map. Unknown names are refused here, before any work. ``workers``: None, one
    per scene and method (`engine.default_workers`); ``budget``: of each solve (None: the defaults)."""
    from reelbench.benchmark.core.study import Study

    jobs = [j._replace(budget=budget) for j in jobs_for(scenes, integrators)]
    if workers is None:
        workers = engine.default_workers(len({_group(j) for j in jobs}))
    return Study(name="stability map", table="stability.csv", identity=IDENTITY, jobs=jobs, run_job=run_job,
                 identity_of=lambda j: (j.case.scene, j.integrator, j.kind), frame=to_frame, report=write_outputs,
                 describe=describe, crash_row=crash_row, group=_group, cost=_cost_hint, workers=workers,
                 key=key, reusable=_reusable)


def write_outputs(out, rows: list[dict], provenance) -> str:
    """stability.md, stability.png and README.md of the whole map (``rows``)."""
    from pathlib import Path

    from reelbench.benchmark.core.report import markdown_table
    from reelbench.benchmark.studies import stability_report
    from reelbench.models.io import atomic_write_text

    out = Path(out)
    merged = to_frame(rows)
    atomic_write_text(out / "stability.md", markdown_table(merged.drop(columns=[KEY_COLUMN])))
    stability_report.plot(merged, out)
    stability_report.write_readme(out, merged, provenance=provenance)
    return f"see {out}/README.md"


def _group(job: Job) -> tuple:
    """The jobs of one (scene, integrator) run in one worker: one compile."""
    return job.case.scene, job.integrator


def _cost_hint(job: Job) -> float:
    """Rough job cost, to start the longest jobs first (compilation dominates the short ones)."""
    from reelbench.integrators import get_integrator

    case, integrator, kind, default_run = job[:4]
    if skip_reason(case, integrator, default_run):
        return 0.0
    compile_s, per_step = get_integrator(integrator).cost_hint  # declared by each method
    horizon, _ = _horizon(case, integrator, kind)
    per_s = {"stiff_string": 200, "many_elements": 400}.get(case.scene, 1)
    return compile_s + horizon * per_s * per_step
