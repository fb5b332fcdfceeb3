"""Regression check of the deterministic accuracy metrics against a committed baseline.

    python -m benchmark check            # recompute the check sweep, compare, exit 1 on a regression
    python -m benchmark check --update   # recompute and rewrite results/baseline/drift.csv

It only composes existing pieces: `sweep.build_tasks` defines the runs (a short sweep of the
three paper scenes × every registered integrator), `runner.execute` runs them on the engine
(process executor: each worker pinned to one XLA thread, so on one machine two checks give
bit-identical numbers), `metrics` gives the accuracy columns and the observed orders. The
command's pipeline is `run_check`, at the end.

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
import io
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import pandas as pd

from reelbench.benchmark.core import engine
from reelbench.benchmark.core.engine import log_stderr
from reelbench.benchmark.runs import runner
from reelbench.benchmark.runs import sweep
from reelbench.benchmark.runs.metrics import ACCURACY, DIRECTIONS, observed_orders
from reelbench.benchmark.core.options import check_tolerance_rules
from reelbench.benchmark.core.policy import BASELINE_FILE, CHECK_FACTOR, CHECK_ORDER_MARGIN, ROW_IDENTITY, axis_of
from reelbench.benchmark.runs.metrics import FLOORS as METRIC_FLOORS
from reelbench.benchmark.core.reference import CACHE_DIR, REFERENCE_METHOD
from reelbench.benchmark.core.report import Provenance, fmt, markdown_table
from reelbench.integrators import Capability, available, get_integrator, plugin_errors
from reelbench.models.io import atomic_write_text
from reelbench.integrators.base import is_finished

BASELINE = BASELINE_FILE
UPDATE_COMMAND = "python -m benchmark check --update"

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

DEFAULT_FACTOR, DEFAULT_ORDER_MARGIN = CHECK_FACTOR, CHECK_ORDER_MARGIN
#: Absolute floors (below them a value is round-off or the reference's own error) and directions:
#: the metric registry's (`benchmark.runs.metrics.METRICS`).
FLOORS = dict(METRIC_FLOORS)
ORDER = "observed_order"
KEY = list(ROW_IDENTITY)
COLUMNS = KEY + ["status", *ACCURACY, ORDER, "steps", "run_time", "compile_time", "reason"]


@dataclass(frozen=True)
class RegressionTolerance:
    """What the drift gate calls a regression of a run against its baseline (the module's
    docstring): a metric worse than ``factor`` × baseline above its floor, an order lower by more
    than ``order_margin``. Not `benchmark.runs.reproducibility.AgreementTolerance`, which decides
    whether two runs of the same sweep on two machines agree."""

    factor: float = DEFAULT_FACTOR
    order_margin: float = DEFAULT_ORDER_MARGIN
    floors: dict = field(default_factory=lambda: dict(FLOORS))

    def __post_init__(self):
        check_tolerance_rules(self.factor, self.order_margin)


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


# ------------------------------------------------------------------------------------------
# the baseline file: comment lines saying how it was made, then the table as CSV

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


def write_baseline(table: pd.DataFrame, path: str | os.PathLike = BASELINE, *, provenance: Provenance | None = None,
                   sweep_note: str = "") -> Path:
    """Write ``table`` atomically (an interrupted update leaves the old baseline intact), under
    comment lines saying how it was made (``provenance``; default: `UPDATE_COMMAND`, now)."""
    provenance = provenance or Provenance(UPDATE_COMMAND)
    ref = ", ".join(f"{k} {v}" for k, v in REFERENCE_METHOD.items())
    header = [
        "reelbench drift baseline: deterministic accuracy metrics of the check sweep (see benchmark/studies/check.py).",
        *provenance.header().splitlines(),
        f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r} (the runner's worker env: one XLA thread per worker).",
        f"Sweep: {sweep_note or 'see benchmark/studies/check.py'}.",
        f"Errors vs the reference: {ref}, saved every {sweep.SAVE_EVERY:g} s.",
        f"Rows: one per run; rows with setting order(dt)/order(rtol) hold the sweep's {ORDER} "
        "(slope of position_error_final vs steps). run_time/compile_time: informational only.",
    ]
    text = "".join(f"# {line}\n" for line in header) + table.reindex(columns=COLUMNS).to_csv(index=False)
    atomic_write_text(path, text)
    return Path(path)


class Baseline(NamedTuple):
    """A baseline file's table and its comment lines (without the ``#``)."""

    table: pd.DataFrame
    header: list[str]


#: A baseline is a few hundred rows; anything far larger is not one (and is not read whole).
MAX_BASELINE_BYTES = 16 * 2**20


def _refuse(path, what: str) -> ValueError:
    return ValueError(f"baseline {path}: {what}; regenerate it with `{UPDATE_COMMAND}`")


def _baseline_text(path: Path) -> str:
    from reelbench.models.io import FileRefused, read_regular_file

    try:
        data = read_regular_file(path, MAX_BASELINE_BYTES)
    except FileRefused as exc:
        if exc.kind == "missing":
            raise ValueError(f"baseline {path} does not exist; create it with `{UPDATE_COMMAND}`") from None
        raise _refuse(path, str(exc)) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = "\x00"
    if "\x00" in text:
        raise _refuse(path, "not a text file (binary or not UTF-8), not a baseline table")
    return text


def read_baseline(path: str | os.PathLike = BASELINE) -> Baseline:
    """The baseline table and its comment header; ValueError naming the file (and the line)
    when it cannot be a baseline: unreadable, binary, not a table, without rows, with a
    duplicated row, or with a finished run whose metrics are not finite numbers."""
    path = Path(path)
    lines = _baseline_text(path).splitlines(keepends=True)
    n = 0
    while n < len(lines) and lines[n].startswith("#"):
        n += 1
    try:
        df = pd.read_csv(io.StringIO("".join(lines[n:])), dtype=str, keep_default_na=False)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise _refuse(path, f"not a CSV table ({str(exc).strip()})") from None
    missing = [c for c in KEY + ["status", *ACCURACY, ORDER] if c not in df]
    if missing:
        raise _refuse(path, f"missing column(s) {', '.join(missing)}")
    if df.empty:
        raise _refuse(path, "no rows (only its header): a check against it would compare nothing")
    df = df.reindex(columns=COLUMNS).fillna("")
    df.index = range(n + 2, n + 2 + len(df))  # each row's line in the file, for messages
    for c in COLUMNS:
        if c not in KEY + ["status", "reason"]:
            # Python's float() parses the shortest repr to the same double on every pandas version
            for line, v in df[c].items():
                try:
                    float(v) if v != "" else None
                except ValueError:
                    raise _refuse(path, f"line {line}: column {c} = {v!r} is not a number") from None
            df[c] = [float(v) if v != "" else np.nan for v in df[c]]
    _check_rows(df, path)
    return Baseline(df.reset_index(drop=True), [line[1:].strip() for line in lines[:n]])


def _check_rows(df: pd.DataFrame, path) -> None:
    """Refuse the baseline at its first row that could not fail a check (`row_problems`)."""
    problems = row_problems(df)
    if problems:
        line, what = problems[0]
        more = f" (and {len(problems) - 1} more row(s) like it)" if len(problems) > 1 else ""
        raise _refuse(path, f"line {line}: {what}{more}")


#: A drift or error of a finished run above this is not a measurement: a relative energy error
#: of 1000, a position error of a kilometre on metre-scale scenes (an attitude error cannot
#: exceed 2√3). A baseline value there would let any later value pass (x2 of 1e300 is inf).
SANITY_BOUND = 1e3
#: Observed orders are the slope of log(error) vs log(steps) over two settings. A baseline order
#: below `order_floor` (a method that does not converge at its order) or above this ceiling
#: (two-point slopes of errors near the floor reach 25: lgvi_yoshida4 on deployment) gates
#: nothing: a regression of the method would pass the margin.
ORDER_CEILING = 32.0


def order_floor(integrator: str, scene: str, axis: str) -> float:
    """The least observed order a baseline may record for ``integrator`` on ``scene``: half its
    declared order on a fixed-step sweep (``axis`` "dt"; the LGVI's is 1 with a reel), and 0.5
    on a tolerance sweep (a slope against the steps, not the classical order)."""
    if axis != "dt":
        return 0.5
    try:
        from reelbench.models import load_scene

        declared = get_integrator(integrator).order_for(load_scene(scene))
    except (ValueError, TypeError, AttributeError):  # an unregistered method or a scene by file
        declared = None
    return max(0.5, 0.5 * declared) if declared else 0.5


def row_problems(df: pd.DataFrame) -> list[tuple[int, str]]:
    """(line, why) of every row of a check table that could not fail a check: a repeated or
    nameless row, an unknown status, a run that did not finish (a check can then only find an
    improvement), a finished run whose metrics are not finite numbers in [0, `SANITY_BOUND`],
    an order row without a finite order in its method's plausible range (`order_floor`,
    `ORDER_CEILING`), and a missing order row where two runs of the sweep give one."""
    from reelbench.benchmark.runs.table import statuses

    known = statuses()
    out: list[tuple[int, str]] = []
    first: dict = {}
    usable: dict = {}  # (scene, integrator, axis) -> [runs that give an order, line of the first]
    for line, row in df.iterrows():
        key = tuple(row[c] for c in KEY)
        if not all(key):
            out.append((line, f"empty {', '.join(c for c, v in zip(KEY, key) if not v)}"))
            continue
        if key in first:
            out.append((line, f"repeats {_name(key)} of line {first[key]} (one row per run)"))
            continue
        first[key] = line
        what = _name(key)
        if _is_order_row(key[2]):
            axis = key[2][len("order("):].rstrip(")")
            lo, v = order_floor(key[1], key[0], axis), row[ORDER]
            if not np.isfinite(v):
                out.append((line, f"{what}: {ORDER} = {v:g} (allowed: a finite number >= 0; every order row has one)"))
            elif not lo <= v <= ORDER_CEILING:
                out.append((line, f"{what}: {ORDER} = {v:g} is outside the plausible range of {key[1]} "
                                  f"({lo:g} to {ORDER_CEILING:g}): a check against it could not fail"))
            continue
        status = row["status"]
        if status not in known:
            out.append((line, f"{what}: status {status!r} is not a status of the runs table "
                              f"(known: {', '.join(known)})"))
        elif not is_finished(status):
            out.append((line, f"{what}: status {status}: a run of the check sweep that is not ok cannot fail a "
                              "check (only an improvement is possible); every run of a usable baseline is ok"))
        else:
            bad = [m for m in ACCURACY if not (np.isfinite(row[m]) and row[m] >= 0)]
            if bad:
                shown = ", ".join(f"{m} = {row[m]:g}" for m in bad)
                out.append((line, f"{what}: {shown} (allowed: a finite number >= 0; every finished run and order "
                                  "row has its values)"))
                continue
            high = [m for m in ACCURACY if row[m] > SANITY_BOUND]
            if high:
                shown = ", ".join(f"{m} = {row[m]:g}" for m in high)
                out.append((line, f"{what}: {shown} is above the sanity bound {SANITY_BOUND:g}: not a measurement, "
                                  "and a check against it could not fail"))
                continue
            err = "position_error_final"
            if row[err] > FLOORS[err] and row.get("steps", 1.0) != 0:
                usable.setdefault((key[0], key[1], axis_of(key[2])), [0, line])[0] += 1
    for (scene, name, axis), (n, line) in usable.items():
        if n >= 2 and (scene, name, f"order({axis})") not in first:
            out.append((line, f"no {ORDER} row for {scene} / {name} / order({axis}), though {n} of its runs give one"))
    return out


def shipped(name: str) -> bool:
    """Whether ``name`` is one of reelbench's own integrators (`integrators.registry.own`), not
    a plugin installed from another package."""
    from reelbench.integrators import registry

    return name in registry.own()


def guests_not_gated(baseline: pd.DataFrame) -> list[str]:
    """Installed plugins the baseline does not know (a default check does not run plugins:
    they are reported, with the command that adds them)."""
    from reelbench.integrators import registry

    own, based = set(registry.own()), set(baseline["integrator"])
    return [n for n in available() if n not in own and n not in based and not n.startswith("test_")]


def comparable(baseline: pd.DataFrame, tasks, path, allow_new=(), *, registered=None,
               load_errors=None) -> list[str]:
    """Before any work: the baseline covers the check sweep ``tasks``, or ValueError naming the
    file, what is missing and the fix. Returns the names of the selected integrators the
    baseline does not know at all and that are not checked: plugins installed from other
    packages, and the methods named in ``allow_new`` (a new method, no baseline yet).

    Fails closed on what the baseline gates: an integrator with baseline rows that is no longer
    registered (removed or renamed; one whose plugin fails to load is a regression of the
    comparison), a gated integrator with any run of the sweep missing from the baseline (its
    coverage shrank), and one of reelbench's own integrators without baseline rows."""
    registered = set(available() if registered is None else registered)
    load_errors = plugin_errors() if load_errors is None else load_errors
    have = set(zip(*(baseline[c] for c in KEY)))
    based = set(baseline["integrator"])
    gone = sorted(based - registered - set(load_errors))
    if gone:
        raise ValueError(f"baseline {path} has rows of {', '.join(gone)}, which {'is' if len(gone) == 1 else 'are'} "
                         "not a registered integrator (removed or renamed?): restore it, or regenerate the "
                         f"baseline with `{UPDATE_COMMAND}` (it drops the rows of integrators that are gone)")
    selected = list(dict.fromkeys(t.integrator for t in tasks))
    unknown = [n for n in selected if n not in based]
    lacking = [n for n in unknown if n not in set(allow_new) and shipped(n)]
    if lacking:
        names = ",".join(lacking)
        raise ValueError(f"baseline {path} has no row this check can compare with for {'; '.join(lacking)}: no rows "
                         f"(reelbench's own method{'s' if len(lacking) > 1 else ''}). Add them with "
                         f"`{UPDATE_COMMAND} --integrators {names}`, or pass --allow-new {names} to check the others "
                         "without them")
    missing = [t for t in tasks if t.integrator in based and t.identity not in have]
    if missing:
        shown = ", ".join(_name(t.identity) for t in missing[:6])
        more = f" and {len(missing) - 6} more" if len(missing) > 6 else ""
        why = ("rows of other scenes or settings only" if not any(t.identity in have
                                                                  for t in tasks) else "its coverage shrank")
        raise ValueError(f"baseline {path} lacks {len(missing)} run(s) of this check's sweep ({why}): {shown}{more}. "
                         f"A check cannot pass on runs it does not compare: regenerate the baseline with "
                         f"`{UPDATE_COMMAND}`")
    if not any(n in based for n in selected):
        raise ValueError(f"baseline {path}: none of this check's runs has a row there (a check of nothing cannot pass)")
    return unknown


def not_gated(names) -> list[str]:
    """The report's lines for the selected integrators the baseline does not know (`comparable`)."""
    return [f"{n}: no baseline rows, not checked{' (a plugin)' if not shipped(n) else ''}; add them with "
            f"`{UPDATE_COMMAND} --integrators {n}`" for n in names]


def merge(baseline: pd.DataFrame | None, current: pd.DataFrame, registered=None) -> pd.DataFrame:
    """The new baseline after an update: ``current`` replaces the rows of the integrators it
    covers; rows of other integrators (an update restricted with --integrators) are kept, those
    of integrators no longer registered nor failing to load (``registered``: default every
    `available` one and every `plugin_errors` one) are dropped."""
    if baseline is None or baseline.empty:
        return current.reset_index(drop=True)
    registered = set(available()) | set(plugin_errors()) if registered is None else set(registered)
    kept = baseline[~baseline["integrator"].isin(set(current["integrator"]))
                    & baseline["integrator"].isin(registered)]
    return pd.concat([current, kept], ignore_index=True).reindex(columns=COLUMNS)


# ------------------------------------------------------------------------------------------
# the comparison

@dataclass
class Comparison:
    regressions: list[dict] = field(default_factory=list)  # scene, integrator, setting, metric, baseline, current, change, allowed
    improvements: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    timing: pd.DataFrame = field(default_factory=pd.DataFrame)
    compared: int = 0
    identical: int = 0  # rows whose status and metrics equal the baseline's bit for bit

    @property
    def failed(self) -> bool:
        return bool(self.regressions)

    def regression(self, key, metric, b, c, change, allowed) -> None:
        self.regressions.append(dict(zip(KEY, key), metric=metric, baseline=b, current=c, change=change, allowed=allowed))

    def improvement(self, key, metric, b, c, change) -> None:
        self.improvements.append(dict(zip(KEY, key), metric=metric, baseline=b, current=c, change=change, allowed=""))


def _g(v: float) -> str:
    return fmt(v, missing="nan")


def _same(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b))


def _is_order_row(setting: str) -> bool:
    return str(setting).startswith("order(")


def _name(key) -> str:
    return " / ".join(key)


def compare(baseline: pd.DataFrame, current: pd.DataFrame, tol: RegressionTolerance = RegressionTolerance(), *,
            registered: list[str] | None = None, load_errors: dict[str, str] | None = None) -> Comparison:
    """Compare ``current`` with ``baseline`` (both in the `to_table` layout) under ``tol``.
    ``registered`` / ``load_errors`` default to the registry's `available()` / `plugin_errors()`."""
    registered = set(available() if registered is None else registered)
    load_errors = plugin_errors() if load_errors is None else load_errors
    out = Comparison()
    base = baseline.set_index(KEY)
    cur = current.set_index(KEY)
    _compare_membership(out, base, cur, registered, load_errors)
    for key in cur.index.intersection(base.index, sort=False):
        b, c = base.loc[key], cur.loc[key]
        out.compared += 1
        out.identical += all(_same(b[m], c[m]) for m in ["status", *ACCURACY, ORDER])
        if _is_order_row(key[2]):
            _compare_order(out, key, float(b[ORDER]), float(c[ORDER]), tol)
        elif _compare_status(out, key, b, c):
            _compare_metrics(out, key, b, c, tol)
    out.timing = _timing(base, cur)
    return out


def _compare_membership(out: Comparison, base: pd.DataFrame, cur: pd.DataFrame, registered: set,
                        load_errors: dict) -> None:
    """Integrators and rows on one side only: notes, except a baseline integrator whose module
    stopped loading (a regression: it must not drop out of the check silently)."""
    ran = set(cur.index.get_level_values("integrator"))
    based = set(base.index.get_level_values("integrator"))
    for name in sorted(ran - based):
        out.notes.append(f"{name}: no baseline, run `{UPDATE_COMMAND}`")
    for name in sorted(based - registered):
        if name in load_errors:
            out.regression(("*", name, "*"), "load", "registered", f"failed to load: {load_errors[name]}"[:80], "gone",
                           "loads")
        else:  # removed or renamed: its rows would drop out of the check silently
            out.regression(("*", name, "*"), "registered", "registered", "not registered (removed or renamed?)",
                           "gone", "registered")
    for key in cur.index.difference(base.index):
        if key[1] in based:
            out.notes.append(f"{_name(key)}: new in the sweep, no baseline row (run `{UPDATE_COMMAND}`)")
    for key in base.index.difference(cur.index):
        if key[1] in ran:
            out.notes.append(f"{_name(key)}: in the baseline but not in this sweep")


def _compare_order(out: Comparison, key, bo: float, co: float, tol: RegressionTolerance) -> None:
    if np.isfinite(bo) and np.isfinite(co):
        if co < bo - tol.order_margin:
            out.regression(key, ORDER, _g(bo), _g(co), f"{co - bo:+.2f}", f">= {bo - tol.order_margin:.3g}")
        elif co > bo + tol.order_margin:
            out.improvement(key, ORDER, _g(bo), _g(co), f"{co - bo:+.2f}")
    elif np.isfinite(bo) != np.isfinite(co):
        # fewer than two usable points: a failed run (reported by its status) or errors
        # now below the floor (an improvement); nothing to compare
        out.notes.append(f"{_name(key)}: {ORDER} {_g(bo)} -> {_g(co)} (not comparable)")


def _compare_status(out: Comparison, key, b: pd.Series, c: pd.Series) -> bool:
    """ok -> not ok is a regression, the reverse an improvement; True when both runs are ok
    (then their metrics are compared)."""
    bs, cs = b["status"], c["status"]
    if bs != cs:
        text = f"{cs}: {c['reason']}"[:80] if not is_finished(cs) else cs
        if is_finished(bs):
            out.regression(key, "status", bs, text, "no longer ok", "ok")
        elif is_finished(cs):
            out.improvement(key, "status", bs, cs, "now ok")
        else:
            out.notes.append(f"{_name(key)}: status {bs} -> {text}")
    return is_finished(bs) and is_finished(cs)


def _compare_metrics(out: Comparison, key, b: pd.Series, c: pd.Series, tol: RegressionTolerance) -> None:
    for m in ACCURACY:
        bv, cv = float(b[m]), float(c[m])
        if not np.isfinite(bv):
            if np.isfinite(cv):  # nothing to compare with is a failure, not a pass
                out.regression(key, m, _g(bv), _g(cv), "missing in the baseline", "a finite baseline value")
            continue
        floor = tol.floors.get(m, 0.0)
        if DIRECTIONS.get(m, "lower") == "lower":  # smaller is better: worse is above factor x baseline
            limit = max(tol.factor * bv, floor)
            if not np.isfinite(cv) or cv > limit:
                change = f"x{cv / bv:.3g}" if np.isfinite(cv) and bv > 0 else "missing" if not np.isfinite(cv) else "from 0"
                out.regression(key, m, _g(bv), _g(cv), change, f"<= {_g(limit)}")
            elif bv > floor and cv < bv / tol.factor:
                out.improvement(key, m, _g(bv), _g(cv), f"x{cv / bv:.3g}")
        else:  # larger is better: worse is below baseline / factor (values under the floor never fail)
            limit = bv / tol.factor
            if not np.isfinite(cv) or (cv < limit and bv > floor):
                change = f"x{cv / bv:.3g}" if np.isfinite(cv) and bv > 0 else "missing"
                out.regression(key, m, _g(bv), _g(cv), change, f">= {_g(limit)}")
            elif cv > tol.factor * bv and cv > floor:
                out.improvement(key, m, _g(bv), _g(cv), f"x{cv / bv:.3g}")


def _timing(base: pd.DataFrame, cur: pd.DataFrame) -> pd.DataFrame:
    """Run and compile time per integrator, summed over the runs present in both (informational)."""
    both = cur.index.intersection(base.index, sort=False)
    both = [k for k in both if not _is_order_row(k[2])]
    if not both:
        return pd.DataFrame()
    rows = []
    b, c = base.loc[both], cur.loc[both]
    for name in sorted({k[1] for k in both}):
        sb, sc = b.xs(name, level="integrator"), c.xs(name, level="integrator")
        rb, rc = float(np.nansum(sb["run_time"])), float(np.nansum(sc["run_time"]))
        row = {"integrator": name, "runs": len(sc), "run_time_baseline": rb, "run_time": rc,
               "ratio": rc / rb if rb > 0 else np.nan,
               "compile_time_baseline": float(np.nansum(sb["compile_time"])),
               "compile_time": float(np.nansum(sc["compile_time"]))}
        # the load average each side's runs were timed under (when recorded): a ratio far from 1
        # under a different load is the machine's, not the method's
        for col, side in (("load_baseline", sb), ("load", sc)):
            if "load_avg" in side:
                loads = pd.to_numeric(side["load_avg"], errors="coerce")
                row[col] = float(loads.mean()) if loads.notna().any() else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def machine_load() -> str:
    """"load average L over C cores" of this machine now (empty where the OS does not say)."""
    try:
        return f"load average {os.getloadavg()[0]:.1f} over {os.cpu_count()} cores"
    except (AttributeError, OSError):
        return ""


def format_report(cmp: Comparison, tol: RegressionTolerance, baseline_path,
                  baseline_header: list[str] | None = None) -> str:
    """The readable outcome: regressions, improvements, notes, timing, verdict."""
    # "Produced by": the header of baselines written before the shared report header
    made = next((h for h in baseline_header or [] if h.startswith(("Generated by", "Produced by"))), "")
    lo, hi = min(tol.floors.values()), max(tol.floors.values())
    floors = f"{lo:.0e}" if lo == hi else ", ".join(f"{k} {v:.0e}" for k, v in tol.floors.items())
    load = machine_load()
    out = [f"check: {cmp.compared} rows compared with {baseline_path}, {cmp.identical} bit-identical"
           + (f" ({made})" if made else ""),
           f"rules: drifts/errors fail above x{tol.factor:g} the baseline and above their floor ({floors}); "
           "observed orders fail below "
           f"baseline - {tol.order_margin:g}; ok -> not ok fails; timing never fails.",
           "informational (never a failure): the bit-identical count (another CPU or XLA build changes the last "
           "digits, so 0 is normal there: the rules above decide), the notes and the timing table"
           + (f"; this machine now: {load}" if load else "") + ".", ""]
    cols = KEY + ["metric", "baseline", "current", "change", "allowed"]
    if cmp.regressions:
        out += [f"## REGRESSIONS ({len(cmp.regressions)})", "", markdown_table(pd.DataFrame(cmp.regressions, columns=cols))]
    if cmp.improvements:
        out += [f"## improvements ({len(cmp.improvements)}): refresh the baseline with `{UPDATE_COMMAND}` to keep them",
                "", markdown_table(pd.DataFrame(cmp.improvements, columns=cols[:-1]))]
    if cmp.notes:
        out += [f"## notes ({len(cmp.notes)}, not failures)", ""] + [f"- {n}" for n in cmp.notes] + [""]
    if not cmp.timing.empty:
        out += ["## timing (s, first solve after compilation; informational, never fails)", "",
                "Run times scale with the machine and its load (load: the mean load average the runs were "
                "timed under, where recorded" + (f"; {load} now" if load else "") + "): a ratio far from 1 "
                "under another load or on another machine is not a regression.", "",
                markdown_table(cmp.timing)]
    out.append(f"check FAILED: {len(cmp.regressions)} regression(s)" if cmp.failed else
               f"check passed: no regressions ({len(cmp.improvements)} improvement(s), {len(cmp.notes)} note(s))")
    return "\n".join(out)


def baseline_for(path: str | os.PathLike, *, update: bool, warn: Callable[[str], None]) -> Baseline | None:
    """The baseline a check compares with: without ``update`` it must be readable (ValueError
    naming the file otherwise); an update replaces a missing one (None) or an unreadable one
    (None, with a warning), so a broken baseline never blocks its own replacement."""
    if not update:
        return read_baseline(path)
    if not Path(path).exists():
        return None
    try:
        return read_baseline(path)
    except ValueError as exc:
        warn(f"warning: {exc}; writing a new one")
        return None


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
