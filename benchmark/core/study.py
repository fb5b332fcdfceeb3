"""One runner for every study that writes a table into a directory.

A study supplies what is its own (`Study`): its jobs, how one runs, the identity of the row a
job makes, its table's columns and its report. `run` owns the rest, the same for every study:

- the jobs are made (input checked) before any work, and before the lock is taken;
- one writer per output directory (`exclusive`: the lock, with Ctrl-C and SIGTERM stopping the
  study as KeyboardInterrupt);
- the earlier table there is read once, under the lock, and refused before any work when it
  cannot be read (`study_store.MergedTable`); this run's rows replace those with the same
  identity and every other row is kept;
- the jobs run on the engine (workers, this process or Dask), and the merged table is written
  atomically after every finished row, so a stop keeps every finished row;
- a rerun resumes: a job whose finished row is in the table, made from the same key
  (`Study.key`: the code and settings that determine it), is not run again, unless ``fresh``;
- the report is written from the whole merged table, also when the study is stopped;
- a stop is one line saying what was saved (exit 130 / 143); a failing disk one line and exit 1.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Hashable

from benchmark.core import engine, store
from benchmark.core.engine import log_stderr
from benchmark.core.report import Provenance
from integrators.base import is_finished
from models.io import printable

#: The column where a row keeps the key it was made from (`Study.key`), for resume.
KEY_COLUMN = "job_key"


@contextlib.contextmanager
def exclusive(out: Path, log: Callable[[str], None]):
    """Hold ``out``'s lock, with Ctrl-C and SIGTERM both stopping the study (KeyboardInterrupt)."""
    with store.OutputLock(out, log=log):
        engine.install_stop_handlers()
        yield


@dataclass
class Study:
    """What a study supplies to `run`. ``run_job`` (and the jobs) must pickle for the workers:
    a module-level function. Every callable other than ``run_job`` runs in this process.

    - ``name``: what the log lines call it;
    - ``table``: the file name of its rows table in the output directory;
    - ``identity``: the columns that name a row (a rerun's row replaces the earlier one);
    - ``jobs``: every job of this run, its input already checked;
    - ``identity_of(job)``: the identity of the row the job makes;
    - ``frame(rows)``: the table of rows, its columns in order;
    - ``report(out, rows, provenance)``: writes the study's other files from the whole merged
      table; returns a line saying what it wrote ("" for nothing);
    - ``header``: the file in the output directory whose header names the earlier runs (the
      provenance of a merged table);
    - ``key(job)``: what determines the job's row (code and settings); None: not resumable;
    - ``crash_row(job, exc)``: the row of a job whose worker died (None: the death is raised);
    - ``group(job)`` / ``cost(job)``: jobs that share a compile run in one worker; the longest
      start first and weigh the ETA;
    - ``workers``: 0 in this process, else that many worker processes; ``scheduler``: a Dask
      address."""

    name: str
    table: str
    identity: tuple[str, ...]
    jobs: list
    run_job: Callable[[Any], dict]
    identity_of: Callable[[Any], tuple]
    frame: Callable[[list[dict]], Any]
    report: Callable[[Path, list[dict], Provenance], str]
    describe: Callable[[dict], str] = str
    key: Callable[[Any], str] | None = None
    crash_row: Callable[[Any, BaseException], dict] | None = None
    group: Callable[[Any], Hashable] | None = None
    cost: Callable[[Any], float] | None = None
    expand: Callable[[dict], list[dict]] | None = None
    text_columns: tuple[str, ...] = ()
    workers: int = 0
    scheduler: str | None = None
    setup: tuple = field(default=())
    header: str = "README.md"


def job_key(settings: dict, *files: str) -> str:
    """A `Study.key`: a short hash of what determines a job's row, its ``settings`` (JSON), the
    code version (`benchmark.core.store.code_version`) and the study's own source ``files``
    (paths from the repository root)."""
    import hashlib
    import json

    what = {"settings": settings, "code": store.code_version(), "study": store.source_hash((), files)}
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _kept(study: Study, earlier: list[dict]) -> dict[int, dict]:
    """The jobs whose finished row(s), made from the same key, the table already holds (their
    rows stay in the table as they are)."""
    if study.key is None:
        return {}
    finished = {store.identity_of(r, study.identity): r for r in earlier
                if is_finished(str(r.get("status", ""))) and r.get(KEY_COLUMN)}
    kept = {}
    for i, job in enumerate(study.jobs):
        row = finished.get(tuple(study.identity_of(job)))
        if row is not None and str(row[KEY_COLUMN]) == study.key(job):
            kept[i] = row
    return kept


def run(study: Study, out: Path, *, command: str, fresh: bool = False,
        log: Callable[[str], None] = log_stderr) -> int:
    """Run ``study`` into ``out`` (see the module's docstring); returns the exit status."""
    from benchmark.core.study_store import MergedTable

    out = Path(out)
    provenance = Provenance(command, workers=study.workers or 1)
    jobs, rows, table, kept = study.jobs, [], None, {}

    def keyed(i: int, row: dict) -> None:
        if study.key is not None:
            row[KEY_COLUMN] = study.key(jobs[i])

    def expand(row: dict) -> list[dict]:  # every table row a job makes carries the job's key
        return [{**x, KEY_COLUMN: row[KEY_COLUMN]} if KEY_COLUMN in row else x for x in study.expand(row)]

    def on_rows(done: list[dict]) -> None:
        rows[:] = [r for r in done if not any(r is k for k in kept.values())]  # kept rows are in the table
        table(rows)

    def report(done: list[dict]) -> str:
        return study.report(out, table.merged(done), table.provenance(provenance, done, out / study.header))

    try:
        with exclusive(out, log):
            table = MergedTable(out / study.table, study.identity, study.frame, text_columns=study.text_columns,
                                expand=expand if study.expand else None)
            kept = {} if fresh else _kept(study, table.base)
            log(f"{study.name}: {len(jobs)} job(s) on {study.workers or 'this process'}"
                f"{' worker(s)' if study.workers else ''} -> {out}/"
                + (f" (merged with its {table.earlier} earlier row(s))" if table.earlier else "")
                + (f"; {len(kept)} kept (finished, same code and settings; --fresh recomputes them)" if kept else ""))
            done = engine.run_jobs(
                study.run_job, jobs, workers=study.workers, scheduler=study.scheduler, done=kept, finish=keyed,
                crash_row=(lambda i, exc: study.crash_row(jobs[i], exc)) if study.crash_row else None,
                group=(lambda i: study.group(jobs[i])) if study.group else None,
                cost=(lambda i: study.cost(jobs[i])) if study.cost else None,
                setup=study.setup, describe=study.describe, on_row=on_rows, log=log)
            on_rows(done)
            wrote = report(rows)
            log(f"{study.name}: done in {provenance.wall_time():.0f} s" + (f"; {wrote}" if wrote else ""))
            return 0
    except KeyboardInterrupt as exc:
        if table is None:
            return engine.stopped(exc, "nothing was written", log)
        note = table.stop_note()
        if table.saved:
            try:  # the report of the whole merged table, so that it agrees with the table
                wrote = report(rows)
                note += "; the report is written from it" + (f" ({wrote})" if wrote else "")
            except Exception as err:  # noqa: BLE001 - the stop line must come out whatever the report does
                note += f"; its report was not written ({type(err).__name__})"
        return engine.stopped(exc, f"{note}; run the same command again to compute the rest", log)
    except OSError as exc:  # a full or failing disk: what was written is intact
        log(f"error: {printable(exc)}; {table.stop_note() if table is not None else 'nothing was written'}")
        return 1
