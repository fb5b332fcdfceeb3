"""The results store: what a study writes to disk, and what of an earlier run it may keep.

* One writer per output directory (`OutputLock`).
* Tables are written whole and atomically after every finished row (`TableWriter`), so an
  interrupted study leaves the last complete table, never half a file.
* Resume: every row of the runs table carries a `run_key` (scene physics, integrator,
  setting, horizon, save interval, code version); `kept_rows` keeps the rows of an earlier
  table (`read_previous`) with the same key, so only the rest is computed. Rows whose status
  may have been transient (`RETRY_STATUSES`) are never kept.
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

from models.io import atomic_path, atomic_write_text

ROOT = Path(__file__).resolve().parent.parent


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


#: The source that determines a row of the runs table: the model, the integrators, and the
#: benchmark code that runs a task, measures it and computes its reference.
_CODE_DIRS = ("models", "integrators")
_CODE_FILES = ("benchmark/runner.py", "benchmark/metrics.py", "benchmark/reference.py", "benchmark/sweep.py")


def code_version() -> str:
    """A hash of the source that determines a row (`_CODE_DIRS`, `_CODE_FILES`): rows computed
    by other code are recomputed on resume, never mixed in."""
    return source_hash(_CODE_DIRS, _CODE_FILES)


def run_key(task, code: str | None = None) -> str:
    """Identity of a task's row (a `benchmark.sweep.Task`): the scene's physics hash (not its
    name), the integrator, the setting, horizon and save interval, and the code version."""
    from models import load_scene

    scene = load_scene(task.scene, **dict(task.overrides))
    what = {"scene": scene.key(), "integrator": task.integrator, "dt": task.dt, "rtol": task.rtol,
            "atol": task.atol, "t_end": task.t_end if task.t_end is not None else scene.t_end,
            "save_every": task.save_every, "code": code or code_version()}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------
# Resume: which rows of an earlier run are kept
# ------------------------------------------------------------------------------------------
#: Rows with these statuses are recomputed on resume (the cause may have been transient).
RETRY_STATUSES = ("crashed", "error")


def read_previous(path: str | os.PathLike, log: Callable[[str], None] | None = None) -> list[dict]:
    """The rows of an earlier run's ``runs.csv`` that can be resumed from (none if the file is
    missing, unreadable or has no `run_key` column)."""
    import pandas as pd

    path = Path(path)
    if not path.exists():
        return []
    try:
        df = pd.read_csv(path)
    except Exception as exc:  # a damaged table is not a reason to stop: start afresh
        if log:
            log(f"warning: {path} cannot be read ({type(exc).__name__}); its rows are recomputed")
        return []
    if "run_key" not in df or "status" not in df:
        return []
    df = df[~df["status"].isin(RETRY_STATUSES)]
    if "reason" in df:
        df["reason"] = df["reason"].fillna("")
    return df.to_dict("records")


def kept_rows(keys: list[str], previous: Iterable[dict] | None) -> dict[int, dict]:
    """{index: earlier row} for every key of ``keys`` that a row of ``previous`` carries."""
    kept = {r["run_key"]: r for r in (previous or []) if r.get("run_key")}
    return {i: kept[k] for i, k in enumerate(keys) if k in kept}


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


# ------------------------------------------------------------------------------------------
# One writer per output directory
# ------------------------------------------------------------------------------------------
class LockedError(ValueError):
    """Another live process holds the output directory's lock."""


class OutputLock:
    """``with OutputLock(out):`` -- at most one study writes into ``out`` at a time.

    The lock is a file holding the owner's pid and host; a lock whose pid no longer runs on
    this host (a run killed with -9) is taken over."""

    NAME = ".reelbench.lock"

    def __init__(self, directory: str | os.PathLike, log: Callable[[str], None] | None = None):
        self.path = Path(directory) / self.NAME
        self.log = log
        self.held = False

    def _holder(self) -> dict | None:
        try:
            return json.loads(self.path.read_text())
        except (OSError, ValueError):
            return None

    @staticmethod
    def _alive(pid: int) -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # exists, owned by someone else
            return True
        return True

    def acquire(self) -> "OutputLock":
        me = {"pid": os.getpid(), "host": socket.gethostname(), "command": " ".join(sys.argv)}
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                self._refuse_or_take_over()
                continue
            with os.fdopen(fd, "w") as fh:
                json.dump(me, fh)
            self.held = True
            return self
        raise LockedError(f"could not take the lock {self.path}; delete it if no run is using {self.path.parent}/")

    def _refuse_or_take_over(self) -> None:
        """LockedError naming the holder if it is alive; else remove its stale lock."""
        holder = self._holder()
        if holder is None:  # half-written by a holder that is starting: give it a moment
            time.sleep(0.2)
            holder = self._holder() or {}
        pid, host = holder.get("pid"), holder.get("host")
        if isinstance(pid, int) and (host != socket.gethostname() or self._alive(pid)):
            raise LockedError(
                f"{self.path.parent}/ is in use by another run (pid {pid} on {host}: "
                f"{holder.get('command', '?')}); lock file {self.path}. Wait for it to finish or "
                f"use another --out; if that run is gone, delete the lock file") from None
        if self.log:
            self.log(f"taking over the stale lock {self.path} (pid {pid} is not running)")
        self.path.unlink(missing_ok=True)

    def release(self) -> None:
        if self.held:
            holder = self._holder()
            if holder is None or holder.get("pid") == os.getpid():
                self.path.unlink(missing_ok=True)
            self.held = False

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# ------------------------------------------------------------------------------------------
# Trajectory files
# ------------------------------------------------------------------------------------------
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
    # an .npz is a zip archive; random bytes, a pickle or a cut file are not
    if not zipfile.is_zipfile(path):
        raise UnreadableFile("not an .npz archive: truncated or not written by reelbench")


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
