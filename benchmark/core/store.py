"""The results store: what a study writes to disk, and what of an earlier run it may keep.

* One writer per output directory (`OutputLock`).
* Tables are written whole and atomically after every finished row (`TableWriter`), so an
  interrupted study leaves the last complete table, never half a file.
* Resume: every row of the runs table carries a `run_key` (scene physics, integrator,
  setting, horizon, save interval, code version); `kept_rows` keeps the rows of an earlier
  table (`read_runs`) with the same key, so only the rest is computed. Rows whose status
  may have been transient (`integrators.base.RETRY_STATUSES`) are never kept.
* Trust: a row read back is used only when it passes `check_row` -- its types, ranges and
  status vocabulary (`statuses`, the one list of them), finite non-negative costs, and the
  digest of every column recorded when it was written (`row_digest`; a row without one in a
  table whose other rows have one is not trusted, rows from before such digests only with
  `StoredRuns.accept_legacy`). The digest catches a row edited by hand or damaged on disk; like
  any checksum stored beside its data, it does not stop a deliberate edit that recomputes it.
  A table that cannot be read whole is copied intact beside it and its readable rows salvaged
  (`read_runs`).
* Merging: a run restricted to fewer scenes, methods or settings than its output table holds
  adds or replaces only its own rows (`merge_rows`: one row per scene, integrator and
  setting); a table holds one horizon and one set of scene values per scene, and a run that
  would mix two is refused before any work (`merge_conflicts`).
* Trajectory files: `.npz` archives written atomically (`write_npz`), and read back only when
  they are readable archives (`read_npz`, `read_trajectory`, else `UnreadableFile` saying why).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import socket
import sys
import time
import zipfile
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from benchmark.core.policy import ROW_IDENTITY
from models.io import atomic_path, atomic_write_text

ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------------
# Identity of code and of rows
# ------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def source_hash(dirs: tuple = (), files: tuple = ()) -> str:
    """A hash of the Python and TOML source under ``dirs`` and of ``files`` (paths relative to
    the repository root), names included: it changes when any of that code does. Read once per
    process (the code a process runs does not change under it)."""
    paths = sorted(p for d in dirs for p in (ROOT / d).rglob("*") if p.suffix in (".py", ".toml"))
    paths += [ROOT / f for f in files]
    h = hashlib.sha256()
    for f in paths:
        h.update(str(f.relative_to(ROOT)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


#: The physics source: the model and the integrators (a reference's identity, `benchmark.core.reference`,
#: and part of every row's code version).
PHYSICS_DIRS = ("models", "integrators")
#: The source that determines a row of the runs table: the physics, and the benchmark code that
#: runs a task, measures it and computes its reference.
_CODE_DIRS = PHYSICS_DIRS
_CODE_FILES = ("benchmark/runs/runner.py", "benchmark/runs/metrics.py", "benchmark/core/reference.py", "benchmark/runs/sweep.py",
               "benchmark/core/policy.py")


def code_version() -> str:
    """A hash of the source that determines a row (`_CODE_DIRS`, `_CODE_FILES`): rows computed
    by other code are recomputed on resume, never mixed in."""
    return source_hash(_CODE_DIRS, _CODE_FILES)


def run_key(task, code: str | None = None) -> str:
    """Identity of a task's row (a `benchmark.runs.sweep.Task`): the scene's physics hash (not its
    name), the integrator, the setting, horizon and save interval, and the code version."""
    from models import load_scene

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
    from benchmark.runs.metrics import ACCURACY  # here: it imports pandas, which the command line's start does not

    return tuple(ACCURACY)


def _missing(v) -> bool:
    return v is None or (isinstance(v, float) and v != v) or (isinstance(v, str) and v == "")


def _canonical_legacy(v) -> str:
    """One text per value, the same after a round trip through CSV (numbers as floats)."""
    if _missing(v):
        return ""
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, float, np.integer, np.floating)):
        return repr(float(v))
    return str(v)


def _canonical(v) -> str:
    """One text per value, the same after a round trip through CSV: numbers, and text that
    reads as one (a column the reader keeps as text), as floats."""
    if isinstance(v, str):
        try:
            return repr(float(v))
        except ValueError:
            return v
    return _canonical_legacy(v)


def row_digest(row: dict) -> str:
    """SHA-256 (16 hex digits) of every value a row has (`DIGEST_EXCLUDED` apart; an empty value
    is left out, so a column added to the table later changes no digest), written with the row
    and checked when it is read back (`check_row`)."""
    text = "\x1f".join(f"{c}={_canonical(row[c])}" for c in sorted(map(str, row))
                       if c not in DIGEST_EXCLUDED and not _missing(row[c]))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def legacy_digest(row: dict) -> str:
    """The digest older code wrote: over `LEGACY_DIGEST_COLUMNS` only."""
    text = "\x1f".join(f"{c}={_canonical_legacy(row.get(c))}" for c in LEGACY_DIGEST_COLUMNS)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def statuses() -> tuple[str, ...]:
    """Every status a row of the runs table may have."""
    from integrators.base import TABLE_ONLY_STATUSES, Status

    return tuple(s.value for s in Status) + TABLE_ONLY_STATUSES


def _number(v) -> float | None:
    """A number of the table, or None for text that is not one (empty is NaN)."""
    if _missing(v):
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
    from integrators.base import is_finished  # here: the command line imports this module at start

    errors = error_columns()
    for c in (*ROW_IDENTITY, "status"):
        if _missing(row.get(c)) or not isinstance(row.get(c), str):
            return f"no {c}"
    from models.schema import is_safe_name  # the names become parts of file names (figures)

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
    if not _missing(digest) and str(digest) not in (row_digest(row), legacy_digest(row)):
        return "its values do not match the digest written with it (edited or damaged after it was written)"
    return None


def is_legacy(row: dict) -> bool:
    """Whether a row predates digests over every column (none, or `legacy_digest`'s): what its
    digest does not cover is checked by range only."""
    digest = row.get("row_digest")
    return _missing(digest) or (str(digest) != row_digest(row) and str(digest) == legacy_digest(row))


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

    @property
    def resumable(self) -> list[dict]:
        """The trusted rows a run may keep instead of computing (transient failures retried, rows
        that predate full digests recomputed unless accepted)."""
        from integrators.base import RETRY_STATUSES

        legacy = {id(r) for r in self.legacy}
        return [r for r in self.rows if r.get("status") not in RETRY_STATUSES and r.get("run_key")
                and id(r) not in legacy]

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
#: A runs table is a few MB; anything far larger is not one (and is not read whole).
MAX_RUNS_BYTES = 512 * 2**20


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
        if "reason" in row and _missing(row["reason"]):
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
        texts = {tuple(sorted((k, _canonical(v)) for k, v in r.items() if not _missing(v))) for _, r in same}
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
    from models.io import FileRefused, read_regular_file

    path = Path(path)
    if not path.exists():  # (a dangling link too: the table is written fresh in its place)
        return StoredRuns([], [])
    try:
        data = read_regular_file(path, MAX_RUNS_BYTES)
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
    digested = any(not _missing(r.get("row_digest")) for r in rows)
    good = []
    for r in rows:
        reason = check_row(r, known)
        if reason is None and digested and _missing(r.get("row_digest")):
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


def read_previous(path: str | os.PathLike, log: Callable[[str], None] | None = None) -> list[dict]:
    """The trusted rows of an earlier run's ``runs.csv`` that a run may resume from
    (`read_runs`, transient failures left out)."""
    return read_runs(path, log).resumable


def kept_rows(keys: list[str], previous: Iterable[dict] | None) -> dict[int, dict]:
    """{index: earlier row} for every key of ``keys`` that a row of ``previous`` carries."""
    kept = {r["run_key"]: r for r in (previous or []) if isinstance(r.get("run_key"), str) and r["run_key"]}
    return {i: kept[k] for i, k in enumerate(keys) if k in kept}


# ------------------------------------------------------------------------------------------
# Merging a run into the table already in its output directory
# ------------------------------------------------------------------------------------------
def identity_of(row: dict, identity: tuple = ROW_IDENTITY) -> tuple:
    """A row's place in its table (by default `benchmark.core.policy.ROW_IDENTITY`)."""
    return tuple(row.get(c) for c in identity)


def merge_rows(base: Iterable[dict], new: Iterable[dict], identity: tuple = ROW_IDENTITY,
               expand: Callable[[dict], list[dict]] | None = None) -> list[dict]:
    """The rows of ``base`` with those of ``new`` in their place (same ``identity``, by default
    `ROW_IDENTITY`; a study's table names its own), and the other rows of ``new`` after the last
    base row of their scene and integrator (else at the end). ``expand(row)``: the table rows
    of one new row (a run's history, a ladder's runs), which replace every base row with its
    identity, as a whole."""
    expand = expand or (lambda r: [r])
    replace = {}
    for r in new:
        replace[identity_of(r, identity)] = expand(r)
    out, placed = [], set()
    for r in base:
        k = identity_of(r, identity)
        if k not in replace:
            out.append(r)
        elif k not in placed:
            out += replace[k]
            placed.add(k)
    for k, rows in replace.items():
        if k in placed or not rows:
            continue
        r = rows[0]
        same = [j for j, o in enumerate(out) if o.get("scene") == r.get("scene") and o.get("integrator") == r.get("integrator")]
        at = same[-1] + 1 if same else len(out)
        out[at:at] = rows
    return out


def _same(a, b) -> bool:
    fa, fb = _number(a), _number(b)
    if fa is not None and fb is not None and fa == fa and fb == fb:
        return abs(fa - fb) <= 1e-12 * max(abs(fa), abs(fb))
    return _canonical(a) == _canonical(b)


def merge_conflicts(base: Iterable[dict], scenes: dict[str, tuple[float, str]]) -> list[str]:
    """Why the rows of a run cannot join ``base``: for each scene of the run (name -> (horizon
    t_end, physics hash `Scene.key`)), base rows of the same name over another horizon or with
    other scene values (a row without a physics hash is compared by horizon only)."""
    out = []
    for name, (t_end, key) in scenes.items():
        rows = [r for r in base if r.get("scene") == name]
        other_t = sorted({float(r["t_end"]) for r in rows if not _missing(r.get("t_end")) and not _same(r["t_end"], t_end)})
        other_key = sorted({str(r["scene_key"]) for r in rows if not _missing(r.get("scene_key")) and r["scene_key"] != key})
        if other_t:
            out.append(f"scene {name!r}: its {len(rows)} rows there are over t_end = "
                       f"{', '.join(f'{t:g}' for t in other_t)} s, this run's over {t_end:g} s")
        elif other_key:
            out.append(f"scene {name!r}: its rows there were computed with other scene values (physics hash "
                       f"{', '.join(other_key)}, this run's {key}; e.g. another --set)")
    return out


# ------------------------------------------------------------------------------------------
# Tables
# ------------------------------------------------------------------------------------------
def frame(rows: Iterable[dict], columns: list[str], *, extra: bool = True):
    """Rows -> a table with ``columns`` first, in that order (a column no row has is NaN), then
    (``extra``) any other keys of the rows."""
    import pandas as pd

    columns = list(columns)
    df = pd.DataFrame(list(rows))
    for c in columns:
        if c not in df:
            df[c] = np.nan
    return df[columns + ([c for c in df.columns if c not in columns] if extra else [])]


def write_table(path: str | os.PathLike, df, drop: Iterable[str] = ()) -> Path:
    """``df`` as CSV, atomically, without the columns ``drop`` (those it has)."""
    df = df.drop(columns=[c for c in drop if c in df])
    atomic_write_text(path, df.to_csv(index=False))
    return Path(path)


class TableWriter:
    """The ``on_row`` of a study: rewrites the table ``path`` (``to_table(rows)``, without the
    columns ``drop``) atomically whenever rows come in, and counts the rows it has saved."""

    def __init__(self, path: str | os.PathLike, to_table: Callable, drop: Iterable[str] = ()):
        self.path, self.to_table, self.drop = Path(path), to_table, tuple(drop)
        self.saved = 0

    def __call__(self, rows: list[dict]) -> None:
        write_table(self.path, self.to_table(rows), self.drop)
        self.saved = len(rows)


class OutputKeys:
    """What each derived file of an output directory (a figure, a study's table) was made from:
    ``{file name: key}`` in one JSON file, so a rerun whose inputs did not change keeps the file
    instead of recomputing it (`fresh`), and a report can say which files other inputs made."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            self.keys = {str(k): str(v) for k, v in data.items()} if isinstance(data, dict) else {}
        except (OSError, ValueError):
            self.keys = {}

    def fresh(self, name: str, key: str) -> bool:
        """Whether ``name`` exists beside the keys and was made from ``key``."""
        return self.keys.get(name) == key and (self.path.parent / name).is_file()

    def record(self, name: str, key: str) -> None:
        self.keys[name] = key
        atomic_write_text(self.path, json.dumps(self.keys, indent=1, sort_keys=True) + "\n")


def rows_key(rows: Iterable[dict], drop: Iterable[str] = ()) -> str:
    """A key of table rows that survives a round trip through CSV (numbers as floats, empty as
    NaN; column order ignored): the same rows read back give the same key."""
    drop = set(drop)
    canon = sorted(sorted((str(k), _canonical(v)) for k, v in r.items() if k not in drop) for r in rows)
    return key_of(canon)


def key_of(*parts) -> str:
    """A 16-hex-digit SHA-256 of ``parts`` (JSON, sorted keys; other objects by their text)."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------
# One writer per output directory
# ------------------------------------------------------------------------------------------
class LockedError(ValueError):
    """Another live process holds the output directory's lock."""


class OutputLock:
    """``with OutputLock(out):`` -- at most one study writes into ``out`` at a time.

    A kernel lock (flock) on a file in ``out``: it dies with its process, so a run killed with -9
    leaves nothing that blocks the next one. The file holds the owner's pid, host and command,
    for the refusal of a second run."""

    NAME = ".reelbench.lock"
    #: Seconds a second run waits before it is refused: enough for a holder that is releasing.
    WAIT = 0.1

    def __init__(self, directory: str | os.PathLike, log: Callable[[str], None] | None = None):
        self.path = Path(directory) / self.NAME
        self.log = log
        self.held = False
        self._lock = None

    def _holder(self) -> dict:
        try:
            holder = json.loads(self.path.read_text())
        except (OSError, ValueError):  # gone, or not yet written by a holder that is starting
            return {}
        return holder if isinstance(holder, dict) else {}

    def acquire(self) -> "OutputLock":
        import filelock

        from models.io import WriteFailed

        me = json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "command": " ".join(sys.argv)}).encode()

        def write_holder(fd: int) -> None:
            os.pwrite(fd, me, 0)
            # cut what a killed holder's longer text left; not truncated to 0 first: on ext4 that
            # makes the last close flush the file (4 ms instead of 0.03)
            os.ftruncate(fd, len(me))

        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)  # the command line checks --out without creating it
            lock = filelock.FileLock(self.path, timeout=self.WAIT, on_acquired=write_holder)
            lock.acquire()
        except filelock.Timeout:  # held: a second run is refused at once
            holder = self._holder()
            who = f"pid {holder.get('pid', '?')} on {holder.get('host', '?')}: {holder.get('command', '?')}"
            raise LockedError(
                f"{self.path.parent}/ is in use by another run ({who}); lock file {self.path}. "
                f"Wait for it to finish or use another --out") from None
        except OSError as exc:  # read-only, full, ...: the `cannot write FILE` line, no lock left
            where = self.path.parent if not self.path.parent.is_dir() else self.path
            raise WriteFailed(exc.errno, exc.strerror or str(exc), str(where)) from None
        self._lock, self.held = lock, True
        self._remove_stale_temporaries()
        return self

    #: Temporaries of the atomic writer (`models.io.atomic_path`: ".NAME.XXXXXXXX.tmp.SUFFIX")
    #: unchanged this long are stale: a live write rewrites its file as it goes and renames it
    #: within moments.
    STALE_AFTER = 5.0

    def _remove_stale_temporaries(self) -> None:
        """Delete what a run killed with -9 left of its atomic writes in the directory and its
        cache (with the lock held, no study of this directory is writing)."""
        import re

        pattern = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[^./]+)?$")
        now, removed = time.time(), []
        for d in (self.path.parent, self.path.parent / "cache"):
            try:
                entries = list(os.scandir(d))
            except OSError:
                continue
            for e in entries:
                try:
                    if (pattern.match(e.name) and e.is_file(follow_symlinks=False)
                            and now - e.stat(follow_symlinks=False).st_mtime > self.STALE_AFTER):
                        os.unlink(e.path)
                        removed.append(e.name)
                except OSError:
                    continue
        if removed and self.log:
            self.log(f"removed {len(removed)} temporary file(s) an interrupted run left in {self.path.parent}/: "
                     + ", ".join(removed[:5]) + (" ..." if len(removed) > 5 else ""))

    def release(self) -> None:
        if self.held:
            try:
                # unlinked while still held, so the directory is left as it was; a second run that
                # opened the file before finds it unlinked once it gets the lock, and is refused
                self.path.unlink(missing_ok=True)
            except OSError:  # a file system gone read-only: the file stays, and blocks nobody
                pass
            self._lock.release()
            self._lock, self.held = None, False

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# ------------------------------------------------------------------------------------------
# Trajectory files
# ------------------------------------------------------------------------------------------
#: The most an .npz archive read back may expand to (bytes): a run's trajectory within the memory
#: budgets of `benchmark.core.options` reads in seconds; more is refused before anything is read.
MAX_ARCHIVE_BYTES = 2 * 2**30


class UnreadableFile(ValueError):
    """A file that is not a readable .npz archive; the message says why."""


def write_npz(path: str | os.PathLike, arrays: dict, *, compressed: bool = False) -> Path:
    """``arrays`` as an .npz archive, atomically (an interrupted write leaves the old file)."""
    save = np.savez_compressed if compressed else np.savez
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            save(fh, **arrays)
    return Path(path)


def _unreadable(exc: Exception) -> UnreadableFile:
    text = str(exc).splitlines()[0][:120] if str(exc) else ""
    return UnreadableFile(f"{type(exc).__name__}: {text}")


def _require_archive(path: Path) -> None:
    from models.io import FileRefused, require_regular

    try:
        require_regular(path)  # a FIFO would block the zip reader, a device feed it forever
    except FileRefused as exc:
        raise UnreadableFile(str(exc)) from None
    # an .npz is a zip archive; random bytes, a pickle or a cut file are not
    if not zipfile.is_zipfile(path):
        raise UnreadableFile("not an .npz archive: truncated or not written by reelbench")
    # what its members expand to, from the archive's directory, before any is read (a small file
    # may expand to gigabytes; the reader never returns more than a member declares)
    try:
        with zipfile.ZipFile(path) as archive:
            expands = sum(info.file_size for info in archive.infolist())
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise _unreadable(exc) from None
    if expands > MAX_ARCHIVE_BYTES:
        raise UnreadableFile(f"its arrays expand to {expands / 2**30:.3g} GiB, over the {MAX_ARCHIVE_BYTES / 2**30:.3g} "
                             "GiB that are read back (a trajectory that large: save fewer points, --save-every)")


def read_npz(path: str | os.PathLike) -> dict:
    """Every array of an .npz archive, read at once and without pickles; `UnreadableFile`
    saying why when it cannot be (truncated, random bytes, a pickle, a bad member)."""
    _require_archive(Path(path))
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except Exception as exc:  # whatever the reader trips on, the file is unusable
        raise _unreadable(exc) from None


def read_trajectory(path: str | os.PathLike):
    """A trajectory written by `integrators.Trajectory.save` (``simulate``); `UnreadableFile`
    saying why when the file is not one."""
    from integrators import Trajectory

    _require_archive(Path(path))
    try:
        return Trajectory.load(path)
    except Exception as exc:  # whatever the reader trips on, the file is not a trajectory
        raise _unreadable(exc) from None


#: The array fields of `integrators.Trajectory`; its other fields are its metadata.
TRAJECTORY_ARRAYS = ("t", "x", "attitude", "velocity", "momentum", "work")


def trajectory_parts(traj) -> tuple[dict, dict]:
    """(arrays, metadata) of a trajectory: the arrays it has, and every other field."""
    arrays = {k: np.asarray(getattr(traj, k)) for k in TRAJECTORY_ARRAYS if getattr(traj, k) is not None}
    meta = {f.name: getattr(traj, f.name) for f in dataclasses.fields(traj) if f.name not in TRAJECTORY_ARRAYS}
    return arrays, meta


def trajectory_from(arrays: dict, meta: dict):
    """The trajectory of `trajectory_parts` (a missing array is None)."""
    from integrators import Trajectory

    return Trajectory(**{k: arrays.get(k) for k in TRAJECTORY_ARRAYS}, **meta)


def merge_study_table(earlier, new, key: Iterable[str]):
    """A study's table (a DataFrame) with the rows of ``new`` in place of every row of
    ``earlier`` that has the same values in the columns ``key`` (a run's rows replace that run's
    rows as a whole), and ``earlier``'s other rows kept as they were, first: a study that
    recomputes a few of its runs never drops the others. ``earlier`` may be None."""
    import pandas as pd

    key = list(key)
    if earlier is None or earlier.empty:  # (None when neither has rows: every run of a study crashed)
        return new.reset_index(drop=True) if new is not None else None
    if new is None or new.empty:
        return earlier.reset_index(drop=True)
    missing = [c for c in key if c not in earlier or c not in new]
    if missing:
        raise ValueError(f"merge_study_table: key column(s) {missing} missing")
    replaced = pd.MultiIndex.from_frame(new[key].astype(str).drop_duplicates())
    keep = ~pd.MultiIndex.from_frame(earlier[key].astype(str)).isin(replaced)
    return pd.concat([earlier[keep], new], ignore_index=True)
