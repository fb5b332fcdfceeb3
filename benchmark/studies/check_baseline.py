"""The drift baseline file of `python -m benchmark check` (`benchmark.studies.check`): its layout,
writing it under the header that says how it was made, reading it back, and refusing, before any
work, a baseline that could not fail a check (`row_problems`) or that does not cover the check's
sweep (`comparable`). An update's new baseline is `merge`'s.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import pandas as pd

from reelbench.benchmark.core.policy import BASELINE_FILE, ROW_IDENTITY, axis_of
from reelbench.benchmark.core.reference import REFERENCE_METHOD
from reelbench.benchmark.core.report import Provenance
from reelbench.benchmark.runs import sweep
from reelbench.benchmark.runs.metrics import ACCURACY
from reelbench.benchmark.runs.metrics import FLOORS as METRIC_FLOORS
from reelbench.integrators import available, get_integrator, plugin_errors
from reelbench.integrators.base import is_finished
from reelbench.models.io import atomic_write_text

BASELINE = BASELINE_FILE
UPDATE_COMMAND = "python -m benchmark check --update"
#: Absolute floors (below them a value is round-off or the reference's own error) and directions:
#: the metric registry's (`benchmark.runs.metrics.METRICS`).
FLOORS = dict(METRIC_FLOORS)
ORDER = "observed_order"
KEY = list(ROW_IDENTITY)
COLUMNS = KEY + ["status", *ACCURACY, ORDER, "steps", "run_time", "compile_time", "reason"]


def is_order_row(setting: str) -> bool:
    """Whether a row of the table holds a sweep's observed order (setting ``order(dt)`` / ``order(rtol)``)."""
    return str(setting).startswith("order(")


def name_of(key) -> str:
    """A row's identity in a message: "scene / integrator / setting"."""
    return " / ".join(key)


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
            out.append((line, f"repeats {name_of(key)} of line {first[key]} (one row per run)"))
            continue
        first[key] = line
        why = _order_row_problem(key, row) if is_order_row(key[2]) else _run_row_problem(key, row, known)
        if why:
            out.append((line, why))
            continue
        err = "position_error_final"
        if not is_order_row(key[2]) and row[err] > FLOORS[err] and row.get("steps", 1.0) != 0:
            usable.setdefault((key[0], key[1], axis_of(key[2])), [0, line])[0] += 1
    for (scene, name, axis), (n, line) in usable.items():
        if n >= 2 and (scene, name, f"order({axis})") not in first:
            out.append((line, f"no {ORDER} row for {scene} / {name} / order({axis}), though {n} of its runs give one"))
    return out


def _order_row_problem(key: tuple, row) -> str | None:
    """Why an order row could not fail a check: no finite order, or one outside the method's
    plausible range; None when it could."""
    axis = key[2][len("order("):].rstrip(")")
    lo, v = order_floor(key[1], key[0], axis), row[ORDER]
    if not np.isfinite(v):
        return f"{name_of(key)}: {ORDER} = {v:g} (allowed: a finite number >= 0; every order row has one)"
    if not lo <= v <= ORDER_CEILING:
        return (f"{name_of(key)}: {ORDER} = {v:g} is outside the plausible range of {key[1]} "
                f"({lo:g} to {ORDER_CEILING:g}): a check against it could not fail")
    return None


def _run_row_problem(key: tuple, row, known) -> str | None:
    """Why a run's row could not fail a check: an unknown status, a run that did not finish, a
    metric that is not a finite number in [0, `SANITY_BOUND`]; None when it could."""
    what, status = name_of(key), row["status"]
    if status not in known:
        return f"{what}: status {status!r} is not a status of the runs table (known: {', '.join(known)})"
    if not is_finished(status):
        return (f"{what}: status {status}: a run of the check sweep that is not ok cannot fail a "
                "check (only an improvement is possible); every run of a usable baseline is ok")
    bad = [m for m in ACCURACY if not (np.isfinite(row[m]) and row[m] >= 0)]
    if bad:
        shown = ", ".join(f"{m} = {row[m]:g}" for m in bad)
        return f"{what}: {shown} (allowed: a finite number >= 0; every finished run and order row has its values)"
    high = [m for m in ACCURACY if row[m] > SANITY_BOUND]
    if high:
        shown = ", ".join(f"{m} = {row[m]:g}" for m in high)
        return (f"{what}: {shown} is above the sanity bound {SANITY_BOUND:g}: not a measurement, "
                "and a check against it could not fail")
    return None


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
        shown = ", ".join(name_of(t.identity) for t in missing[:6])
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
