"""The answer, `python -m benchmark answer`: each method's cheapest setting at each target found
by search, and wall-time verdicts from paired timing, at one or more string sizes (N = 10 and
N = 40 by default).

Two studies on the one runner (`benchmark.core.study.run`: its engine, its merged table written
after every row, resume by key, a row digest), run in one lock on the output directory:

1. **search** (``search.csv``): one row per scene × N × method × step axis × target
   (`benchmark.answer.jobs.run_search`), in worker processes (or on Dask), the references they
   read computed first;
2. **timing** (``timing.csv``): one row per scene × N × target times the compiled methods that met
   it, paired on one pinned core (`benchmark.answer.jobs.run_timing`), in this process one job
   after another (never two timings at once).

Then ``cheapest.csv`` (`benchmark.answer.table.answer_table`), ``answer.md`` (the README's answer
block), README.md and the work–precision figures (`benchmark.answer.answer_report`), from the
whole merged tables; into the committed results/, the project README's answer block too. A run
keeps the rows of other scenes, sizes, methods and targets already in its output, and replaces
its own (so the extended answer adds to the main job's); a stop keeps every finished row, of
either stage, and the same command resumes.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from reelbench.benchmark.answer import jobs as _jobs
from reelbench.benchmark.answer import search as _search
from reelbench.benchmark.core import engine
from reelbench.benchmark.core.policy import PAIRED_BUDGET, RESULTS, SEARCH_TIME_LIMIT
from reelbench.benchmark.core.store import frame
from reelbench.benchmark.core.study import KEY_COLUMN, Study, job_key
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

#: The two tables, their columns and a row's place in each: one row per search, one per timing.
SEARCH_TABLE, TIMING_TABLE = "search.csv", "timing.csv"
SEARCH_COLUMNS = ["scene", "elements", "integrator", "sweep", "metric", "target", "setting", "cost", "cost_column",
                  "error", "setting_low", "setting_high", "setting_finer", "high_status", "bound", "runs", "spread",
                  "confirmed", "erratic_above", "implementation", "note", "points", "job_time", KEY_COLUMN,
                  "row_digest"]
TIMING_COLUMNS = ["scene", "elements", "metric", "target", "ratios", "rounds", "seconds", "core", "load_avg",
                  "note", KEY_COLUMN, "row_digest"]
SEARCH_IDENTITY = ("scene", "elements", "integrator", "sweep", "metric", "target")
TIMING_IDENTITY = ("scene", "elements", "metric", "target")
#: What a row's digest leaves out besides itself (`benchmark.core.store.row_digest`): its resume
#: key and how long its job took.
NOT_DIGESTED = (KEY_COLUMN, "job_time")
#: The source a search row depends on beyond the runs' code (`benchmark.core.store.code_version`),
#: and a timing row.
SEARCH_CODE = ("benchmark/answer/jobs.py", "benchmark/answer/search.py", "benchmark/work/flops.py")
TIMING_CODE = ("benchmark/answer/jobs.py", "benchmark/answer/paired.py")

#: Where the committed answer lives: an `answer` run into it also rewrites the README's answer block.
COMMITTED_ANSWER = RESULTS


def is_committed_answer(out: Path) -> bool:
    from reelbench.benchmark.core.store import ROOT

    try:
        return Path(out).resolve() == (ROOT / COMMITTED_ANSWER).resolve()
    except OSError:
        return False


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
    max_steps: int | None = None  # each search solve's budget (None: no step cap)
    time_limit: float = SEARCH_TIME_LIMIT
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


# ------------------------------------------------------------------------------------------
# The two studies, and the run
# ------------------------------------------------------------------------------------------
class _Merged:
    """A stage's `Study.report`: keeps the whole merged table (its rows), for the next stage and
    the answer's report, which are written once both stages are done."""

    def __init__(self, columns: list[str]):
        self.columns, self.rows = columns, []

    def __call__(self, out: Path, rows: list[dict], provenance) -> str:
        self.rows = rows
        return ""

    def frame(self, rows: list[dict] | None = None):
        return frame(self.rows if rows is None else rows, self.columns)


def _reusable_search(row: dict) -> bool:
    """A search kept on resume: any that ended, but one whose worker died or that raised."""
    from reelbench.integrators.base import RETRY_STATUSES  # here: the command line's start loads no integrator

    return str(row.get("bound", "")) not in RETRY_STATUSES


def search_study(request: AnswerRequest, cache_dir: str, merged: _Merged) -> Study:
    """The searches of ``request`` as a study (its jobs made, its names checked); ``merged`` gets
    the whole merged search table."""

    jobs = _jobs.search_jobs(request.scenes, request.integrators, list(request.targets), request.elements,
                             request.t_end, request.max_runs, request.max_steps, request.time_limit)
    costs = dict(zip(jobs, _jobs.search_costs(jobs)))
    return Study(name="answer search", table=SEARCH_TABLE, identity=SEARCH_IDENTITY, jobs=jobs,
                 run_job=functools.partial(_jobs.run_search, cache_dir=cache_dir),
                 identity_of=lambda j: tuple(getattr(j, c) for c in SEARCH_IDENTITY), frame=merged.frame,
                 report=merged, describe=_jobs.describe_search,
                 key=lambda j: job_key({"search": asdict(j)}, *SEARCH_CODE), crash_row=_jobs.search_crash_row,
                 group=_jobs.search_group, cost=costs.__getitem__, reusable=_reusable_search, digest=NOT_DIGESTED,
                 setup=lambda todo: _jobs.references(todo, cache_dir), unit="searches",
                 workers=0 if request.executor == "serial" else (request.jobs or engine.default_workers(len(jobs))),
                 scheduler=request.scheduler if request.executor == "dask" else None)


def timing_study(request: AnswerRequest, searched, merged: _Merged) -> Study:
    """The paired timings of the searches ``searched`` (the whole merged search table), in this
    process one after another (one pinned core, never two at once); ``merged`` gets the whole
    merged timing table."""
    return Study(name="answer timing", table=TIMING_TABLE, identity=TIMING_IDENTITY,
                 jobs=_jobs.timing_jobs(searched, request.t_end, request.timing_budget), run_job=_jobs.run_timing,
                 identity_of=lambda j: tuple(getattr(j, c) for c in TIMING_IDENTITY), frame=merged.frame,
                 report=merged, describe=_jobs.describe_timing,
                 key=lambda j: job_key({"timing": asdict(j)}, *TIMING_CODE), cost=lambda j: j.budget + 5.0,
                 reusable=lambda row: True, digest=NOT_DIGESTED, unit="paired timings", workers=0)


def run_answer(request: AnswerRequest, log: Callable[[str], None] = engine.log_stderr) -> int:
    """search.csv, timing.csv (each written after every job), cheapest.csv, answer.md, README.md
    and the work–precision figures into ``request.out``; a stopped study keeps its finished rows
    and resumes from them. Into the committed results/, the project README's answer block too."""
    import pandas as pd

    from reelbench.benchmark.core import study
    from reelbench.benchmark.core.reference import CACHE_DIR
    from reelbench.benchmark.core.report import Provenance
    from reelbench.benchmark.core.study_store import read_rows

    out, provenance = Path(request.out), Provenance(request.command)
    others = [(p, pd.read_csv(p)) for p in request.compare_with]  # read now: one may be this run's own output
    searched, timed = _Merged(SEARCH_COLUMNS), _Merged(TIMING_COLUMNS)
    search = search_study(request, str(CACHE_DIR), searched)  # its input checked before the lock and any work
    tables: list = []  # the merged tables of the two stages, as the runner reads them
    run = functools.partial(study.run, out=out, command=request.command, fresh=request.fresh, log=log, held=True,
                            tables=tables)
    try:
        with study.exclusive(out, log):
            read_rows(out / TIMING_TABLE, TIMING_IDENTITY)  # an unreadable timing.csv is refused before any work
            log(f"{len(search.jobs)} searches: {len(request.scenes)} scene(s) × N = "
                f"{', '.join(map(str, request.elements))} × {len(request.integrators)} method(s) × "
                f"{len(request.targets)} target(s); results -> {out}/")
            run(search)
            search_table = searched.frame()  # the whole merged table, earlier runs' rows included
            timing = timing_study(request, search_table, timed)
            log(f"{len(timing.jobs)} paired timings (at most {request.timing_budget:g} s each, on one pinned core)")
            run(timing)
            kept = {r.get("row_digest") for t in tables for r in t.base}  # rows of earlier runs
            _report(request, out, search_table, timed.frame(), others, provenance, search.workers, kept, log)
    except KeyboardInterrupt as exc:
        search_rows, timing_rows = ([t.saved for t in tables] + [0, 0])[:2]
        return engine.stopped(exc, f"{search_rows} search row(s) and {timing_rows} timing row(s) are saved in {out}; "
                                   "run the same command again to resume", log)
    log(f"done in {provenance.wall_time():.0f} s: {out}/cheapest.csv, {out}/README.md")
    return 0


def _report(request: AnswerRequest, out: Path, searched, timed, others: list, provenance, workers: int, kept: set,
            log: Callable[[str], None]) -> None:
    """cheapest.csv, answer.md, the figures and README.md from the whole merged tables; into the
    committed results/, the project README's answer block too."""
    from reelbench.benchmark.answer import answer_report
    from reelbench.benchmark.answer.table import answer_table
    from reelbench.benchmark.core.store import write_table
    from reelbench.models.io import atomic_write_text

    table = answer_table(searched, timed)
    write_table(out / "cheapest.csv", table)
    labels = labels_of(table[["metric", "target"]].drop_duplicates().itertuples(index=False))
    block = answer_report.answer_block(table, labels, request.command, _shown(out / "cheapest.csv"))
    atomic_write_text(out / "answer.md", block)
    made = answer_report.figures(searched, out)
    compared = [answer_report.agreement_text(table, other, f"`{p}`") for p, other in others]
    for text in compared:
        log(text.rstrip())
    spent = answer_report.accounting(searched, timed, provenance.wall_time(), workers, kept)
    log(spent)
    atomic_write_text(out / "README.md", answer_report.readme(block.splitlines(), made,
                                                              provenance.header() + "\n\n" + spent, compared))
    log(f"{out}/README.md and {len(made)} work–precision figure(s) written")
    if is_committed_answer(out):
        from reelbench.benchmark.core.store import ROOT

        log(answer_report.write_answer(ROOT / "README.md", block))
