"""The answer's jobs and how each runs: a search (`run_search`, one row of ``search.csv``) and a
paired timing (`run_timing`, one row of ``timing.csv``).

1. **search**: one job per scene × N × method × step axis × target runs
   `benchmark.answer.search.search` on ``run(setting) -> (status, error, cost)``: one solve, its
   metric against the reference read at the saved times (`benchmark.core.reference.reference_at`),
   its cost in flops (`benchmark.work.flops`, the work unit the methods are ranked by); a run beyond
   a sanity bound is ``inaccurate`` (`benchmark.runs.metrics.INACCURATE`), not finished. The jobs of
   one scene × N × method run in one worker (`search_group`), so a setting one target ran is not run
   again for another (`_SOLVED`) and a new step size compiles nothing (`integrators.fixed_step`).
2. **timing**: one job per scene × N × target times the compiled methods that met it, each at its
   setting there, paired and interleaved on one pinned core (`benchmark.answer.paired`).
   scipy's methods (``implementation`` "scipy-python") are left out of the wall-time ranking:
   their time is the interpreter's between right-hand-side calls.

A search bit-identical to another's is one computation, ranked and timed once (`twins`).
"""

from __future__ import annotations

import functools
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from reelbench.benchmark.core import engine
from reelbench.benchmark.answer import paired as _paired
from reelbench.benchmark.answer import search as _search
from reelbench.benchmark.core.policy import PAIRED_BUDGET, SAVE_EVERY, SEARCH_TIME_LIMIT, Setting

if TYPE_CHECKING:
    import pandas as pd

#: The search's range and start per axis: (start, lowest, highest, factor). dt: seconds; a
#: step above 0.1 s is beyond every shipped method's stability on these scenes (the search
#: would say "largest setting"); rtol: the adapters' own range, 1e-13 above the reference's 1e-12.
AXES = {"dt": (0.005, 1e-5, 0.1, 2.0), "rtol": (1e-6, 1e-13, 1e-1, 10.0)}


@dataclass(frozen=True)
class SearchJob:
    scene: str
    elements: int
    integrator: str
    sweep: str  # "dt" or "rtol"
    metric: str
    target: float
    t_end: float | None = None
    max_runs: int = _search.MAX_RUNS
    max_steps: int | None = None  # each solve's budget (`answer --max-steps`, `--time-limit`): a
    time_limit: float = SEARCH_TIME_LIMIT  # setting past it is not finished (finer settings cost more)


@dataclass(frozen=True)
class TimingJob:
    scene: str
    elements: int
    metric: str
    target: float
    candidates: tuple  # ((integrator, sweep, setting), ...)
    t_end: float | None = None
    budget: float = PAIRED_BUDGET


def _scene(name: str, elements: int, t_end: float | None):
    from reelbench.models import load_scene

    return load_scene(name, elements=int(elements), **({"t_end": t_end} if t_end is not None else {}))


def solve_kwargs(sweep: str, setting: float, t_end: float) -> dict:
    """A search's or a timing's solve of ``setting`` on axis ``sweep`` (the sweep's save interval)."""
    return {"t_end": t_end, "save_every": SAVE_EVERY, **Setting.on_axis(sweep, setting).solve_kwargs()}


#: The solves this worker ran: (scene, N, t_end, method, axis, setting) -> (status, metrics, cost,
#: column, seconds).
_SOLVED: dict = {}
#: The references this worker read: (scene, N, t_end, cache) -> trajectory.
_REFERENCES: dict = {}


def _solve_once(job: SearchJob, setting: float, cache_dir: str) -> tuple[str, dict, float, str, dict]:
    """(status, every accuracy metric, flops, the cost column, its seconds: the solve's run and
    compile time and the rest, metrics and flops) of one setting, solved once per worker."""
    key = (job.scene, job.elements, job.t_end, job.integrator, job.sweep, float(setting), job.max_steps, job.time_limit)
    if key in _SOLVED:
        return _SOLVED[key]
    from reelbench.benchmark.work.flops import run_flops
    from reelbench.benchmark.runs.metrics import INACCURATE, inaccurate_reason, run_metrics
    from reelbench.benchmark.core.reference import get_reference
    from reelbench.integrators import get_integrator
    from reelbench.integrators.base import Status, is_finished
    from reelbench.models import build_model

    scene = _scene(job.scene, job.elements, job.t_end)
    t_end = scene.t_end
    ref_key = (job.scene, job.elements, job.t_end, cache_dir)
    if ref_key not in _REFERENCES:  # read (and its checksum verified) once per worker
        _REFERENCES[ref_key] = get_reference(scene, t_end, SAVE_EVERY, Path(cache_dir), log=None)
    ref = _REFERENCES[ref_key]
    started = time.perf_counter()
    try:
        traj = get_integrator(job.integrator).solve(scene, max_steps=job.max_steps, time_limit=job.time_limit,
                                                    **solve_kwargs(job.sweep, setting, t_end))
    except ValueError:  # a setting the method refuses (e.g. dt beyond t_end): not finished
        out = (Status.FAILED.value, {}, math.nan, "flops", {})
        _SOLVED[key] = out
        return out
    model = build_model(scene)
    metrics = run_metrics(scene, traj, ref, SAVE_EVERY)
    status = traj.status
    if is_finished(status) and inaccurate_reason(metrics, scene):  # finished, but no solution: not a point
        status = INACCURATE
    flops, _ = run_flops(job.integrator, model, traj.stats, traj.stats.get("rhs", traj.settings.get("rhs")),
                         adaptive=job.sweep == "rtol")
    cost, column = (flops, "flops") if np.isfinite(flops) else (float(traj.stats.get("steps", math.nan)), "steps")
    run, compiling = (float(traj.stats.get(k) or 0.0) for k in ("wall_time", "compile_time"))
    seconds = {"run_time": run, "compile_time": compiling,
               "other_time": max(0.0, time.perf_counter() - started - run - compiling)}
    out = (status, metrics, float(cost), column, seconds)
    _SOLVED[key] = out
    return out


def run_search(job: SearchJob, cache_dir: str) -> dict:
    """One search job's row (`SEARCH_COLUMNS`); a failure inside is a row with bound "error"."""
    from reelbench.benchmark.runs.runner import implementation

    row = {**asdict(job), "implementation": implementation(job.integrator)}
    row.pop("max_runs"), row.pop("t_end")
    started = time.perf_counter()
    try:
        start, lowest, highest, factor = AXES[job.sweep]
        columns, points = set(), []

        def run(setting):
            status, metrics, cost, column, seconds = _solve_once(job, setting, cache_dir)
            columns.add(column)
            points.append({"setting": setting, "status": status, "cost": cost, "cost_column": column,
                           **seconds, **metrics})
            return status, metrics.get(job.metric, math.nan), cost

        found = _search.search(run, job.target, start, lowest=lowest, highest=highest, factor=factor,
                               grid=_search.GRID[job.sweep], max_runs=job.max_runs)
        row.update(setting=found.setting, cost=found.cost, error=found.error, setting_low=found.setting_low,
                   setting_high=found.setting_high, setting_finer=found.setting_finer, high_status=found.high_status,
                   bound=found.bound, runs=found.runs, spread=found.spread, confirmed=found.confirmed,
                   erratic_above=found.erratic_above,
                   cost_column="flops" if columns == {"flops"} else "+".join(sorted(columns)),
                   note=_search_note(job.sweep, found), points=json.dumps(points, default=float))
    except Exception as exc:  # a bug in one search must not lose the others
        from reelbench.integrators.base import ERROR  # here: the command line's start loads no integrator

        row.update(bound=ERROR, note=f"{type(exc).__name__}: {exc}"[:300])
    row["job_time"] = time.perf_counter() - started  # the progress line's ETA learns from it
    return row


def _search_note(sweep: str, found) -> str:
    """What a reader must know of a search's answer: a lucky setting above it, or none confirmed."""
    if math.isfinite(found.erratic_above):
        return (f"the error was erratic above this setting: {setting_text(sweep, found.erratic_above)} met the "
                "target but a setting just finer did not")
    if math.isfinite(found.setting) and not found.confirmed:
        return f"not confirmed: the runs ran out before the {_search.CONFIRM} settings just finer were run"
    if found.non_monotone:
        return "non-monotone: a finer setting missed the target"
    return ""


def run_timing(job: TimingJob, log: Callable[[str], None] = engine.log_stderr) -> dict:
    """One timing job's row: the paired ratios (`benchmark.answer.paired`) as JSON in ``ratios``."""
    from reelbench.benchmark.runs.ranking import entry_name
    from reelbench.benchmark.core.report import one_minute_load
    from reelbench.integrators import get_integrator

    row = {k: v for k, v in asdict(job).items() if k not in ("candidates", "t_end", "budget")}
    scene = _scene(job.scene, job.elements, job.t_end)
    solves = {}
    two_axes = {i for i, _, _ in job.candidates if sum(c[0] == i for c in job.candidates) > 1}
    for integrator, sweep, setting in job.candidates:
        integ, kw = get_integrator(integrator), solve_kwargs(sweep, setting, scene.t_end)
        first = integ.solve(scene, **kw)  # compiles; its time is not a sample
        if not first.ok:
            continue
        solves[entry_name(integrator, sweep, integrator in two_axes)] = functools.partial(_wall_time, integ, scene, kw)
    if not solves:
        return {**row, "ratios": "[]", "rounds": 0, "seconds": 0.0, "note": "no candidate finished"}
    started = time.perf_counter()
    with _paired.pinned() as core:
        ratios = _paired.time_paired(solves, budget=job.budget)
    row.update(ratios=json.dumps([asdict(r) for r in ratios]), rounds=ratios[0].pairs,
               seconds=time.perf_counter() - started, core=core, load_avg=one_minute_load(),
               note="" if _paired.resolved(ratios) else f"the budget ended before every interval was within ±{_paired.PRECISION * 100:g} %")
    return row


def _wall_time(integ, scene, kw) -> float:
    return float(integ.solve(scene, **kw).stats["wall_time"])


def setting_text(sweep: str, v: float) -> str:
    """A setting's label (`Setting.label`, four digits); "" for none."""
    return Setting.on_axis(sweep, v).label(digits=4) if np.isfinite(v) else ""


# ------------------------------------------------------------------------------------------
# The jobs of a run
# ------------------------------------------------------------------------------------------
def search_jobs(scenes, integrators, targets, elements, t_end=None, max_runs=_search.MAX_RUNS,
                max_steps: int | None = None, time_limit: float = SEARCH_TIME_LIMIT):
    """Every scene × N × method × axis its capabilities allow × target; each solve within
    ``max_steps`` (None: no cap) and ``time_limit`` s."""
    from reelbench.integrators import Capability, get_integrator

    jobs = []
    for scene in scenes:
        for n in elements:
            for name in integrators:
                integ = get_integrator(name)
                axes = [a for a, cap in (("dt", Capability.FIXED_STEP), ("rtol", Capability.ADAPTIVE)) if integ.has(cap)]
                for axis in axes:
                    for metric, target in targets:
                        jobs.append(SearchJob(scene, int(n), name, axis, metric, float(target), t_end, max_runs,
                                              max_steps, float(time_limit)))
    return jobs


#: What two searches must share, bit for bit, to be one computation ranked once (`twins`).
TWIN_COLUMNS = ("sweep", "setting", "setting_low", "setting_high", "error", "cost", "runs")


def twins(g: pd.DataFrame) -> dict[tuple[str, str], str]:
    """(integrator, sweep) -> the method it is ranked as, for every search of one scene × N ×
    metric × target that is bit-identical to another's in `TWIN_COLUMNS` (the same bracket,
    the same error and flops at the same setting after the same number of runs: e.g. ``lgvi_sym``
    and ``lgvi`` at fixed length, one trajectory). Of such a group the method first in
    `benchmark.runs.sweep.PRESENTATION_ORDER` is ranked; a search that reached nothing is never a twin."""
    import pandas as pd

    from reelbench.benchmark.runs.ranking import presentation_rank

    out = {}
    found = g[pd.to_numeric(g["setting"], errors="coerce").notna()]
    for _, h in found.groupby(list(TWIN_COLUMNS), sort=False, dropna=False):
        names = sorted(h["integrator"], key=presentation_rank)
        for other in names[1:]:
            out[(other, h["sweep"].iloc[0])] = names[0]
    return out


def timing_jobs(searched: pd.DataFrame, t_end=None, budget=PAIRED_BUDGET) -> list[TimingJob]:
    """One per scene × N × metric × target: the compiled entries that met it (a method with a
    fixed-step and an adaptive axis is two entries, like with like), each at its searched setting;
    a search bit-identical to another's (`twins`) is timed once, as the method ranked."""
    out = []
    ok = searched[searched["setting"].notna() & (searched["implementation"] != "scipy-python")]
    for (scene, n, metric, target), g in ok.groupby(["scene", "elements", "metric", "target"], sort=True):
        same = twins(g)
        cands = tuple(sorted((r.integrator, r.sweep, float(r.setting)) for r in g.itertuples()
                             if (r.integrator, r.sweep) not in same))
        out.append(TimingJob(scene, int(n), metric, float(target), cands, t_end, budget))
    return out


def search_crash_row(job: SearchJob, exc: BaseException) -> dict:
    """The row of a search whose worker died."""
    from reelbench.integrators.base import CRASHED  # here: the command line's start loads no integrator

    return {**asdict(job), "bound": CRASHED, "note": engine.crash_reason(exc)}


def search_group(job: SearchJob) -> tuple:
    """The searches of one scene × N × method run in one worker: one compile, shared solves."""
    return job.scene, job.elements, job.integrator


def references(jobs: list[SearchJob], cache_dir: str) -> list[tuple[str, Callable]]:
    """(label, call) of each reference the searches ``jobs`` read, computed once before them (two
    workers never compute the same one)."""
    from reelbench.benchmark.core.reference import ReferenceProblem, prepare_reference

    problems = sorted({ReferenceProblem(j.scene, (("elements", j.elements),) + ((("t_end", j.t_end),) if j.t_end else ()),
                                        j.t_end, SAVE_EVERY) for j in jobs}, key=str)
    return [(f"reference {p.scene} N={dict(p.overrides)['elements']}",
             functools.partial(prepare_reference, p, cache_dir)) for p in problems]


def describe_search(row: dict) -> str:
    what = (f"{row['setting']:.4g} ({row['bound']}, {row['runs']} runs)" if np.isfinite(row.get("setting", np.nan))
            else f"{row['bound']}")
    return f"search {row['scene']} N={row['elements']} {row['integrator']} {row['sweep']} {row['metric']} <= " \
           f"{row['target']:g}: {what}"


def describe_timing(row: dict) -> str:
    ratios = json.loads(row.get("ratios") or "[]")
    best = f"{ratios[0]['method']} {ratios[0]['verdict']}" if ratios else "nothing timed"
    return f"timing {row['scene']} N={row['elements']} {row['metric']} <= {row['target']:g}: {best} " \
           f"({row.get('rounds', 0)} rounds)"


#: Predicted solves of one search, and seconds of one at N = 10 per unit of a method's declared
#: per-step cost (`Integrator.cost_hint`): a first guess the progress line's ETA corrects per method.
SOLVES_PER_SEARCH = 12
SOLVE_SECONDS = 0.05


def search_costs(jobs: list[SearchJob]) -> list[float]:
    """Predicted seconds of each search: the method's declared compile time on the first search of
    its (scene, N, method) group, then its solves, scaled by N (scipy's by its interpreter factor)."""
    from reelbench.benchmark.runs.runner import method_cost

    seen, out = set(), []
    for j in jobs:
        compile_s, per_step = method_cost(j.integrator)
        group = (j.scene, j.elements, j.integrator)
        first = group not in seen
        seen.add(group)
        out.append((compile_s if first else 0.0) + SOLVES_PER_SEARCH * SOLVE_SECONDS * per_step * j.elements / 10.0)
    return out

