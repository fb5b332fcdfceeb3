"""One runner for every study that writes a table into a directory.

A study supplies what is its own (`Study`): its jobs, how one runs, the identity of the row a
job makes, its table's columns and its report. `run` owns the rest, the same for every study:

- the jobs are made (input checked) before any work, and before the lock is taken;
- one writer per output directory (`exclusive`: the lock, with Ctrl-C and SIGTERM stopping the
  study as KeyboardInterrupt);
- the earlier table there is read once, under the lock, and refused before any work when it
  cannot be read (`study_store.MergedTable`; a study with a reading policy of its own, the runs
  table's, plugs it in: `Study.read`); this run's rows replace those with the same identity and
  every other row is kept;
- the jobs run on the engine (workers, this process or Dask), and the merged table is written
  atomically after every finished row (what the study keeps beside it first, `Study.beside`), so
  a stop keeps every finished row;
- a rerun resumes: a job whose finished row is in the table, made from the same key
  (`Study.key`: the code and settings that determine it), is not run again, unless ``fresh``;
- a study whose rows carry a digest (`Study.digest`, `benchmark.core.store.row_digest`) has
  each row it makes written with it, and an earlier row whose digest fails is named and dropped
  (recomputed when this run has its job); the earlier rows it keeps keep their digests;
- the report is written from the whole merged table, also when the study is stopped (unless
  the report is itself work a stop must not start: `Study.report_on_stop`);
- a stop is one line saying what was saved and how to resume (exit 130 / 143), in the study's
  words (`Wording`); a failing disk one line and exit 1;
  a job that failed (`Study.failure`) one error line at the end, and exit 1.

A study may run inside another that holds the same directory (``held``: `run --horizon` makes the
energy study in its own output; the answer runs its searches, then its timings, in one lock): the
caller then owns the lock and the stop, and reads what each study saved (``tables``).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Hashable

from reelbench.benchmark.core import engine, store
from reelbench.benchmark.core.engine import log_stderr
from reelbench.benchmark.core.report import Provenance
from reelbench.models.io import printable

#: The column where a row keeps the key it was made from (`Study.key`), for resume.
KEY_COLUMN = "job_key"


@dataclass(frozen=True)
class Wording:
    """How the runner's lines name a study's rows: ``row`` what a finished job makes ("no row had
    finished"), ``saved`` what became of them ("3 finished row(s) are merged into PATH") and
    ``kept`` the line of a resumed run (a format of ``name``, ``kept``, ``total``, ``left`` and
    ``unit``). The lines are the same for every study; only these words are a study's."""

    row: str = "row"
    saved: str = "are merged into"
    kept: str = "{name}: kept {kept} of {total} {unit} (same code and settings; --fresh recomputes them)"


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
      ``key_column``: where a row keeps it;
    - ``digest``: the columns a row's digest (`benchmark.core.store.row_digest`) leaves out,
      besides itself; None: the rows carry no digest;
    - ``crash_row(job, exc)``: the row of a job whose worker died (None: the death is raised);
    - ``group(job)`` / ``cost(job)``: jobs that share a compile run in one worker; the longest
      start first and weigh the ETA;
    - ``setup``: calls that run before the jobs, spread over the workers (e.g. the reference
      solution the jobs read from a cache): a tuple of calls, or ``setup(jobs)``, the (label,
      call) pairs that the jobs this run runs need (those kept on resume need none);
    - ``expand(row)``: the table rows of a job's row (a run's history), which replace that job's
      earlier rows as a whole; none: the job's earlier rows go;
    - ``read_earlier(df)``: the study's reading of its earlier table as read (a DataFrame): the
      rows it keeps, in its columns (e.g. a table of older code given the columns it lacks);
    - ``read(path, log)``: a reading policy of the study's own, in place of the runner's
      (`study_store.read_rows`): the rows of the earlier table to merge with ([] when there is
      none), each already checked (its digest too); it may refuse the run (ValueError), before
      any work, and may move rows it does not keep aside;
    - ``reusable(row)``: whether an earlier row made from the same key is kept on resume
      (default: a finished run's, `is_finished`);
    - ``failure(row)``: for a row that is no result (a job whose worker died and that makes no
      table row), what failed, in a few words; None for a result;
    - ``after_jobs(out, log)``: a step of the study's own once its jobs are done, before its
      report (skipped when stopped): e.g. a measurement its report reads beside the table;
    - ``report_on_stop``: whether a stopped study writes its report (False where the report is
      work of its own, such as a solve for a figure, which a stop must not start);
    - ``wording``: how the runner's lines name its rows (`Wording`);
    - ``beside(out, rows)``: writes what the study keeps beside its table from the merged table
      rows (e.g. arrays a CSV cannot hold), before each save of the table, so that every saved
      row has it;
    - ``unit``: what the log lines call its jobs;
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
    read_earlier: Callable[[Any], Any] | None = None
    reusable: Callable[[dict], bool] | None = None
    failure: Callable[[dict], str | None] | None = None
    after_jobs: Callable[[Path, Callable[[str], None]], None] | None = None
    beside: Callable[[Path, list[dict]], None] | None = None
    unit: str = "jobs"
    key_column: str = KEY_COLUMN
    digest: tuple[str, ...] | None = None
    text_columns: tuple[str, ...] = ()
    workers: int = 0
    scheduler: str | None = None
    setup: tuple | Callable[[list], list[tuple[str, Callable]]] = field(default=())
    header: str = "README.md"
    read: Callable[[Path, Callable[[str], None]], list[dict]] | None = None
    report_on_stop: bool = True
    wording: Wording = Wording()


def job_key(settings: dict, *files: str) -> str:
    """A `Study.key`: a short hash of what determines a job's row, its ``settings`` (JSON), the
    code version (`benchmark.core.store.code_version`) and the study's own source ``files``
    (paths from the repository root)."""
    return store.key_of({"settings": settings, "code": store.code_version(), "study": store.source_hash((), files)})


def _kept(study: Study, earlier: list[dict]) -> dict[int, dict]:
    """The jobs whose finished row(s) (`Study.reusable`), made from the same key, the table
    already holds (their rows stay in the table as they are)."""
    if study.key is None:
        return {}
    from reelbench.integrators.base import is_finished  # here: a command line's start loads no integrator

    reusable = study.reusable or (lambda r: is_finished(str(r.get("status", ""))))
    column = study.key_column
    finished = {store.identity_of(r, study.identity): r for r in earlier if reusable(r) and r.get(column)}
    kept = {}
    for i, job in enumerate(study.jobs):
        row = finished.get(tuple(study.identity_of(job)))
        if row is not None and str(row[column]) == study.key(job):
            kept[i] = row
    return kept


def run(study: Study, out: Path, *, command: str, fresh: bool = False,
        log: Callable[[str], None] = log_stderr, held: bool = False, failed: list | None = None,
        tables: list | None = None) -> int:
    """Run ``study`` into ``out`` (see the module's docstring); returns the exit status.
    ``held``: the caller holds ``out``'s lock and handles a stop or a failing disk (raised to it,
    the finished rows saved). ``failed``: gets what failed of each failed job (`Study.failure`).
    ``tables``: gets the study's merged table (`study_store.MergedTable`) once it is read, for a
    caller that holds the lock: what a stop leaves (its ``saved`` rows, `stop_note`) and the rows
    it read from earlier runs (its ``base``)."""
    out = Path(out)
    session = _Session(study, out, Provenance(command, workers=study.workers or 1), log, tables)
    if held:
        return session.run(fresh, failed)
    try:
        with exclusive(out, log):
            return session.run(fresh, failed)
    except KeyboardInterrupt as exc:
        table = session.table
        if table is None:
            return engine.stopped(exc, "nothing was written", log)
        note = table.stop_note(study.wording)
        if table.saved and study.report_on_stop:
            try:  # the report of the whole merged table, so that it agrees with the table
                wrote = session.report()
                note += "; the report is written from it" + (f" ({wrote})" if wrote else "")
            except Exception as err:  # noqa: BLE001 - the stop line must come out whatever the report does
                note += f"; its report was not written ({type(err).__name__})"
        return engine.stopped(exc, f"{note}; {_again(study)}", log)
    except OSError as exc:  # a full or failing disk: what was written is intact
        table = session.table
        if table is None:
            log(f"error: {printable(exc)}; nothing was written")
        else:
            log(f"error: {printable(exc)}; {table.stop_note(study.wording)}; free space (or fix the file system) "
                f"and {_again(study)}")
        return 1


def _setup(study: Study, todo: list) -> tuple[list, list | None]:
    """(the setup calls, their labels or None) of the jobs ``todo`` (`Study.setup`)."""
    if not callable(study.setup):
        return list(study.setup), None
    pairs = list(study.setup(todo))
    return [call for _, call in pairs], [label for label, _ in pairs]


def _again(study: Study) -> str:
    """What a stopped study's line says to do next."""
    if study.key is None:
        return "run the same command again to compute the rest"
    return (f"run the same command again to resume (finished {study.unit} are kept), or add --fresh to recompute "
            "this run's rows")


class _Session:
    """One run of a study: its merged table (once the lock is held) and this run's rows."""

    def __init__(self, study: Study, out: Path, provenance: Provenance, log: Callable[[str], None],
                 tables: list | None = None):
        self.study, self.out, self.provenance, self.log, self.tables = study, out, provenance, log, tables
        self.table, self.rows, self.kept = None, [], {}

    def run(self, fresh: bool, failed: list | None) -> int:
        from reelbench.benchmark.core.study_store import MergedTable

        study, out, log = self.study, self.out, self.log
        self.table = MergedTable(out / study.table, study.identity, study.frame, text_columns=study.text_columns,
                                 expand=self._expand if study.expand else None, read_earlier=study.read_earlier,
                                 read=study.read, digest=study.digest, log=log)
        if self.tables is not None:
            self.tables.append(self.table)
        self.kept = kept = _kept(study, [] if fresh else self.table.base)
        n = len(study.jobs)
        log(f"{study.name}: {n} {study.unit} on {study.workers or 'this process'}"
            f"{' worker(s)' if study.workers else ''} -> {out}/"
            + (f" (merged with its {self.table.earlier} earlier row(s))" if self.table.earlier else ""))
        if kept:
            log(study.wording.kept.format(name=study.name, kept=len(kept), total=n, left=n - len(kept), unit=study.unit))
        setup, labels = _setup(study, [job for i, job in enumerate(study.jobs) if i not in kept])
        done = engine.run_jobs(
            study.run_job, study.jobs, workers=study.workers, scheduler=study.scheduler, done=kept, finish=self._keyed,
            crash_row=(lambda i, exc: study.crash_row(study.jobs[i], exc)) if study.crash_row else None,
            group=(lambda i: study.group(study.jobs[i])) if study.group else None,
            cost=(lambda i: study.cost(study.jobs[i])) if study.cost else None,
            setup=setup, setup_labels=labels, describe=study.describe, on_row=self._on_rows, log=log)
        self._on_rows(done)
        if study.after_jobs is not None:
            study.after_jobs(out, log)
        wrote = self.report()
        log(f"{study.name}: done in {self.provenance.wall_time():.0f} s" + (f"; {wrote}" if wrote else ""))
        what = [w for w in map(study.failure, self.rows) if w] if study.failure else []
        if failed is not None:
            failed += what
        if what:
            log(f"error: {study.name}: {len(what)} of {n} {study.unit} did not finish: {'; '.join(what)}; "
                f"{self.table.path} holds the others")
            return 1
        return 0

    def _keyed(self, i: int, row: dict) -> None:
        if self.study.key is not None:
            row[self.study.key_column] = self.study.key(self.study.jobs[i])

    def _expand(self, row: dict) -> list[dict]:  # every table row a job makes carries the job's key
        column = self.study.key_column
        return [{**x, column: row[column]} if column in row else x for x in self.study.expand(row)]

    def _on_rows(self, done: list[dict]) -> None:
        self.rows[:] = [r for r in done if not any(r is k for k in self.kept.values())]  # kept rows are in the table
        if self.study.beside is not None:  # first: a saved row always has what the study keeps beside it
            self.study.beside(self.out, self.table.merged(self.rows))
        self.table(self.rows)

    def report(self) -> str:
        table, rows = self.table, self.rows
        return self.study.report(self.out, table.merged(rows),
                                 table.provenance(self.provenance, rows, self.out / self.study.header))
