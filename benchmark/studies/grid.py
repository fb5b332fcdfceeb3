"""The grid sweep, `python -m benchmark run`: every scene × integrator × setting of the sweep
(`benchmark.runs.sweep`) measured once each (`benchmark.runs.runner`) into ``--out``
(results/grid/ by default): runs.csv (written after every run), runs.md, the figures, the
energy study when --horizon asks for one (`benchmark.studies.horizon`) and README.md
(`runs_report`). It ranks nothing: the answer is `benchmark.answer.answer`'s.

The sweep is a study of the one runner (`benchmark.core.study.run`; `GridSweep`): one job per
task, its row keyed by `benchmark.runs.table.run_key` and carrying the runs table's digest. The
runner holds the output lock, merges the run's rows into the table already in ``--out``
(`benchmark.core.store.merge_rows`) and saves it after every run, resumes, and ends a stop in one
line (exit 130 / 143) with every finished row kept. What the runs table adds is its own: how its
earlier table is read (`benchmark.runs.table.read_runs`: untrusted rows named and recomputed, a
table that cannot be read whole salvaged) and what may join it (`_merge_plan`: refused before
any work, rows set aside, --accept-legacy). Rows of other scenes, methods or settings are kept
and every file is written from the merged table.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, NamedTuple

from reelbench.benchmark.core import engine
from reelbench.benchmark.core import store
from reelbench.benchmark.runs import sweep
from reelbench.benchmark.runs import table as runs_table
from reelbench.benchmark.core.policy import GRID_DIR, ROW_IDENTITY, SAVE_EVERY
from reelbench.benchmark.core.engine import log_stderr
from reelbench.benchmark.core.study import Study, Wording
from reelbench.benchmark.core.report import Provenance
from reelbench.models.io import inside


@dataclass(frozen=True)
class SweepRequest:
    """What `python -m benchmark run` asks for (its options, checked)."""

    out: Path
    scenes: tuple
    integrators: tuple | None = None
    quick: bool = False
    dts: tuple | None = None
    rtols: tuple | None = None
    t_end: float | None = None  # None: each scene's own (--quick: sweep.QUICK_T_END)
    overrides: tuple = ()  # ((key, value), ...) of the scenes, t_end apart
    jobs: int | None = None
    executor: str = sweep.DEFAULT_EXECUTOR
    scheduler: str | None = None
    repeats: int = sweep.MIN_REPEATS
    horizon: float | None = None  # of the energy study; None or 0: none (it is `python -m benchmark energy`'s)
    figures: bool = True
    fresh: bool = False
    compare_with: tuple[str, ...] = ()  # earlier runs.csv files, one README section each
    accept_legacy: bool = False  # keep rows of --out that predate full row digests (then given digests)
    command: str = "python -m benchmark run"
    budget: Any = None  # of each solve (`benchmark.runs.runner.SolveBudget`); None: the default

    @property
    def sweep_t_end(self) -> float | None:
        return sweep.sweep_t_end(self.t_end, self.quick)

    @property
    def energy_horizon(self) -> float:
        """The energy study's horizon, 0 when the run has none (the study is opt-in: --horizon)."""
        return self.horizon or 0.0

    def scene(self, name: str):
        """A scene of the sweep as its runs see it (overrides and --t-end applied)."""
        from reelbench.models import load_scene

        return load_scene(name, **dict(self.overrides), **({"t_end": self.t_end} if self.t_end is not None else {}))


def run_sweep(request: SweepRequest, log: Callable[[str], None] = log_stderr) -> int:
    """The grid sweep into ``request.out``, a study of the one runner (`benchmark.core.study.run`,
    `GridSweep`): runs.csv (written after every run), runs.md, the figures, the energy study when
    ``request.horizon`` asks for one, and README.md (with the orders of the `orders` study and the
    stability map's evidence, `study_file`). It ranks nothing: the answer is
    `benchmark.answer.answer`'s. The run's rows join the table already in ``out``: rows of other
    scenes, methods or settings are kept, and every file is written from the merged table. A
    stopped sweep keeps its finished rows."""
    from reelbench.benchmark.core import study

    sweep_ = GridSweep(request, log)
    rc = study.run(sweep_.study(), request.out, command=request.command, fresh=request.fresh, log=log)
    if rc == 0 and sweep_.failed:  # what of the energy study did not end with a result (a crashed worker)
        log(f"error: the energy study did not finish for {'; '.join(sweep_.failed)}: its history is not in "
            f"{request.out}/energy_horizon.csv (the runs table is complete)")
        return 1
    return rc


class Job(NamedTuple):
    """One run of the sweep: its task, the key of its row (`benchmark.runs.table.run_key`), whose
    method it is (`benchmark.runs.runner.provenance`) and its predicted seconds."""

    task: Any
    key: str
    origin: dict
    cost: float


def run_job(job: Job, cache_dir: str, repeats: int, budget) -> dict:
    """A job's row of the runs table (`benchmark.runs.runner.run_task`, then `finish_row`)."""
    from reelbench.benchmark.runs import runner

    return runner.finish_row(runner.run_task(job.task, cache_dir, repeats, budget=budget), job.key, job.origin)


def crash_row(job: Job, exc: BaseException) -> dict:
    """The row of a job whose worker died: status "crashed"."""
    from reelbench.benchmark.runs import runner
    from reelbench.integrators.base import CRASHED

    row = {**runner.empty_row(job.task), "status": CRASHED, "reason": engine.crash_reason(exc)}
    return runner.finish_row(row, job.key, job.origin)


def runs_frame(rows):
    """The runs table as runs.csv holds it (`benchmark.runs.runner.runs_frame`, without tracebacks)."""
    from reelbench.benchmark.runs import runner

    return runner.runs_frame(rows).drop(columns=["traceback"], errors="ignore")


#: The runner's lines in the sweep's words ("1 finished run(s) are saved in ...").
WORDING = Wording(row="run", saved="are saved in",
                  kept="resuming: {kept} of {total} {unit} already done (kept); computing the other {left}")


class GridSweep:
    """The grid sweep as a study of the one runner (`study`): its tasks are the jobs, a row's
    identity is `ROW_IDENTITY` and its key `run_key` (in its own column, so that a committed table
    resumes); the runs table's digest (`benchmark.runs.table.DIGEST_EXCLUDED`), reading policy
    (`read`) and rule of which rows a resume trusts (`StoredRuns.reusable`); the reference
    solutions of the runs to compute first (`prepare`, its `Study.setup`); its report (`report`). It holds what
    the runner's calls share: the earlier table as read, the energy study, what of it failed."""

    def __init__(self, request: SweepRequest, log: Callable[[str], None]):
        from reelbench.benchmark.runs import runner

        self.request, self.log = request, log
        tasks = sweep.build_tasks(request.scenes, request.integrators, quick=request.quick,
                                dts=request.dts, rtols=request.rtols, t_end=request.t_end,
                                overrides=dict(request.overrides))
        code = store.code_version()
        origins = {name: runner.provenance(name, code) for name in dict.fromkeys(t.integrator for t in tasks)}
        self.jobs = [Job(t, runs_table.run_key(t, origins[t.integrator]["code_digest"]), origins[t.integrator], c)
                     for t, c in zip(tasks, runner.task_costs(tasks))]
        self.names, self.scenes = _this_run(request, tasks)
        self.stored, self.energy, self.failed = None, None, []

    def study(self) -> Study:
        from reelbench.benchmark.core.reference import CACHE_DIR  # the references every study shares
        from reelbench.benchmark.runs import runner

        request = self.request
        budget = request.budget or runner.SolveBudget()
        serial = request.executor == "serial"
        return Study(
            name="grid sweep", table="runs.csv", identity=ROW_IDENTITY, jobs=self.jobs,
            run_job=functools.partial(run_job, cache_dir=str(CACHE_DIR), repeats=request.repeats, budget=budget),
            identity_of=self.identity_of, frame=runs_frame, report=self.report, describe=runner.describe_run,
            key=lambda job: job.key, key_column="run_key",
            digest=runs_table.DIGEST_EXCLUDED, crash_row=crash_row, cost=lambda job: job.cost,
            group=lambda job: (job.task.scene, job.task.integrator),  # one worker per (scene, method): one compile
            read=self.read, reusable=lambda row: self.stored.reusable(row), setup=self.prepare,
            report_on_stop=False, unit="runs", wording=WORDING,
            workers=0 if serial else (request.jobs or engine.default_workers(len(self.jobs))),
            scheduler=request.scheduler if request.executor == "dask" else None)

    def identity_of(self, job: Job) -> tuple:
        return self.names[job.task.scene], job.task.integrator, job.task.setting

    def read(self, path: Path, log) -> list[dict]:
        """The runs table's reading policy (`benchmark.runs.table.read_runs`: untrusted rows named,
        a table that cannot be read whole salvaged), then `_merge_plan` (refusals, rows set aside,
        --accept-legacy) and the energy study's earlier table checked: all before any work."""
        self.stored = runs_table.read_runs(path, log=log)
        _merge_plan(self.request, set(map(self.identity_of, self.jobs)), self.scenes, self.stored, path, log)
        if self.request.figures and self.request.energy_horizon > 0:
            self.energy = _energy_study(self.request, log)
        return self.stored.rows

    def prepare(self, todo: list[Job]) -> list[tuple[str, Callable]]:
        """The reference solutions of the runs to compute, each a setup call with its label."""
        from reelbench.benchmark.core.reference import CACHE_DIR, ReferenceProblem, prepare_reference

        problems = sorted({ReferenceProblem(t.scene, t.overrides, t.t_end, t.save_every) for t in (j.task for j in todo)},
                          key=str)
        if todo:
            self.log(f"references for {len(problems)} scene(s) ...")
        return [(f"reference {Path(p.scene).stem}" + (f" to t = {p.t_end:g} s" if p.t_end else ""),
                 functools.partial(prepare_reference, p, str(CACHE_DIR))) for p in problems]

    def report(self, out: Path, rows: list[dict], provenance: Provenance) -> str:
        """runs.md, the figures (and the energy study) and README.md of the whole merged table."""
        from reelbench.benchmark.core.report import markdown_table
        from reelbench.benchmark.studies import runs_report
        from reelbench.models.io import atomic_write_text

        request, merged = self.request, runs_frame(rows)
        atomic_write_text(out / "runs.md", markdown_table(merged.drop(columns=[c for c in ("reason", "run_key",
                                                                                          "row_digest", "scene_key")
                                                                               if c in merged])))
        orders = _orders_table(out)  # the short-horizon orders study's (`python -m benchmark orders`), never the sweep's
        failures = runs_report.failure_sentence(merged, study_file(out, "stability/stability.csv"))
        figures = _sweep_figures(request, merged, self.log, self.failed, self.energy) if request.figures else []
        # the README states the runs it merges itself (`_sweep_readme`), and no worker count
        provenance = dataclasses.replace(provenance, workers=None, history=())
        _sweep_readme(request, merged, orders, figures, provenance, failures,
                      merged_note=_merged_note(len(self.jobs), merged))
        return (f"{len(self.jobs)} runs in this run, {len(merged)} in {out}/runs.csv; {failures} "
                f"See {out}/README.md")


#: The committed grid sweep's directory (`python -m benchmark run`'s default --out).
COMMITTED_RESULTS = store.ROOT / GRID_DIR


def study_file(out: Path, name: str) -> Path:
    """``out``/``name``, a file of another study the sweep's README cites (orders.csv,
    stability/stability.csv, energy_horizon.csv); for the committed grid without it, the
    committed one in results/, where those studies write by default."""
    path = Path(out) / name
    if not path.exists() and is_committed_results(out):
        return COMMITTED_RESULTS.parent / name
    return path


def is_committed_results(out: Path) -> bool:
    try:
        return Path(out).resolve() == COMMITTED_RESULTS.resolve()
    except OSError:
        return False


def _this_run(request: SweepRequest, tasks) -> tuple[dict, dict]:
    """({task scene: scene name}, {scene name: (horizon, physics hash)}) of a sweep's tasks."""
    from reelbench.models import load_scene

    names, scenes = {}, {}
    for given in dict.fromkeys(t.scene for t in tasks):
        scene = load_scene(given, **dict(request.overrides))
        names[given] = scene.name
        scenes[scene.name] = (request.sweep_t_end or scene.t_end, scene.key())
    return names, scenes


def _merge_plan(request: SweepRequest, mine: set, scenes: dict, stored: runs_table.StoredRuns, path: Path,
                log) -> None:
    """Refuse a run whose rows (identities ``mine``, of ``scenes``: `_this_run`) cannot join the
    table in its --out (before any work), set aside the untrusted rows no recomputation will
    replace, and say in one line what the run replaces."""
    conflicts = runs_table.merge_conflicts(stored.rows, scenes)
    if conflicts:
        raise ValueError(f"{path} cannot take this run's rows: {'; '.join(conflicts)}. A table holds one horizon and "
                         "one set of scene values per scene: give another --out (a scratch directory), or move "
                         f"{path} away to start over")
    legacy = [r for r in stored.legacy if store.identity_of(r) not in mine]  # kept, not recomputed by this run
    if legacy and not request.accept_legacy:
        raise ValueError(f"{path}: {len(legacy)} row(s) this run keeps predate row digests over every column (their "
                         "timings and flops cannot be verified), e.g. " + runs_table.describe_row(legacy[0]) + ": pass "
                         "--accept-legacy once to keep them (checked by range, then written with digests), or move "
                         f"{path} away to start over")
    aside = [(r, why) for r, why in stored.rejected if store.identity_of(r) not in mine]
    if aside:
        rejected = path.with_name("runs.rejected.csv")
        before = runs_table.read_runs(rejected)
        earlier = before.rows + [r for r, _ in before.rejected]
        store.write_table(rejected, store.frame(store.merge_rows(earlier, [dict(r, rejected_because=why)
                                                                          for r, why in aside]), []))
        log(f"warning: {len(aside)} untrusted row(s) of {path} are outside this run and were moved to {rejected}: "
            + ", ".join(runs_table.describe_row(r) for r, _ in aside))
    there = {store.identity_of(r) for r in stored.rows}
    replaced = len(mine & there)
    kept = len(stored.rows) - replaced
    where = "the committed grid results" if is_committed_results(request.out) else str(path)
    log(f"{where}: this run writes {len(mine)} row(s) of {len(scenes)} scene(s) ({replaced} replacing rows there, "
        f"{len(mine) - replaced} new) and keeps the other {kept} row(s) as they are"
        + (f" ({len(legacy)} of them predate row digests: accepted by --accept-legacy, checked by range and "
           "written with digests)" if legacy else "")
        + (f"; {len(stored.legacy) - len(legacy)} row(s) predating row digests are recomputed"
           if len(stored.legacy) > len(legacy) else ""))
    if request.accept_legacy:
        stored.accept_legacy()


def _orders_table(out: Path):
    """``out``/orders.csv of the orders study, or None when there is none (or it is unreadable or from
    before the study: the sweep's slopes over chaotic horizons, which are not orders)."""
    import pandas as pd

    path = study_file(out, "orders.csv")
    try:
        table = pd.read_csv(path) if path.is_file() else None
    except Exception:
        return None
    return table if table is not None and {"declared_order", "within_theory"} <= set(table.columns) else None


def _merged_note(runs: int, merged) -> str:
    other = len(merged) - runs
    if other <= 0:
        return ""
    return (f"This run computed or kept {runs} of the {len(merged)} rows; the other {other} come from earlier runs "
            "into the same directory (other scenes, methods or settings), as they were.")


def _figure_code() -> str:
    return store.source_hash((), ("benchmark/figures/plots.py", "benchmark/figures/styles.py"))


def _scene_rows_key(merged, scene: str) -> str:
    rows = merged[merged["scene"] == scene].to_dict("records")
    return store.key_of(store.rows_key(rows, drop=("load_avg", "task_time", "traceback")), _figure_code())


def _paper_key(request: SweepRequest, scene, paper) -> str:
    return store.key_of(scene.key(), request.sweep_t_end or scene.t_end, paper.name, paper.settings,
                        store.code_version(), _figure_code())


def _sweep_figures(request: SweepRequest, merged, log, failed: list | None = None,
                   energy=None) -> list[tuple[str, str]]:
    """Work–precision per scene of the merged table, the paper's panels of this run's scenes
    (`_paper_figures`), and the ``energy`` study (`_energy_study`: its runs that failed go to
    ``failed``): (file name, note) each. A figure whose inputs did not change since it was drawn
    (`benchmark.core.store.OutputKeys`) is kept, not redrawn."""
    import time

    from reelbench.benchmark.figures import plots

    out = request.out
    keys = store.OutputKeys(out / "figures.json")
    figures = []
    for scene in dict.fromkeys(merged["scene"]):
        name, key, t0 = f"work_precision_{scene}.png", _scene_rows_key(merged, scene), time.perf_counter()
        if keys.fresh(name, key):
            log(f"figure: {name} kept (its rows did not change)")
        else:
            plots.work_precision(merged, scene, out)
            keys.record(name, key)
            log(f"figure: {name} ({time.perf_counter() - t0:.0f} s)")
        figures.append((name, ""))
    figures += _paper_figures(request, merged, keys, log)
    if request.energy_horizon > 0:
        from reelbench.benchmark.core import study
        from reelbench.benchmark.studies import horizon_report

        if energy is not None:  # in this run's lock: a stop is the sweep's
            study.run(energy, out, command=request.command, fresh=request.fresh, log=log, held=True, failed=failed)
        figures += horizon_report.listed(out, dict.fromkeys(j.tabled_as for j in energy.jobs) if energy else ())
    return figures


def _paper_figures(request: SweepRequest, merged, keys, log) -> list[tuple[str, str]]:
    """The paper's panels of this run's scenes, from the method that declares the paper's settings
    (the LGVI at its step size), and those an earlier run drew of the table's other scenes."""
    import time

    from reelbench.benchmark.figures import plots
    from reelbench.integrators import get_integrator
    from reelbench.models.diagnostics import evaluate

    out, paper, figures = request.out, sweep.paper_method(), []
    for s in request.scenes:
        scene = request.scene(s)
        name, key, t0 = f"paper_{scene.name}.png", _paper_key(request, scene, paper), time.perf_counter()
        if keys.fresh(name, key):
            log(f"figure: {name} kept (same scene, method, horizon and code)")
        else:
            log(f"figure: {name}: solving {scene.name} with {paper.label} ...")
            traj = get_integrator(paper.name).solve(scene, t_end=request.sweep_t_end or scene.t_end, save_every=SAVE_EVERY,
                                                    **paper.settings)
            plots.paper_panels(scene, traj, evaluate(scene, traj), inside(out, name))
            keys.record(name, key)
            log(f"figure: {name} ({traj.status}, {time.perf_counter() - t0:.0f} s)")
        figures.append((name, ""))
    run_scenes = {request.scene(s).name for s in request.scenes}
    for scene in dict.fromkeys(merged["scene"]):
        name = f"paper_{scene}.png"
        if scene not in run_scenes and (out / name).is_file():
            figures.append((name, "drawn by an earlier run (this run did not include the scene)"))
    return figures


def _sweep_readme(request: SweepRequest, runs, orders, figures, provenance: Provenance, failures,
                  merged_note: str = "") -> Path:
    """README.md of the whole merged table. A run that keeps rows of earlier runs (``merged_note``)
    keeps what it did not recompute: the header names the run that made the table and those that
    merged into it since, and without --compare-with of its own the earlier README's comparisons
    are made again, against the merged table (`_earlier_comparisons`)."""
    from reelbench.benchmark.studies import runs_report
    from reelbench.benchmark.core.report import earlier_runs

    import pandas as pd

    readme = request.out / "README.md"
    history = earlier_runs(readme) if merged_note else ()
    if history:
        provenance = provenance.merged_into(history)
    if request.compare_with or not history:
        compared = "".join(runs_report.changes_since(pd.read_csv(earlier), runs, f"`{earlier}`")
                           for earlier in request.compare_with)
    else:
        compared = _earlier_comparisons(history, readme, runs)
    horizons = {"sweep": request.sweep_t_end, "energy study": request.energy_horizon if request.figures else 0.0}
    return runs_report.write_readme(request.out, runs, orders, provenance=provenance, figures=figures,
                                    compared=compared, horizons=horizons, failures=failures, merged=merged_note,
                                    energy_csv=study_file(request.out, "energy_horizon.csv"))


def _earlier_comparisons(history, readme: Path, runs) -> str:
    """The "Compared with ..." sections of the earlier README, for a run that merges rows into its
    table: each made again against the merged table when its runs.csv (named by a --compare-with
    of an earlier run in ``history``) is still there, else kept as it was, saying so."""
    import re
    import shlex

    import pandas as pd

    from reelbench.benchmark.studies import runs_report

    given = []
    for command, _ in history:
        try:
            words = shlex.split(command)
        except ValueError:
            continue
        given += [words[k + 1] for k, w in enumerate(words[:-1]) if w == "--compare-with"]
        given += [w.split("=", 1)[1] for w in words if w.startswith("--compare-with=")]
    try:
        old = readme.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        old = ""
    sections = {m.group(1): m.group(0) for m in re.finditer(r"^## Compared with `([^`\n]+)`\n.*?(?=^## |\Z)", old,
                                                              flags=re.M | re.S)}
    out = []
    for label in dict.fromkeys(given + list(sections)):
        path = Path(label)  # as the earlier --compare-with named it: from the working directory
        if path.is_file():
            try:
                out.append(runs_report.changes_since(pd.read_csv(path), runs, f"`{label}`"))
                continue
            except Exception:  # noqa: BLE001 - an unreadable earlier table keeps its earlier text
                pass
        if label in sections:
            head, _, body = sections[label].partition("\n")
            out.append(f"{head}\n\n_Kept from the earlier README: `{label}` is not here to compare with the merged "
                       f"table._\n{body}")
    return "".join(out)


def _energy_study(request: SweepRequest, log):
    """The energy study `run --horizon` makes in its output (`benchmark.studies.horizon`), or None
    when it makes none; its earlier table is checked here, before any work (`study.run` refuses one
    it cannot keep)."""
    from reelbench.benchmark.core.study_store import read_rows
    from reelbench.benchmark.studies import horizon

    scenes = horizon.energy_scenes(request.scenes, request.overrides, log)
    if not scenes:
        log(f"horizon: no scene of this run keeps its length: no energy study ({horizon.TABLE} kept as it was)")
        return None
    energy = horizon.study(request.energy_horizon, scenes, overrides=request.overrides, selected=request.integrators,
                           workers=0 if request.executor == "serial" else request.jobs)
    if not energy.jobs:
        log(f"horizon: none of the selected methods is in the energy study's plan; {horizon.TABLE} kept as it was")
        return None
    read_rows(request.out / energy.table, energy.identity, energy.text_columns, energy.read_earlier)
    return energy
