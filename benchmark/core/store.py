"""The results store: what every study writes to disk, and how it keeps what an earlier run wrote.

* One writer per output directory (`OutputLock`).
* Tables are written whole and atomically after every finished row (`TableWriter`, `write_table`),
  so an interrupted study leaves the last complete table, never half a file.
* Identity: a row's place in its table (`identity_of`, by default `benchmark.core.policy.ROW_IDENTITY`;
  a study's table names its own); a key of anything (`key_of`), of rows (`rows_key`, the same after
  a round trip through CSV: `canonical`), of source code (`source_hash`, `code_version`); what each
  derived file was made from (`OutputKeys`).
* Trust: a row's digest (`row_digest`), written with it and checked when it is read back; the
  one digest of every table that has one.
* Merging: a run's rows replace the rows of the same identity in the table already there, and
  the others are kept (`merge_rows`).
* Trajectory files: `.npz` archives written atomically (`write_npz`), and read back only when
  they are readable archives (`read_npz`, `read_trajectory`, else `UnreadableFile` saying why).

The runs table's own rules (its row key, trust, reading back and resume) are `benchmark.runs.table`.
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

from reelbench.benchmark.core.policy import ROW_IDENTITY
from reelbench.models.io import atomic_path, atomic_write_text

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
#: The source that determines a measurement (a row of the runs table, and every study's rows and
#: figures keyed on `code_version`): the physics, and the benchmark code that runs a task,
#: measures it and computes its reference. Named by path only: nothing here imports it.
_CODE_DIRS = PHYSICS_DIRS
_CODE_FILES = ("benchmark/runs/runner.py", "benchmark/runs/metrics.py", "benchmark/core/reference.py", "benchmark/runs/sweep.py",
               "benchmark/core/policy.py")


def code_version() -> str:
    """A hash of the source that determines a measurement (`_CODE_DIRS`, `_CODE_FILES`): rows
    computed by other code are recomputed on resume, never mixed in (`benchmark.runs.table.run_key`,
    and the keys of the other studies)."""
    return source_hash(_CODE_DIRS, _CODE_FILES)


def is_missing(v) -> bool:
    """Whether a table value is missing: None, NaN or empty text (all read back from CSV alike)."""
    return v is None or (isinstance(v, float) and v != v) or (isinstance(v, str) and v == "")


def canonical(v) -> str:
    """One text per value, the same after a round trip through CSV: numbers, and text that
    reads as one (a column the reader keeps as text), as floats; a missing value as ""."""
    if isinstance(v, str):
        try:
            return repr(float(v))
        except ValueError:
            return v
    if is_missing(v):
        return ""
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, float, np.integer, np.floating)):
        return repr(float(v))
    return str(v)


# ------------------------------------------------------------------------------------------
# Merging a run into the table already in its output directory
# ------------------------------------------------------------------------------------------
#: The column where a row keeps its digest (`row_digest`).
DIGEST_COLUMN = "row_digest"


def row_digest(row: dict, leave_out: Iterable[str] = ()) -> str:
    """SHA-256 (16 hex digits) of every value a row has, but those of ``leave_out`` and the digest
    itself. An empty value is left out, so a column added to a table later changes no digest, and
    values are written as `canonical`, so the digest survives a round trip through CSV."""
    skip = {DIGEST_COLUMN, *leave_out}
    text = "\x1f".join(f"{c}={canonical(row[c])}" for c in sorted(map(str, row))
                       if c not in skip and not is_missing(row[c]))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def digest_holds(row: dict, leave_out: Iterable[str] = ()) -> bool:
    """Whether a row read back carries the digest of its values (`row_digest`, leaving out
    ``leave_out``): the one check of every table whose rows have one."""
    written = row.get(DIGEST_COLUMN)
    return isinstance(written, str) and written == row_digest(row, leave_out)


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


#: A results table is a few MB; anything far larger is not one, and is not read back (the readers
#: of a study's earlier table: `benchmark.core.study_store.read_rows`, `benchmark.runs.table.read_runs`).
MAX_TABLE_BYTES = 512 * 2**20


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
    canon = sorted(sorted((str(k), canonical(v)) for k, v in r.items() if k not in drop) for r in rows)
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

        from reelbench.models.io import WriteFailed

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
    from reelbench.models.io import FileRefused, require_regular

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
    from reelbench.integrators import Trajectory

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
    from reelbench.integrators import Trajectory

    return Trajectory(**{k: arrays.get(k) for k in TRAJECTORY_ARRAYS}, **meta)
