"""The answer: each method's cheapest setting at each target found by search, and wall-time
verdicts from paired timing, at one or more string sizes (N = 10 and N = 40 by default).

Two stages on the engine (`benchmark.core.engine`: worker processes, progress with a measured ETA,
stop signals, crash rows), each resumable like the sweep (`benchmark.core.store`: a row is written
atomically as soon as its job ends, and a rerun keeps every row whose key it finds):

1. **search** (``search.csv``): one job per scene × N × method × step axis × target runs
   `benchmark.answer.search.search` on ``run(setting) -> (status, error, cost)``: one solve, its
   metric against the reference read at the saved times (`benchmark.core.reference.reference_at`),
   its cost in flops (`benchmark.work.flops`, the work unit the methods are ranked by); a run beyond
   a sanity bound is ``inaccurate`` (`benchmark.runs.metrics.INACCURATE`), not finished. The jobs of
   one scene × N × method run in one worker, so a setting one target ran is not run again for
   another (`_SOLVED`) and a new step size compiles nothing (`integrators.fixed_step`).
2. **timing** (``timing.csv``): one job per scene × N × target times the compiled methods that
   met it, each at its setting there, paired and interleaved on one pinned core
   (`benchmark.answer.paired`), in this process one job after another (never two timings at once).
   scipy's methods (``implementation`` "scipy-python") are left out of the wall-time ranking:
   their time is the interpreter's between right-hand-side calls.

``cheapest.csv`` then holds one row per scene × N × metric × target × cost kind × method
(`answer_table`); `answer_lines` writes the README's answer block from it.
"""

from __future__ import annotations

import functools
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from reelbench.benchmark.core import engine
from reelbench.benchmark.answer import paired as _paired
from reelbench.benchmark.answer import search as _search
from reelbench.benchmark.core.policy import (BEST_VERDICTS, CHEAPEST_FILE, IDENTICAL, LOWER_BOUND, NO_FLOPS_COUNT, NOT_REACHED,
                                   PAIRED_BUDGET, RANKED_VERDICTS, RESULTS, SAVE_EVERY, SEARCH_TIME_LIMIT, SLOWER, TIE,
                                   Setting)
from reelbench.benchmark.core.store import code_version, frame, key_of
from reelbench.benchmark.runs.table import kept_rows
from reelbench.benchmark.runs.sweep import DEFAULT_EXECUTOR

#: The default targets: (metric, target, label); ``--targets`` asks for others, on any metric
#: of `benchmark.runs.metrics.METRICS`.
TARGETS = (("energy_error", 1e-4, "energy error (relative to max T)"),
           ("position_error_final", 1e-6, "body position error at t_end (m)"))
#: Methods the main job runs beside the default sweep's: the compiled eighth-order pair, which is
#: the fastest at the position targets of all three paper scenes at N = 10 (the extended
#: methods' trial, results/previous/extended_methods_trial.csv); an answer without it would
#: name a slower method.
MAIN_JOB_EXTRA = ("dopri8",)


def default_methods(extended: bool = False) -> tuple[str, ...]:
    """The methods the answer searches unless named: the project's own default-sweep methods and
    `MAIN_JOB_EXTRA`, or every own method (``extended``)."""
    from reelbench.benchmark.runs.sweep import EXTENDED_METHODS, default_names

    return tuple(n for n in default_names() if extended or n not in EXTENDED_METHODS or n in MAIN_JOB_EXTRA)


#: The string sizes of the main job, and of the extended answer.
ELEMENTS = (10,)
EXTENDED_ELEMENTS = (10, 40)
#: The search's range and start per axis: (start, lowest, highest, factor). dt: seconds; a
#: step above 0.1 s is beyond every shipped method's stability on these scenes (the search
#: would say "largest setting"); rtol: the adapters' own range, 1e-13 above the reference's 1e-12.
AXES = {"dt": (0.005, 1e-5, 0.1, 2.0), "rtol": (1e-6, 1e-13, 1e-1, 10.0)}

SEARCH_COLUMNS = ["scene", "elements", "integrator", "sweep", "metric", "target", "setting", "cost", "cost_column",
                  "error", "setting_low", "setting_high", "setting_finer", "high_status", "bound", "runs", "spread",
                  "confirmed", "erratic_above", "implementation", "note", "points", "job_time", "run_key", "row_digest"]
TIMING_COLUMNS = ["scene", "elements", "metric", "target", "ratios", "rounds", "seconds", "core", "load_avg",
                  "note", "run_key", "row_digest"]
#: Columns of cheapest.csv.
COLUMNS = ["scene", "elements", "metric", "target", "cost_kind", "integrator", "entry", "sweep", "setting", "setting_low",
           "setting_high", "bound", "cost", "cost_low", "cost_high", "ratio", "ratio_low", "ratio_high", "pairs",
           "verdict", "cost_column", "error", "runs", "note"]


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

    def key(self, code: str) -> str:
        return key_of("search", asdict(self), code)


@dataclass(frozen=True)
class TimingJob:
    scene: str
    elements: int
    metric: str
    target: float
    candidates: tuple  # ((integrator, sweep, setting), ...)
    t_end: float | None = None
    budget: float = PAIRED_BUDGET

    def key(self, code: str) -> str:
        return key_of("timing", asdict(self), code)


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
    key = (job.scene, job.elements, job.t_end, job.integrator, job.sweep, float(setting))
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
        traj = get_integrator(job.integrator).solve(scene, time_limit=SEARCH_TIME_LIMIT,
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
        return (f"the error was erratic above this setting: {_setting_text(sweep, found.erratic_above)} met the "
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


# ------------------------------------------------------------------------------------------
# The jobs of a study, and the study
# ------------------------------------------------------------------------------------------
def search_jobs(scenes, integrators, targets, elements=ELEMENTS, t_end=None, max_runs=_search.MAX_RUNS):
    """Every scene × N × method × axis its capabilities allow × target."""
    from reelbench.integrators import Capability, get_integrator

    jobs = []
    for scene in scenes:
        for n in elements:
            for name in integrators:
                integ = get_integrator(name)
                axes = [a for a, cap in (("dt", Capability.FIXED_STEP), ("rtol", Capability.ADAPTIVE)) if integ.has(cap)]
                for axis in axes:
                    for metric, target in targets:
                        jobs.append(SearchJob(scene, int(n), name, axis, metric, float(target), t_end, max_runs))
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


def _finish(row: dict, key: str) -> dict:
    row["run_key"] = key
    row["row_digest"] = _digest(row)
    return row


def _describe_search(row: dict) -> str:
    what = (f"{row['setting']:.4g} ({row['bound']}, {row['runs']} runs)" if np.isfinite(row.get("setting", np.nan))
            else f"{row['bound']}")
    return f"search {row['scene']} N={row['elements']} {row['integrator']} {row['sweep']} {row['metric']} <= " \
           f"{row['target']:g}: {what}"


def _describe_timing(row: dict) -> str:
    ratios = json.loads(row.get("ratios") or "[]")
    best = f"{ratios[0]['method']} {ratios[0]['verdict']}" if ratios else "nothing timed"
    return f"timing {row['scene']} N={row['elements']} {row['metric']} <= {row['target']:g}: {best} " \
           f"({row.get('rounds', 0)} rounds)"


def _code(*files: str) -> str:
    """The code a row of this study depends on: the runs' (`benchmark.core.store.code_version`) and ``files``."""
    from reelbench.benchmark.core.store import source_hash

    return key_of(code_version(), source_hash((), files))


#: The source a search row depends on beyond the runs' code, and a timing row.
SEARCH_CODE = ("benchmark/answer/answer.py", "benchmark/answer/search.py", "benchmark/work/flops.py")
TIMING_CODE = ("benchmark/answer/answer.py", "benchmark/answer/paired.py")


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


def run_search_stage(jobs: list[SearchJob], *, workers: int, cache_dir: str, previous=(), on_row=None,
                     scheduler: str | None = None, log=engine.log_stderr) -> pd.DataFrame:
    code = _code(*SEARCH_CODE)
    keys = [j.key(code) for j in jobs]
    kept = kept_rows(keys, previous)
    if kept:
        log(f"resuming: {len(kept)} of {len(jobs)} searches already done (kept)")
    from reelbench.benchmark.core.reference import ReferenceProblem, prepare_reference

    from reelbench.integrators.base import CRASHED  # here: the command line's start loads no integrator

    todo = [j for i, j in enumerate(jobs) if i not in kept]
    # each reference once, before the searches read it (two workers never compute the same one)
    problems = sorted({ReferenceProblem(j.scene, (("elements", j.elements),) + ((("t_end", j.t_end),) if j.t_end else ()),
                                        j.t_end, SAVE_EVERY) for j in todo}, key=str)
    rows = engine.run_jobs(functools.partial(run_search, cache_dir=cache_dir), jobs, workers=workers,
                           scheduler=scheduler,
                           setup=[functools.partial(prepare_reference, p, cache_dir) for p in problems],
                           setup_labels=[f"reference {p.scene} N={dict(p.overrides)['elements']}" for p in problems],
                           group=lambda i: (jobs[i].scene, jobs[i].elements, jobs[i].integrator),
                           cost=search_costs(jobs).__getitem__,
                           crash_row=lambda i, exc: {**asdict(jobs[i]), "bound": CRASHED,
                                                     "note": engine.crash_reason(exc)},
                           done=kept, finish=lambda i, row: _finish(row, keys[i]), describe=_describe_search,
                           on_row=on_row, log=log)
    return frame(rows, SEARCH_COLUMNS)


def run_timing_stage(jobs: list[TimingJob], *, previous=(), on_row=None, log=engine.log_stderr) -> pd.DataFrame:
    """The timing jobs in this process, one after another (one pinned core, never two at once)."""
    code = _code(*TIMING_CODE)
    keys = [j.key(code) for j in jobs]
    kept = kept_rows(keys, previous)
    rows = engine.run_jobs(run_timing, jobs, workers=0, cost=lambda i: jobs[i].budget + 5.0,
                           done=kept, finish=lambda i, row: _finish(row, keys[i]),
                           describe=_describe_timing, on_row=on_row, log=log)
    return frame(rows, TIMING_COLUMNS)


# ------------------------------------------------------------------------------------------
# cheapest.csv and the answer block
# ------------------------------------------------------------------------------------------
def _setting_text(sweep: str, v: float) -> str:
    return Setting.on_axis(sweep, v).label(digits=4) if np.isfinite(v) else ""


def answer_table(searched: pd.DataFrame, timed: pd.DataFrame) -> pd.DataFrame:
    """cheapest.csv: per scene × N × metric × target, the work rows (every entry, a method on
    one axis, that reached the target, by its searched cost in flops: winner when its cost, with
    the bracket's 10 % below it, stays below every other's, else tie) and the wall rows (the
    paired timing's ratios, intervals, pairs and verdicts)."""
    from reelbench.benchmark.runs.ranking import entry_name, presentation_rank, work_verdicts

    rows = []
    for (scene, n, metric, target), g in searched.groupby(["scene", "elements", "metric", "target"], sort=True):
        work, same = [], twins(g)
        axes = g.groupby("integrator")["sweep"].nunique().to_dict()
        for (integ, sweep), h in g.groupby(["integrator", "sweep"], sort=True):
            r = h.iloc[0]
            if (integ, sweep) in same:
                rows.append(dict(scene=scene, elements=int(n), metric=metric, target=target, cost_kind="work",
                                 integrator=integ, entry=entry_name(integ, sweep, axes[integ] > 1), sweep=sweep,
                                 setting=_setting_text(sweep, r["setting"]), verdict=IDENTICAL,
                                 cost_column=r["cost_column"], error=r["error"], runs=r["runs"],
                                 note=f"its search is bit-identical to {same[(integ, sweep)]}'s "
                                      f"({', '.join(TWIN_COLUMNS)}): ranked as one entry"))
                continue
            mates = sorted((i for (i, sw), m in same.items() if m == integ and sw == sweep), key=presentation_rank)
            entry = entry_name(integ, sweep, axes[integ] > 1, mates)
            spread = r["spread"] if np.isfinite(r.get("spread", np.nan)) else 0.0
            base = dict(scene=scene, elements=int(n), metric=metric, target=target, cost_kind="work",
                        integrator=integ, entry=entry, sweep=sweep, setting=_setting_text(sweep, r["setting"]),
                        setting_low=r["setting_low"], setting_high=r["setting_high"], bound=r["bound"],
                        cost_column=r["cost_column"], error=r["error"], runs=r["runs"], note=r.get("note", ""))
            if np.isfinite(r["setting"]) and r["cost_column"] != "flops":
                # a cost in another unit (steps: a method XLA's cost model cannot count) is no
                # point on the flops axis: it reached the target, but is not ranked by work
                base.update(cost=np.nan, verdict=NO_FLOPS_COUNT,
                            note=f"its cost at the target is {r['cost']:.4g} {r['cost_column']}, not flops: not ranked "
                                 "by work")
            elif np.isfinite(r["setting"]) and _counts_whole_step(integ):
                # the cost at the target lies between the bracket's coarser end and its answer
                base.update(cost=r["cost"], cost_low=r["cost"] / (1.0 + max(spread, 0.0)), cost_high=r["cost"])
            elif np.isfinite(r["setting"]):
                # counted by its evaluations alone (Radau: its Newton solves left out): the work is
                # at least this, so it can show a method slower, never make one the winner
                base.update(cost=r["cost"], cost_low=r["cost"] / (1.0 + max(spread, 0.0)), cost_high=np.inf,
                            verdict=LOWER_BOUND, note=LOWER_BOUND_NOTE)
            else:
                base.update(cost=np.nan, verdict=NOT_REACHED)
            work.append(base)
        work_verdicts([w for w in work if w.get("verdict") != LOWER_BOUND])
        _rank_lower_bounds(work)
        rows += work
        t = timed[(timed["scene"] == scene) & (timed["elements"] == n) & (timed["metric"] == metric)
                  & (timed["target"] == target)] if len(timed) else timed
        if len(t):
            # the timing names each method as `run_timing` does, without its twins
            by_entry = {**{r["entry"].split(" = ")[0]: r for r in work}, **{r["integrator"]: r for r in work}}
            # the verdicts of today's rule (`benchmark.answer.paired.verdicts`), not those stored with the timing
            stored = [_paired.Ratio(**r) for r in json.loads(t.iloc[0]["ratios"] or "[]")]
            for ratio in [asdict(r) for r in (_paired.verdicts(stored) if stored else [])]:
                w = by_entry.get(ratio["method"], {})
                rows.append(dict(scene=scene, elements=int(n), metric=metric, target=target, cost_kind="wall",
                                 integrator=w.get("integrator", ratio["method"]), entry=w.get("entry", ratio["method"]),
                                 sweep=w.get("sweep", ""), setting=w.get("setting", ""), cost=ratio["time"],
                                 ratio=ratio["ratio"], ratio_low=ratio["low"], ratio_high=ratio["high"],
                                 pairs=ratio["pairs"], verdict=ratio["verdict"], cost_column="run_time (paired)",
                                 note=t.iloc[0].get("note", "")))
    return frame(rows, COLUMNS, extra=False)


#: The note of a work cost that is only a lower bound (`benchmark.work.flops.counting_rule`
#: "evaluations"): one below the winner's has the verdict `LOWER_BOUND` (it cannot be ranked).
LOWER_BOUND_NOTE = ("its flops count right-hand sides, Jacobians and LU factorisations only (its Newton solves "
                    "and stage arithmetic left out): a lower bound of its work, ranked only where it is above "
                    "the winner's")


def _counts_whole_step(integrator: str) -> bool:
    from reelbench.benchmark.work.flops import WHOLE_STEP_RULES, counting_rule

    try:
        return counting_rule(integrator) in WHOLE_STEP_RULES
    except ValueError:  # an integrator no longer registered: its count cannot be vouched for
        return False


def _rank_lower_bounds(work: list[dict]) -> None:
    """A lower-bound cost above the winner's (or the tie's best) cost interval is `slower`
    (its ratio interval open above); one below it stays a `LOWER_BOUND`, unranked."""
    ranked = [w for w in work if w.get("verdict") in BEST_VERDICTS]
    best = min(ranked, key=lambda w: (w["cost"], w["entry"])) if ranked else None
    for w in work:
        if w.get("verdict") == LOWER_BOUND and best is not None and w["cost_low"] > best["cost_high"]:
            w.update(verdict=SLOWER, ratio=w["cost"] / best["cost"], ratio_low=w["cost_low"] / best["cost_high"],
                     ratio_high=np.inf)


def _use_line(g: pd.DataFrame) -> str:
    """"use X (setting, cost, interval); next Y at r× [lo–hi]" for one cost kind's rows; a tie
    (only where the intervals overlap) names its members with their ratios, then the first
    method outside it."""
    ranked = g[g["verdict"].isin(RANKED_VERDICTS)].sort_values(["ratio", "entry"])
    if ranked.empty:
        return "no method reached it"
    kind = g["cost_kind"].iloc[0]
    best = ranked.iloc[0]

    def unit(v):
        return f"{v * 1e3:.3g} ms" if kind == "wall" else f"{v:.3g} flops"

    def rel(r):
        if not np.isfinite(r["ratio_high"]):  # a lower bound of its cost
            return f"≥ {r['ratio_low']:.2f}× (a lower bound)"
        return f"{r['ratio']:.2f}× [{r['ratio_low']:.2f}–{r['ratio_high']:.2f}]"

    own = (f"{best['setting']}, {unit(best['cost'])}, {int(best['pairs'])} pairs" if kind == "wall"
           else f"{best['setting']}, {unit(best['cost'])} [{best['cost_low']:.3g}–{best['cost_high']:.3g}]")
    ties = ranked[ranked["verdict"] == TIE].iloc[1:]
    rest = ranked[ranked["verdict"] == SLOWER]
    if best["verdict"] == TIE:
        head = f"tie: `{best['entry']}` ({own}), " + ", ".join(f"`{r['entry']}` at {rel(r)}"
                                                                    for _, r in ties.iterrows())
    else:
        head = f"use `{best['entry']}` ({own})"
    if rest.empty:
        return head + ("" if len(ranked) > 1 else "; no other method reached it")
    nxt = rest.iloc[0]
    # a tie goes by the intervals, the order by the ratios: a wide interval can keep a member at
    # 1.33x in the tie while a narrow one puts 1.18x outside it, so "next" would misread
    after = "first outside the tie" if best["verdict"] == TIE else "next"
    return head + f"; {after} `{nxt['entry']}` at {rel(nxt)}"


def answer_lines(table: pd.DataFrame, labels: dict | None = None) -> list[str]:
    """The README's answer block: one bullet per scene × target (by wall time, paired, and by
    work), then per scene × target one line on how the wall-time answer changes from the
    smallest N to the largest."""
    labels = labels or {}
    lines = []
    for (scene, metric, target), g in table.groupby(["scene", "metric", "target"], sort=True):
        sizes = sorted(g["elements"].unique())
        for n in sizes:
            h = g[g["elements"] == n]
            parts = [f"{'by wall time' if k == 'wall' else 'by work'}: {_use_line(h[h['cost_kind'] == k])}"
                     for k in ("wall", "work") if (h["cost_kind"] == k).any()]
            lines.append(f"- **{scene}**, N = {n}, {labels.get(metric, metric)} ≤ {target:g}: " + "; ".join(parts) + ".")
        if len(sizes) > 1:
            first, last = (g[(g["elements"] == n) & (g["cost_kind"] == "wall")] for n in (sizes[0], sizes[-1]))
            win = [(x.sort_values(["ratio", "entry"])["entry"].iloc[0] if len(x) else "none") for x in (first, last)]
            lines.append(f"  - from N = {sizes[0]} to N = {sizes[-1]}: fastest `{win[0]}` → `{win[1]}`"
                         + (" (unchanged)" if win[0] == win[1] else ""))
    return lines


def answer_block(table: pd.DataFrame, labels: dict | None = None, command: str = "python -m benchmark answer",
                 table_file: str = str(CHEAPEST_FILE)) -> str:
    """The project README's answer block: one table per N, one sentence per scene, how it was made."""
    from reelbench.benchmark.answer import answer_report

    bounded = sorted(table.loc[table["note"].fillna("").eq(LOWER_BOUND_NOTE), "integrator"].unique())
    return "\n".join(answer_report.tables(table, labels) + answer_report.how_made(
        command, bounded, _paired.EQUIVALENCE, _search.CONFIRM, table_file)) + "\n"


#: Where the committed answer lives: an `answer` run into it also rewrites the README's answer block.
COMMITTED_ANSWER = RESULTS


def is_committed_answer(out: Path) -> bool:
    from reelbench.benchmark.core.store import ROOT

    try:
        return Path(out).resolve() == (ROOT / COMMITTED_ANSWER).resolve()
    except OSError:
        return False


# ------------------------------------------------------------------------------------------
# The study: python -m benchmark answer
# ------------------------------------------------------------------------------------------
#: What a row's digest leaves out (itself, the resume key, and how long its job took).
_NOT_DIGESTED = ("run_key", "row_digest", "job_time")


def _digest(row: dict) -> str:
    """A row's digest over every column it has a value in (so that it survives a round trip
    through CSV, where a missing value and an empty one read back alike)."""
    from reelbench.benchmark.core.store import canonical

    return key_of(sorted((str(k), canonical(v)) for k, v in row.items()
                         if k not in _NOT_DIGESTED and canonical(v) != ""))


#: A row's place in search.csv / timing.csv: one row per search, one per timing.
SEARCH_IDENTITY = ("scene", "elements", "integrator", "sweep", "metric", "target")
TIMING_IDENTITY = ("scene", "elements", "metric", "target")
#: Each table's row identity, by its file name.
IDENTITY = {"search.csv": SEARCH_IDENTITY, "timing.csv": TIMING_IDENTITY}


def read_rows(path: Path, log=engine.log_stderr, identity: tuple | None = None) -> list[dict]:
    """The rows of an earlier search.csv / timing.csv whose digest matches (the others are
    named and recomputed); none when the file is missing. A file that cannot be read, or is not
    a table of this study (no ``identity`` column; by default its file name's), is refused before
    any work, as every study's earlier table is (`benchmark.core.study_store.read_rows`): this
    run would overwrite it."""
    from reelbench.benchmark.core.study_store import read_rows as read_table

    rows = read_table(Path(path), IDENTITY[Path(path).name] if identity is None else identity)
    good = [r for r in rows if isinstance(r.get("row_digest"), str) and r["row_digest"] == _digest(r)]
    if len(good) < len(rows):
        log(f"warning: {path}: {len(rows) - len(good)} row(s) fail their digest; they are recomputed")
    return good


def merged(base: list[dict], new: list[dict], identity: tuple) -> list[dict]:
    """``base`` with ``new``'s rows in place of those of the same ``identity``, the rest after."""
    def ident(r):
        return tuple(str(r.get(c)) if isinstance(r.get(c), str) else float(r.get(c)) for c in identity)

    replace = {ident(r): r for r in new}
    out = [replace.pop(ident(r), r) for r in base]
    return out + [r for r in new if ident(r) in replace]


@dataclass(frozen=True)
class AnswerRequest:
    """What `python -m benchmark answer` asks for (its options, checked)."""

    out: Path
    scenes: tuple
    integrators: tuple
    elements: tuple = ELEMENTS
    targets: tuple = tuple((m, t) for m, t, _ in TARGETS)
    t_end: float | None = None
    max_runs: int = _search.MAX_RUNS
    timing_budget: float = PAIRED_BUDGET
    jobs: int | None = None
    fresh: bool = False
    command: str = "python -m benchmark answer"
    compare_with: tuple = ()  # earlier cheapest.csv files, one agreement paragraph each
    executor: str = DEFAULT_EXECUTOR  # where the searches run (`benchmark.runs.sweep.EXECUTORS`); the timing stays here
    scheduler: str | None = None


def _shown(path: Path) -> str:
    """``path`` relative to the repository where it lies inside it, else as given."""
    from reelbench.benchmark.core.store import ROOT

    try:
        return str(Path(path).resolve().relative_to(ROOT.resolve()))
    except ValueError:
        return str(path)


def labels_of(targets) -> dict:
    """metric -> its words: the default targets' labels, else the metric's own description."""
    from reelbench.benchmark.runs.metrics import METRICS

    words = {m: label for m, _, label in TARGETS}
    described = {m.name: m.description or m.name for m in METRICS}
    return {m: words.get(m, described.get(m, m)) for m, _ in targets}


def run_answer(request: AnswerRequest, log: Callable[[str], None] = engine.log_stderr) -> int:
    """search.csv, timing.csv (each written after every job), cheapest.csv, answer.md, README.md
    and the work–precision figures into ``request.out``; a stopped study keeps its finished rows
    and resumes from them. Into the committed results/, the project README's answer block too."""
    import os

    import pandas as pd

    from reelbench.benchmark.answer import answer_report
    from reelbench.benchmark.core.study import exclusive
    from reelbench.benchmark.core.reference import CACHE_DIR
    from reelbench.benchmark.core.report import Provenance
    from reelbench.benchmark.core.store import TableWriter, write_table
    from reelbench.models.io import atomic_write_text

    out = Path(request.out)
    out.mkdir(parents=True, exist_ok=True)
    provenance = Provenance(request.command)
    # a run joins the rows already there: rows of other scenes, sizes, methods or targets are kept
    # (`merged`), this run's replace theirs (so the extended answer adds to the main job's)
    earlier = {name: read_rows(out / name, log) for name in ("search.csv", "timing.csv")}
    others = [(p, pd.read_csv(p)) for p in request.compare_with]  # read now: one may be this run's own output
    search_csv = TableWriter(out / "search.csv",
                             lambda rows: frame(merged(earlier["search.csv"], rows, SEARCH_IDENTITY), SEARCH_COLUMNS))
    timing_csv = TableWriter(out / "timing.csv",
                             lambda rows: frame(merged(earlier["timing.csv"], rows, TIMING_IDENTITY), TIMING_COLUMNS))
    try:
        with exclusive(out, log):
            targets = list(request.targets)
            jobs = search_jobs(request.scenes, request.integrators, targets, request.elements, request.t_end,
                               request.max_runs)
            log(f"{len(jobs)} searches: {len(request.scenes)} scene(s) × N = "
                f"{', '.join(map(str, request.elements))} × {len(request.integrators)} method(s) × "
                f"{len(targets)} target(s); results -> {out}/")
            workers = 0 if request.executor == "serial" else (request.jobs or min(len(jobs), os.cpu_count() or 1))
            searched = run_search_stage(jobs, workers=workers, cache_dir=str(CACHE_DIR),
                                        scheduler=request.scheduler if request.executor == "dask" else None,
                                        previous=[] if request.fresh else earlier["search.csv"],
                                        on_row=search_csv, log=log)
            search_csv(searched.to_dict("records"))
            searched = search_csv.to_table(searched.to_dict("records"))  # with the rows kept from earlier runs
            tjobs = timing_jobs(searched, request.t_end, request.timing_budget)
            log(f"{len(tjobs)} paired timings (at most {request.timing_budget:g} s each, on one pinned core)")
            timed = run_timing_stage(tjobs, previous=[] if request.fresh else earlier["timing.csv"],
                                     on_row=timing_csv, log=log)
            timing_csv(timed.to_dict("records"))
            timed = timing_csv.to_table(timed.to_dict("records"))
            table = answer_table(searched, timed)
            write_table(out / "cheapest.csv", table)
            labels = labels_of(table[["metric", "target"]].drop_duplicates().itertuples(index=False))
            block = answer_block(table, labels, request.command, _shown(out / "cheapest.csv"))
            atomic_write_text(out / "answer.md", block)
            made = answer_report.figures(searched, out)
            compared = [answer_report.agreement_text(table, other, f"`{p}`") for p, other in others]
            for text in compared:
                log(text.rstrip())
            kept = {r.get("row_digest") for name in ("search.csv", "timing.csv") for r in earlier[name]}
            spent = answer_report.accounting(searched, timed, provenance.wall_time(), workers, kept)
            log(spent)
            atomic_write_text(out / "README.md", answer_report.readme(block.splitlines(), made,
                                                                      provenance.header() + "\n\n" + spent, compared))
            log(f"{out}/README.md and {len(made)} work–precision figure(s) written")
            if is_committed_answer(out):
                from reelbench.benchmark.answer.answer_report import write_answer
                from reelbench.benchmark.core.store import ROOT

                log(write_answer(ROOT / "README.md", block))
    except KeyboardInterrupt as exc:
        return engine.stopped(exc, f"{search_csv.saved} search row(s) and {timing_csv.saved} timing row(s) are "
                                   f"saved in {out}; run the same command again to resume", log)
    log(f"done in {provenance.wall_time():.0f} s: {out}/cheapest.csv, {out}/README.md")
    return 0
