"""Regression check of the deterministic accuracy metrics against a committed baseline.

    python -m benchmark check            # recompute the check sweep, compare, exit 1 on a regression
    python -m benchmark check --update   # recompute and rewrite results/baseline/drift.csv

It only composes existing pieces: `sweep.build_tasks` defines the runs (a short sweep of the
three paper scenes × every registered integrator), `runner.execute` runs them on the engine
(process executor: each worker pinned to one XLA thread, so on one machine two checks give
bit-identical numbers), `metrics` gives the accuracy columns and the observed orders. The
command's pipeline is `run_check`, at the end. The baseline file is
`benchmark.studies.check_baseline`'s, the comparison and its report `benchmark.studies.check_compare`'s.

It is a gate, not a study on the one runner (`benchmark.core.study`): it writes no table into an
output directory, and nothing until its whole sweep is done, since a verdict (or a baseline) needs
every run and every observed order of the sweep. A stop leaves the baseline as it was; a rerun
measures again. It shares the runner's parts: the engine (through `runner.execute`) and the stop
handling (`engine.stopped`).

Tolerance rules (a regression fails the check, exit status 1):

- drifts and errors (`metrics.ACCURACY`): worse than ``factor`` × baseline (default ×2), and
  above that metric's absolute floor (`FLOORS`). The metrics are deterministic, so any change
  comes from the code; ×2 lets through the small changes of a refactoring that reorders
  floating-point work (adaptive step sequences shift by a step or two), while a real
  regression (a lost order, a broken momentum map) moves them by orders of magnitude. The
  floors sit above round-off and the reference's own error, so values at that level
  (π3 and orthogonality of the LGVI, errors of tight runs) never fail on noise.
- observed orders: lower than baseline − ``order_margin`` (default 0.5, absolute). Orders use
  only errors above the position floor, so round-off never enters a slope.
- status: a run that was "ok" and no longer is (diverged, newton_failed, error, ...); an
  integrator of the baseline whose module no longer loads (`plugin_errors()`) or that is no
  longer registered (removed or renamed).

Improvements beyond the same margins are reported. Run and compile times are reported, never
judged.

A check cannot pass on nothing, and fails closed on what it gates (exit 2, naming the file and
the line, before any work): a baseline that is unreadable, binary, not a table, without rows,
with a repeated row, or with a row that could not fail (`row_problems`: an unknown status, a
run that did not finish, a metric that is not a finite number in [0, `SANITY_BOUND`], an order
outside its method's plausible range, a missing order row) is refused; so is one whose
coverage shrank (a run of the sweep of a method it gates has no row), one with rows of a
method no longer registered, and one without rows of one of reelbench's own selected methods
(a new method: `--allow-new NAME`, or add its rows with `--update --integrators NAME`). A
method the baseline does not know that comes from another package (an installed plugin) is
reported with the command that adds it, and not run: installing a plugin never breaks the
check. ``--update`` writes no baseline that could not fail. A metric the run has and the
baseline lacks is a regression, not a note.
"""

from __future__ import annotations

import collections
from typing import Callable

import numpy as np
import pandas as pd

from reelbench.benchmark.core import engine
from reelbench.benchmark.core.engine import log_stderr
from reelbench.benchmark.core.reference import CACHE_DIR
from reelbench.benchmark.core.report import Provenance
from reelbench.benchmark.runs import runner, sweep
from reelbench.benchmark.runs.metrics import observed_orders
from reelbench.benchmark.studies.check_baseline import (BASELINE, COLUMNS, FLOORS, KEY, ORDER,  # noqa: F401
                                                        ORDER_CEILING, SANITY_BOUND, UPDATE_COMMAND, Baseline,
                                                        baseline_for, comparable, guests_not_gated, merge,
                                                        not_gated, order_floor, read_baseline, row_problems,
                                                        write_baseline)
from reelbench.benchmark.studies.check_compare import (DEFAULT_FACTOR, DEFAULT_ORDER_MARGIN, Comparison,  # noqa: F401
                                                       RegressionTolerance, compare, format_report, machine_load)
from reelbench.integrators import Capability, get_integrator

# The check sweep: short, so the whole check costs about 140 CPU-seconds (measured; mostly JAX
# compilation, one per scene and JAX method, and the references). Two settings per method give an observed order.
SCENES = sweep.PAPER_SCENES
T_END = 0.5
FIXED_DTS = (0.0025, 0.00125)  # inside the LGVI's and Tsit5's stability limit on all three scenes
#: Methods whose coarse check step is past their cliff on one of the scenes, checked one halving
#: finer: Yoshida's triple jump takes a backward substep of 1.70 h, and at 2.5 ms on deployment it
#: finishes with energy error 1.25 and position error 2.5 m (`inaccurate`), a row that could not
#: fail a check.
FINER_DTS = {"lgvi_yoshida4": (0.00125, 0.000625)}
ADAPTIVE_RTOLS = (1e-4, 1e-6)
IMPLICIT_RTOLS = (1e-3, 1e-4)  # implicit solves cost 10-100x more per step: loose tolerances only


def build_check_tasks(integrators=None, *, scenes=SCENES, t_end: float = T_END, dts=FIXED_DTS,
                      rtols=ADAPTIVE_RTOLS, implicit_rtols=IMPLICIT_RTOLS, overrides: dict | None = None) -> list:
    """The check sweep as runner tasks; unknown integrator names raise ValueError (before any work).

    A method that is both adaptive and fixed-step (Tsit5) is checked on its adaptive axis only:
    each axis is a separate JAX compilation per scene, and the check must stay about a minute."""
    names = list(integrators) if integrators else sweep.default_names()
    tasks = []
    for name in names:
        integ = get_integrator(name)  # raises for unknown names
        adaptive = integ.has(Capability.ADAPTIVE)
        tols = implicit_rtols if integ.has(Capability.IMPLICIT) else rtols
        own_dts = FINER_DTS.get(name, dts) if dts == FIXED_DTS else dts
        tasks += [t for t in sweep.build_tasks(scenes, [name], dts=own_dts, rtols=tols, t_end=t_end,
                                               overrides=overrides)
                  if not (adaptive and t.dt is not None)]
    return tasks


def measure(tasks, *, executor: str = sweep.DEFAULT_EXECUTOR, jobs: int | None = None, cache_dir: str = str(CACHE_DIR),
            costs: dict | None = None, budget=None, log: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Run ``tasks`` (no timing repeats) and return the table in the baseline's layout.

    ``costs`` {(scene, integrator): seconds} (from the baseline) orders the work longest first,
    so no worker is left with a long compilation at the end; unknown groups go first."""
    kw = {"log": log} if log else {}
    if budget is not None:  # each solve's (`runner.SolveBudget`); else the default
        kw["budget"] = budget
    costs = costs or {}
    per_group = collections.Counter((t.scene, t.integrator) for t in tasks)
    # One worker runs all settings of a (scene, integrator): it compiles the JAX solve once.
    # The engine sums a group's task costs: each task carries its share of the group's seconds.
    runs = runner.execute(tasks, executor=executor, jobs=jobs, repeats=0, cache_dir=cache_dir,
                          group=lambda t: (t.scene, t.integrator),
                          cost=lambda t: costs.get((t.scene, t.integrator), np.inf) / per_group[(t.scene, t.integrator)],
                          **kw)
    return to_table(runs)


def costs_of(baseline: pd.DataFrame | None) -> dict:
    """Seconds (compile + first run) per (scene, integrator) recorded in ``baseline``."""
    if baseline is None or baseline.empty:
        return {}
    t = baseline[["compile_time", "run_time"]].fillna(0.0).sum(axis=1)
    return t.groupby([baseline["scene"], baseline["integrator"]]).sum().to_dict()


def to_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Runs -> one row per run, plus one row per sweep with its observed order
    (setting ``order(dt)`` / ``order(rtol)``; sweeps with fewer than two usable points have none)."""
    err = "position_error_final"
    # orders from errors above the floor only (metrics.observed_orders skips NaN errors)
    masked = runs.assign(**{err: runs[err].where(runs[err] > FLOORS[err])})
    orders = observed_orders(masked, error=err)
    parts = [runs.assign(**{ORDER: np.nan})]
    if not orders.empty:
        orders = orders[orders["points"] >= 2]
        parts.append(pd.DataFrame({"scene": orders["scene"], "integrator": orders["integrator"],
                                   "setting": "order(" + orders["sweep"] + ")", "status": "",
                                   ORDER: orders["observed_order"]}))
    table = pd.concat(parts, ignore_index=True).reindex(columns=COLUMNS)
    for c in ("status", "reason"):
        table[c] = table[c].fillna("").astype(str)
    return table


def describe(tasks) -> str:
    """The sweep in one line, for the baseline's header."""
    settings: dict[str, list[str]] = {}
    for t in tasks:
        if t.setting not in settings.setdefault(t.integrator, []):
            settings[t.integrator].append(t.setting)
    scenes = list(dict.fromkeys(t.scene for t in tasks))
    horizons = sorted({t.t_end for t in tasks if t.t_end is not None})
    overrides = sorted({o for t in tasks for o in t.overrides})
    return (f"{len(tasks)} runs; scenes {', '.join(scenes)}; t_end {', '.join(f'{v:g}' for v in horizons)} s"
            + (f"; overrides {dict(overrides)}" if overrides else "") + f"; atol = rtol * {sweep.ATOL_FACTOR:g}; "
            + "; ".join(f"{n} {' '.join(v)}" for n, v in settings.items()))


def run_check(*, update: bool = False, baseline=None, integrators=None, factor: float | None = None,
              order_margin: float | None = None, jobs: int | None = None, executor: str = sweep.DEFAULT_EXECUTOR,
              cache_dir: str | None = None, tasks=None, command: str | None = None, allow_new=(), budget=None,
              log: Callable[[str], None] | None = None, echo: Callable[[str], None] = print) -> int:
    """Recompute the check sweep and compare it with the baseline (or with ``update``, rewrite
    the baseline). Returns the exit status: 0 passed or updated, 1 regressions. Bad input
    raises ValueError before any work, a baseline that leaves a selected integrator (not in
    ``allow_new``) with nothing to compare included."""
    baseline = BASELINE if baseline is None else baseline
    provenance = Provenance(command or UPDATE_COMMAND)
    tol = RegressionTolerance(factor=DEFAULT_FACTOR if factor is None else factor,
                              order_margin=DEFAULT_ORDER_MARGIN if order_margin is None else order_margin)
    if jobs is not None and jobs < 1:
        raise ValueError(f"--jobs = {jobs!r} is invalid (allowed: >= 1)")
    tasks = build_check_tasks(integrators) if tasks is None else tasks
    old = baseline_for(baseline, update=update, warn=log or echo)
    table = old.table if old is not None else None
    unknown = [] if update else comparable(table, tasks, baseline, allow_new)
    if not update and integrators is None:  # installed plugins are guests: reported, not run
        unknown += [n for n in guests_not_gated(table) if n not in unknown]
    tasks = [t for t in tasks if t.integrator not in set(unknown)]  # nothing to compare them with
    try:
        current = measure(tasks, executor=executor, jobs=jobs, cache_dir=cache_dir or str(CACHE_DIR),
                          costs=costs_of(table), budget=budget, log=log)
    except KeyboardInterrupt as exc:
        return engine.stopped(exc, "the baseline was not changed", log or log_stderr)
    cmp = compare(table, current, tol) if old is not None else None
    if cmp is not None:
        cmp.notes += not_gated(unknown)
        echo(format_report(cmp, tol, baseline, old.header))
        if not update and cmp.compared == 0:
            raise ValueError(f"baseline {baseline}: no row of this check was compared (a check of nothing cannot pass)")
    if update:
        problems = row_problems(current.set_axis(range(1, len(current) + 1)))
        if problems:  # a baseline that could not fail is not written (the old one stays)
            lines = [f"  {why}" for _, why in problems[:10]]
            echo("\n".join([f"baseline NOT written: {len(problems)} row(s) of this sweep could not fail a check "
                             f"(fix the method, or leave it out with --integrators); {baseline} is unchanged:",
                             *lines]))
            return 1
        path = write_baseline(merge(table, current), baseline, provenance=provenance,
                              sweep_note=describe(tasks))
        echo(f"baseline written: {path} ({len(current)} rows recomputed)")
        return 0
    return 1 if cmp.failed else 0
