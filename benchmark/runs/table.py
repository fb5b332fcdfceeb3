"""The runs table (``runs.csv``): what a row of it may hold, and what of an earlier table a run
may keep. Its columns are written by `benchmark.runs.runner`; the generic store (the lock,
atomic tables, the merge by row identity) is `benchmark.core.store`.

* Identity: every row carries a `run_key` (scene physics, integrator, setting, horizon, save
  interval, code version); a run keeps the rows of an earlier table (`read_runs`) with the same
  key, so only the rest is computed (the grid sweep through the study runner,
  `benchmark.core.study`).
  Rows whose status may have been transient (`integrators.base.RETRY_STATUSES`) are never kept
  (`StoredRuns.reusable`).
* Trust: a row read back is used only when it passes `check_row` -- its types, ranges and
  status vocabulary (`statuses`, the one list of them), finite non-negative costs, and the
  digest of every column recorded when it was written (`row_digest`; a row without one in a
  table whose other rows have one is not trusted, rows from before such digests only with
  `StoredRuns.accept_legacy`). The digest catches a row edited by hand or damaged on disk; like
  any checksum stored beside its data, it does not stop a deliberate edit that recomputes it.
  A table that cannot be read whole is copied intact beside it and its readable rows salvaged
  (`read_runs`).
* Merging: a run restricted to fewer scenes, methods or settings than its output table holds
  adds or replaces only its own rows (`benchmark.core.store.merge_rows`: one row per scene,
  integrator and setting); a table holds one horizon and one set of scene values per scene,
  and a run that would mix two is refused before any work (`merge_conflicts`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from reelbench.benchmark.core import store
from reelbench.benchmark.core.policy import ROW_IDENTITY
from reelbench.benchmark.core.store import canonical, code_version, identity_of, is_missing
from reelbench.models.io import atomic_path


# ------------------------------------------------------------------------------------------
# Identity of a row
# ------------------------------------------------------------------------------------------
def run_key(task, code: str | None = None) -> str:
    """Identity of a task's row (a `benchmark.runs.sweep.Task`): the scene's physics hash (not its
    name), the integrator, the setting, horizon and save interval, and the code version."""
    from reelbench.models import load_scene

    scene = load_scene(task.scene, **dict(task.overrides))
    what = {"scene": scene.key(), "integrator": task.integrator, "dt": task.dt, "rtol": task.rtol,
            "atol": task.atol, "t_end": task.t_end if task.t_end is not None else scene.t_end,
            "save_every": task.save_every, "code": code or code_version()}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------
# Trust: what a row of the runs table may hold, and its digest
# ------------------------------------------------------------------------------------------
# The statuses recomputed on resume (`RETRY_STATUSES`) and those of the runs table besides the
# integrators' own (`TABLE_ONLY_STATUSES`) are named in `integrators.base`, beside `Status`. Every
# reader that validates a status (resume, the drift gate, figures) asks `statuses`.

#: The columns a row's digest leaves out: the digest itself, and the traceback of a failed run
#: (never written to the table). Every other column is covered, measurements included (run
#: times, flops, us_per_eval: the rankings read them), and so is a column added later.
DIGEST_EXCLUDED = ("row_digest", "traceback")
#: The columns digests covered before they covered every column (`legacy_digest`): a row whose
#: digest is over these only was written by older code, and its timings are unverified.
LEGACY_DIGEST_COLUMNS = (
    "scene", "scene_key", "integrator", "setting", "dt", "rtol", "atol", "t_end", "status", "reason", "rhs",
    "steps", "rhs_evals", "jac_evals", "lu_decompositions", "newton_iterations", "work_evals",
    "energy_error", "pi3_error", "orthogonality_error", "position_error_final", "position_error_max",
    "attitude_error_final", "attitude_error_max", "t_reached", "implementation", "run_key")
#: Numeric columns: counts (non-negative), errors (non-negative; NaN where a run did not
#: finish: the accuracy metrics' columns, `error_columns`), costs (finite and non-negative where
#: present), settings (positive where present).
COUNT_COLUMNS = ("steps", "rhs_evals", "jac_evals", "lu_decompositions", "newton_iterations", "work_evals",
                 "timing_repeats", "rejected_steps", "max_newton_iterations")
COST_COLUMNS = ("run_time", "run_time_low", "run_time_high", "compile_time", "us_per_eval", "load_avg",
                "task_time", "t_reached", "min_step", "median_step", "max_step", "flops")
SETTING_COLUMNS = ("dt", "rtol", "atol", "t_end")


def error_columns() -> tuple[str, ...]:
    """The accuracy metrics' columns, read from their registry (`benchmark.runs.metrics.METRICS`), so that
    a new `Metric` is range-checked on read-back too."""
    from reelbench.benchmark.runs.metrics import ACCURACY  # here: it imports pandas, which the command line's start does not

    return tuple(ACCURACY)


def _canonical_legacy(v) -> str:
    """The text older code digested for a value (`legacy_digest`): as `canonical`, but text is
    kept as it is (never read as a number)."""
    return v if isinstance(v, str) else canonical(v)


def row_digest(row: dict) -> str:
    """The runs table's digest of a row (`benchmark.core.store.row_digest`, the one digest), over
    every column but `DIGEST_EXCLUDED`; written with the row and checked when it is read back
    (`check_row`)."""
    return store.row_digest(row, DIGEST_EXCLUDED)


def legacy_digest(row: dict) -> str:
    """The digest older code wrote: over `LEGACY_DIGEST_COLUMNS` only."""
    text = "\x1f".join(f"{c}={_canonical_legacy(row.get(c))}" for c in LEGACY_DIGEST_COLUMNS)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def statuses() -> tuple[str, ...]:
    """Every status a row of the runs table may have."""
    from reelbench.integrators.base import TABLE_ONLY_STATUSES, Status

    return tuple(s.value for s in Status) + TABLE_ONLY_STATUSES


def _number(v) -> float | None:
    """A number of the table, or None for text that is not one (empty is NaN)."""
    if is_missing(v):
        return np.nan
    if isinstance(v, (bool, np.bool_)):
        return None
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def check_row(row: dict, known_statuses=None) -> str | None:
    """Why a row read back from a runs table cannot be trusted, or None when it can: its
    identity columns present, its status one of `statuses`, its numbers numbers (counts,
    errors and costs finite and non-negative where present, settings positive), its run times
    ordered (low <= median <= high), accuracy values for a finished run and none for another,
    and its digest (`row_digest`) the one written with it (a row without a digest, from an
    older table, is checked by the other rules alone)."""
    from reelbench.integrators.base import is_finished  # here: the command line imports this module at start

    errors = error_columns()
    for c in (*ROW_IDENTITY, "status"):
        if is_missing(row.get(c)) or not isinstance(row.get(c), str):
            return f"no {c}"
    from reelbench.models.schema import is_safe_name  # the names become parts of file names (figures)

    for c in ("scene", "integrator"):
        if not is_safe_name(row[c]):
            return f"{c} = {row[c]!r} is not a plain name (it would become part of a file name)"
    status = row["status"]
    if status not in (known_statuses or statuses()):
        return f"status {status!r} is not a status of the runs table"
    numbers = {}
    for c in (*COUNT_COLUMNS, *errors, *COST_COLUMNS, *SETTING_COLUMNS):
        if c not in row:
            continue
        v = _number(row[c])
        if v is None:
            return f"{c} = {row[c]!r} is not a number"
        if v == v and not (np.isfinite(v) and v >= 0):
            return f"{c} = {row[c]!r} is outside its range (a finite number >= 0)"
        numbers[c] = v
    for c in ("dt", "rtol", "atol", "t_end"):
        if numbers.get(c) == 0:
            return f"{c} = 0 is outside its range (> 0)"
    if not is_finished(status) and any(numbers.get(c, np.nan) == numbers.get(c, np.nan) for c in errors):
        return f"status {status} with accuracy values (only a finished run has them)"
    if is_finished(status):
        if not numbers.get("run_time", np.nan) == numbers.get("run_time", np.nan):
            return "a finished run without a run_time"
        present = [c for c in errors if c in row]
        if present and not any(numbers[c] == numbers[c] for c in present):
            return "a finished run without any accuracy value"
        lo, mid, hi = (numbers.get(c, np.nan) for c in ("run_time_low", "run_time", "run_time_high"))
        if (lo == lo and lo > mid * (1 + 1e-12)) or (hi == hi and hi < mid * (1 - 1e-12)):
            return f"run_time_low <= run_time <= run_time_high does not hold ({lo:g}, {mid:g}, {hi:g})"
    digest = row.get("row_digest")
    if not is_missing(digest) and not (store.digest_holds(row, DIGEST_EXCLUDED) or str(digest) == legacy_digest(row)):
        return "its values do not match the digest written with it (edited or damaged after it was written)"
    return None


def is_legacy(row: dict) -> bool:
    """Whether a row predates digests over every column (none, or `legacy_digest`'s): what its
    digest does not cover is checked by range only."""
    digest = row.get("row_digest")
    return is_missing(digest) or (not store.digest_holds(row, DIGEST_EXCLUDED) and str(digest) == legacy_digest(row))


# ------------------------------------------------------------------------------------------
# Resume: which rows of an earlier run are kept
# ------------------------------------------------------------------------------------------
@dataclasses.dataclass
class StoredRuns:
    """The rows of an earlier ``runs.csv``: those that pass `check_row`, and those that do not,
    each with why (``rejected``: (row, reason)). ``legacy``: trusted rows that predate digests
    over every column (`is_legacy`), kept only when the run accepts them (`accept_legacy`).
    ``aside``: where the table was copied intact when it could not be read whole."""

    rows: list[dict]
    rejected: list[tuple[dict, str]]
    legacy: list[dict] = dataclasses.field(default_factory=list)
    aside: Path | None = None

    @property
    def unverified(self) -> int:
        return len(self.legacy)

    def reusable(self, row: dict) -> bool:
        """Whether a run may keep ``row``, one of `rows`, instead of computing it again (given the
        same `run_key`): not a status that may have been transient (`RETRY_STATUSES`: retried),
        and not a row that predates full digests (recomputed unless accepted). The grid sweep's
        `benchmark.core.study.Study.reusable`."""
        from reelbench.integrators.base import RETRY_STATUSES

        return (row.get("status") not in RETRY_STATUSES and bool(row.get("run_key"))
                and not any(row is r for r in self.legacy))

    def accept_legacy(self) -> None:
        """Keep the rows that predate full digests (checked by range) and give them digests, so
        that the next read verifies them: the one-time, explicit ``--accept-legacy``."""
        for r in self.legacy:
            r["row_digest"] = row_digest(r)
        self.legacy = []


#: Columns of the runs table that hold text; the others are read as numbers where they are
#: (a version "1.10" or a digest "12e5" is not a number).
TEXT_COLUMNS = ("scene", "integrator", "setting", "status", "reason", "rhs", "implementation", "run_key",
                "row_digest", "scene_key", "traceback", "flops_note", "rejected_because", "package",
                "package_version", "code_digest")


def _records(records: Iterable[dict]) -> list[dict]:
    """CSV records (every value text) -> rows: empty as NaN, numbers as floats, text kept."""
    rows = []
    for rec in records:
        row = {}
        for k, v in rec.items():
            if v == "":
                row[k] = np.nan
                continue
            try:
                row[k] = float(v) if k not in TEXT_COLUMNS else v
            except ValueError:
                row[k] = v  # text where a number belongs: `check_row` says so
        if "reason" in row and is_missing(row["reason"]):
            row["reason"] = ""
        rows.append(row)
    return rows


class _NotATable(Exception):
    """A runs table that cannot be read whole; the message says why."""


def _read_whole(data: bytes) -> list[dict]:
    import io

    import pandas as pd

    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _NotATable(f"a byte that is not UTF-8 at offset {exc.start}") from None
    if "\x00" in text:
        raise _NotATable("binary: it holds NUL bytes")
    if not text.strip():
        raise _NotATable("empty")
    try:
        # every column as text first: a number edited into text must be seen, not coerced to NaN
        df = pd.read_csv(io.StringIO(text), dtype=str, keep_default_na=False)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, ValueError) as exc:
        raise _NotATable(f"not a CSV table: {str(exc).strip().splitlines()[0][:100]}") from None
    missing = [c for c in ROW_IDENTITY + ("status",) if c not in df]
    if missing:
        raise _NotATable(f"not a runs table: no column(s) {', '.join(missing)}")
    return _records(df.to_dict("records"))


def _salvage(data: bytes) -> tuple[list[dict], int]:
    """The rows of a table that cannot be read whole, one line at a time: (readable rows, the
    number of other lines). A row with a byte that is not UTF-8, a NUL, or the wrong number
    of fields is not readable; without a header naming the identity columns nothing is."""
    import csv
    import io

    text = data.decode("utf-8", "surrogateescape").replace("\x00", "\udc00")  # unreadable bytes marked
    try:
        lines = list(csv.reader(io.StringIO(text, newline="")))
    except csv.Error:
        lines = [line.split(",") for line in text.splitlines()]  # a broken quote: fields as they stand
    lines = [line for line in lines if line]
    if not lines:
        return [], 0
    header, body = lines[0], lines[1:]
    unreadable = lambda fields: any("\udc00" <= ch <= "\udcff" for f in fields for ch in f)  # noqa: E731
    if unreadable(header) or not set(ROW_IDENTITY + ("status",)) <= set(header) or len(set(header)) < len(header):
        return [], len(body)
    good = [dict(zip(header, f)) for f in body if len(f) == len(header) and not unreadable(f)]
    return _records(good), len(body) - len(good)


def _set_aside(path: Path) -> Path:
    """Copy ``path`` intact (atomically) to ``<stem>.unreadable-<UTC time>.csv`` beside it."""
    import shutil

    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    aside = path.with_name(f"{path.stem}.unreadable-{stamp}{path.suffix}")
    k = 1
    while aside.exists():
        k += 1
        aside = path.with_name(f"{path.stem}.unreadable-{stamp}-{k}{path.suffix}")
    with atomic_path(aside) as tmp:
        shutil.copyfile(path, tmp)
    return aside


def _duplicates(rows: list[dict]) -> tuple[list[dict], list[tuple[dict, str]], int]:
    """(rows with each identity once, rows rejected, exact copies dropped): of rows with the
    same scene, integrator and setting, an exact copy is dropped; copies that differ are all
    rejected (which one is the run's cannot be told)."""
    by_id: dict = {}
    for line, r in enumerate(rows, start=2):
        by_id.setdefault(identity_of(r), []).append((line, r))
    keep, bad, copies = [], [], 0
    for same in by_id.values():
        line0, first = same[0]
        texts = {tuple(sorted((k, canonical(v)) for k, v in r.items() if not is_missing(v))) for _, r in same}
        if len(texts) == 1:
            keep.append(first)
            copies += len(same) - 1
        else:
            lines = ", ".join(str(line) for line, _ in same)
            bad += [(r, f"it appears {len(same)} times with different values (lines {lines})") for _, r in same]
    order = {id(r): k for k, r in enumerate(rows)}
    return sorted(keep, key=lambda r: order[id(r)]), bad, copies


def read_runs(path: str | os.PathLike, log: Callable[[str], None] | None = None) -> StoredRuns:
    """The rows of an earlier run's ``runs.csv`` (none if the file is missing), each checked by
    `check_row`; every row that fails is named through ``log``.

    A table that cannot be read whole (a byte that is not UTF-8, binary, empty, not a runs
    table, or a row that appears twice) is copied intact beside it first (`StoredRuns.aside`),
    and its readable rows are salvaged one by one; one line says how many were kept and where
    the rest are. A row without a digest in a table whose other rows have one is not trusted
    (its digest was removed); a table without any digest is from older code (`legacy`)."""
    from reelbench.models.io import FileRefused, read_regular_file

    path = Path(path)
    if not path.exists():  # (a dangling link too: the table is written fresh in its place)
        return StoredRuns([], [])
    try:
        data = read_regular_file(path, store.MAX_TABLE_BYTES)
    except FileRefused as exc:  # kept as it is: the run is refused, before any work
        raise ValueError(f"{path} {exc}: move it away, or give another --out") from None
    why, aside, lost = None, None, 0
    try:
        rows = _read_whole(data)
    except _NotATable as exc:
        why = str(exc)
        rows, lost = _salvage(data)
    rows, bad, copies = _duplicates(rows)
    if why is None and (bad or copies):
        why = f"{len(bad) + copies} row(s) repeat the scene, integrator and setting of another"
    if why is not None:
        aside = _set_aside(path)
    known = statuses()
    digested = any(not is_missing(r.get("row_digest")) for r in rows)
    good = []
    for r in rows:
        reason = check_row(r, known)
        if reason is None and digested and is_missing(r.get("row_digest")):
            reason = "it has no row digest, where the table's other rows have one (removed after it was written)"
        (bad.append((r, reason)) if reason else good.append(r))
    if log:
        if aside is not None:
            log(f"warning: {path} cannot be read whole ({why}): copied intact to {aside}; kept {len(good)} "
                f"trusted row(s) of it, the other {len(bad) + lost + copies} are in that copy"
                + (f" ({copies} exact repeat(s) dropped)" if copies else ""))
        for r, reason in bad:
            log(f"warning: {path}: row {describe_row(r)} is not trusted ({reason}); it is recomputed if this run "
                "includes it")
    legacy = [r for r in good if is_legacy(r)]
    return StoredRuns(good, bad, legacy, aside)


def describe_row(row: dict) -> str:
    """scene/integrator/setting of a row, for messages."""
    return "/".join(str(row.get(c, "?")) for c in ROW_IDENTITY)


# ------------------------------------------------------------------------------------------
# Joining: whether a run's rows may join the table already in its output directory
# ------------------------------------------------------------------------------------------
def _same(a, b) -> bool:
    fa, fb = _number(a), _number(b)
    if fa is not None and fb is not None and fa == fa and fb == fb:
        return abs(fa - fb) <= 1e-12 * max(abs(fa), abs(fb))
    return canonical(a) == canonical(b)


def merge_conflicts(base: Iterable[dict], scenes: dict[str, tuple[float, str]]) -> list[str]:
    """Why the rows of a run cannot join ``base``: for each scene of the run (name -> (horizon
    t_end, physics hash `Scene.key`)), base rows of the same name over another horizon or with
    other scene values (a row without a physics hash is compared by horizon only)."""
    out = []
    for name, (t_end, key) in scenes.items():
        rows = [r for r in base if r.get("scene") == name]
        other_t = sorted({float(r["t_end"]) for r in rows if not is_missing(r.get("t_end")) and not _same(r["t_end"], t_end)})
        other_key = sorted({str(r["scene_key"]) for r in rows if not is_missing(r.get("scene_key")) and r["scene_key"] != key})
        if other_t:
            out.append(f"scene {name!r}: its {len(rows)} rows there are over t_end = "
                       f"{', '.join(f'{t:g}' for t in other_t)} s, this run's over {t_end:g} s")
        elif other_key:
            out.append(f"scene {name!r}: its rows there were computed with other scene values (physics hash "
                       f"{', '.join(other_key)}, this run's {key}; e.g. another --set)")
    return out
