"""The grid sweep, `python -m benchmark run`: every scene × integrator × setting of the sweep
(`benchmark.runs.sweep`) measured once each (`benchmark.runs.runner`) into ``--out``
(results/grid/ by default): runs.csv (written after every run), runs.md, the figures, the
energy study when --horizon asks for one (`benchmark.studies.horizon`) and README.md
(`runs_report`). It ranks nothing: the answer is `benchmark.answer.answer`'s.

The run's rows join the table already in ``--out`` (`benchmark.core.store.merge_rows`; what
may join is `benchmark.runs.table`'s): rows of other scenes, methods or settings are kept and
every file is written from the merged table. The output lock is held for the whole sweep;
Ctrl-C / SIGTERM keeps every finished row and ends in one line saying what was saved, with
the exit status 130 / 143.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from reelbench.benchmark.core import engine
from reelbench.benchmark.core import store
from reelbench.benchmark.runs import sweep
from reelbench.benchmark.runs import table as runs_table
from reelbench.benchmark.core.policy import GRID_DIR, SAVE_EVERY
from reelbench.benchmark.core.engine import log_stderr
from reelbench.benchmark.core.study import exclusive
from reelbench.benchmark.core.report import Provenance
from reelbench.models.io import inside, printable


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
    """The grid sweep into ``request.out``: runs.csv (written after every run), runs.md, the
    figures, the energy study when ``request.horizon`` asks for one, and README.md (with the
    orders of the `orders` study and the stability map's evidence, `study_file`). It ranks nothing: the
    answer is `benchmark.answer.answer`'s. The run's rows join the table already
    in ``out`` (`benchmark.core.store.merge_rows`): rows of other scenes, methods or settings are kept,
    and every file is written from the merged table. A stopped sweep keeps its finished rows."""
    from reelbench.benchmark.runs import runner

    runs_csv = store.TableWriter(request.out / "runs.csv", runner.runs_frame, drop=("traceback",))
    try:
        with exclusive(request.out, log):
            return _sweep(request, runs_csv, log)
    except (KeyboardInterrupt, OSError) as exc:
        what = (f"{runs_csv.saved} finished run(s) are saved in {runs_csv.path}" if runs_csv.saved
                else "no run had finished, nothing saved")
        earlier = getattr(runs_csv, "earlier", 0)
        if earlier:
            what += f" (its {earlier} earlier row(s) are kept)"
        resume = "run the same command again to resume (finished runs are kept), or add --fresh to recompute this run's rows"
        if isinstance(exc, OSError):  # a full or failing disk: stop, say what is safe, exit 1
            log(f"error: {printable(exc)}; {what}; free space (or fix the file system) and {resume}")
            return 1
        return engine.stopped(exc, f"{what}; {resume}", log)


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


def _merge_plan(request: SweepRequest, tasks, stored: runs_table.StoredRuns, path: Path, log) -> None:
    """Refuse a run whose rows cannot join the table in its --out (before any work), set aside
    the untrusted rows no recomputation will replace, and say in one line what the run replaces."""
    names, scenes = _this_run(request, tasks)
    mine = {(names[t.scene], t.integrator, t.setting) for t in tasks}
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


def _sweep(request: SweepRequest, runs_csv: store.TableWriter, log) -> int:
    from reelbench.benchmark.runs import runner
    from reelbench.benchmark.studies import runs_report
    from reelbench.benchmark.core.reference import CACHE_DIR
    from reelbench.benchmark.core.report import markdown_table
    from reelbench.models.io import atomic_write_text

    out = request.out
    cache = CACHE_DIR  # the references every study shares (`benchmark.core.reference.user_cache_dir`)
    provenance = Provenance(request.command)
    tasks = sweep.build_tasks(request.scenes, request.integrators, quick=request.quick, dts=request.dts,
                              rtols=request.rtols, t_end=request.t_end, overrides=dict(request.overrides))
    stored = runs_table.read_runs(runs_csv.path, log=log)
    _merge_plan(request, tasks, stored, runs_csv.path, log)  # refuses a run that cannot join, before any work
    energy = _energy_study(request, log) if request.figures and request.energy_horizon > 0 else None
    base = stored.rows
    runs_csv.to_table = lambda rows: runner.runs_frame(store.merge_rows(base, rows))
    runs_csv.earlier = len(base)
    log(f"{len(tasks)} runs: {len(request.scenes)} scene(s) × {len({t.integrator for t in tasks})} integrator(s); "
        f"results -> {out}/")
    runs = runner.execute(tasks, jobs=request.jobs, executor=request.executor, scheduler=request.scheduler,
                          repeats=request.repeats, cache_dir=str(cache), on_row=runs_csv,
                          **({"budget": request.budget} if request.budget else {}),
                          previous=[] if request.fresh else stored.resumable, log=log,
                          group=lambda t: (t.scene, t.integrator))  # one worker per (scene, method): one compile
    runs_csv(runs.to_dict("records"))
    merged = runs_csv.to_table(runs.to_dict("records")).drop(columns=["traceback"], errors="ignore")
    atomic_write_text(out / "runs.md", markdown_table(merged.drop(columns=[c for c in ("reason", "run_key", "row_digest",
                                                                                      "scene_key") if c in merged])))
    orders = _orders_table(out)  # the short-horizon orders study's (`python -m benchmark orders`), never the sweep's
    failures = runs_report.failure_sentence(merged, study_file(out, "stability/stability.csv"))
    failed: list[str] = []  # what of the energy study did not end with a result (a crashed worker)
    figures = _sweep_figures(request, merged, log, failed, energy) if request.figures else []
    _sweep_readme(request, merged, orders, figures, provenance, failures, merged_note=_merged_note(runs, merged))
    log(f"done in {provenance.wall_time():.0f} s: {len(runs)} runs in this run, {len(merged)} in {out}/runs.csv; "
        f"{failures} See {out}/README.md")
    if failed:
        log(f"error: the energy study did not finish for {'; '.join(failed)}: its history is not in "
            f"{out}/energy_horizon.csv (the runs table is complete)")
        return 1
    return 0


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


def _merged_note(runs, merged) -> str:
    other = len(merged) - len(runs)
    if other <= 0:
        return ""
    return (f"This run computed or kept {len(runs)} of the {len(merged)} rows; the other {other} come from earlier runs "
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
    (from the method that declares the paper's settings, the LGVI at its step size), and the
    ``energy`` study (`_energy_study`: its runs that failed go to ``failed``): (file name, note)
    each. A figure whose inputs did not change since it was drawn
    (`benchmark.core.store.OutputKeys`) is kept, not redrawn."""
    import time

    from reelbench.benchmark.figures import plots
    from reelbench.integrators import get_integrator
    from reelbench.models.diagnostics import evaluate

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
    paper = sweep.paper_method()
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
    if request.energy_horizon > 0:
        from reelbench.benchmark.core import study
        from reelbench.benchmark.studies import horizon_report

        if energy is not None:  # in this run's lock: a stop is the sweep's
            study.run(energy, out, command=request.command, fresh=request.fresh, log=log, held=True, failed=failed)
        figures += horizon_report.listed(out, dict.fromkeys(j.tabled_as for j in energy.jobs) if energy else ())
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
