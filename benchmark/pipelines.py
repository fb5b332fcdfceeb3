"""Every command's pipeline: the one function the command line calls once its input is checked.

Each composes the layers below it and nothing else: the jobs of a study (`runner`,
`stability`, `check`, `horizon`, `xval`, `lgvi_speed`, `reel_reversal`) run on the engine
(`engine.run_jobs`), their rows go to the results store (`store`: the output lock, atomic
tables), their words and figures through the report and plot layers (`report`, `plots` and
the writers `runs_report`, `stability_report`, `xval_report`). A study that writes into a
directory holds its lock and turns Ctrl-C / SIGTERM into one line saying what was saved, and
the exit status 130 / 143.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from benchmark import engine, store
from benchmark.engine import log_stderr
from benchmark.report import Provenance


@contextlib.contextmanager
def _exclusive(out: Path, log: Callable[[str], None]):
    """Hold ``out``'s lock, with Ctrl-C and SIGTERM both stopping the study (KeyboardInterrupt)."""
    with store.OutputLock(out, log=log):
        engine.install_stop_handlers()
        yield


# ------------------------------------------------------------------------------------------
# run: the sweep -> results/
# ------------------------------------------------------------------------------------------
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
    executor: str = "process"
    scheduler: str | None = None
    repeats: int = 3
    horizon: float | None = None  # of the energy study; None: sweep.FULL_HORIZON (--quick: QUICK_HORIZON)
    figures: bool = True
    fresh: bool = False
    compare_with: str | None = None
    command: str = "python -m benchmark run"

    @property
    def sweep_t_end(self) -> float | None:
        from benchmark import sweep

        return self.t_end or (sweep.QUICK_T_END if self.quick else None)

    @property
    def energy_horizon(self) -> float:
        from benchmark import sweep

        return self.horizon if self.horizon is not None else (sweep.QUICK_HORIZON if self.quick else sweep.FULL_HORIZON)

    def scene(self, name: str):
        """A scene of the sweep as its runs see it (overrides and --t-end applied)."""
        from models import load_scene

        return load_scene(name, **dict(self.overrides), **({"t_end": self.t_end} if self.t_end is not None else {}))


def run_sweep(request: SweepRequest, log: Callable[[str], None] = log_stderr) -> int:
    """The sweep into ``request.out``: runs.csv (written after every run), runs.md, orders.csv,
    the figures, the energy study and README.md. A stopped sweep keeps its finished rows."""
    from benchmark import runner

    runs_csv = store.TableWriter(request.out / "runs.csv", runner.runs_frame, drop=("traceback",))
    try:
        with _exclusive(request.out, log):
            return _sweep(request, runs_csv, log)
    except KeyboardInterrupt as exc:
        what = (f"{runs_csv.saved} finished run(s) are saved in {runs_csv.path}" if runs_csv.saved
                else "no run had finished, nothing saved")
        return engine.stopped(exc, f"{what}; run the same command again to resume (finished runs are kept), "
                                   "or add --fresh to start over", log)


def _sweep(request: SweepRequest, runs_csv: store.TableWriter, log) -> int:
    from benchmark import runner, sweep
    from benchmark.metrics import observed_orders
    from benchmark.reference import CACHE_DIR
    from benchmark.report import markdown_table
    from models.io import atomic_write_text

    out = request.out
    provenance = Provenance(request.command)
    tasks = sweep.build_tasks(request.scenes, request.integrators, quick=request.quick, dts=request.dts,
                              rtols=request.rtols, t_end=request.t_end, overrides=dict(request.overrides))
    previous = [] if request.fresh else store.read_previous(runs_csv.path, log=log)
    log(f"{len(tasks)} runs: {len(request.scenes)} scene(s) × {len({t.integrator for t in tasks})} integrator(s); "
        f"results -> {out}/")
    runs = runner.execute(tasks, jobs=request.jobs, executor=request.executor, scheduler=request.scheduler,
                          repeats=request.repeats, cache_dir=str(out / CACHE_DIR.name), on_row=runs_csv,
                          previous=previous, log=log,
                          group=lambda t: (t.scene, t.integrator))  # one worker per (scene, method): one compile
    runs_csv(runs.to_dict("records"))
    atomic_write_text(out / "runs.md", markdown_table(runs.drop(columns=[c for c in ("traceback", "reason", "run_key")
                                                                         if c in runs])))
    orders = observed_orders(runs)
    store.write_table(out / "orders.csv", orders)
    figures = _sweep_figures(request, runs, log) if request.figures else []
    _sweep_readme(request, runs, orders, figures, provenance)
    n_bad = int((runs["status"] != "ok").sum())
    log(f"done in {provenance.wall_time():.0f} s: {len(runs)} runs, {n_bad} not ok; see {out}/README.md")
    return 0


def _sweep_figures(request: SweepRequest, runs, log) -> list[str]:
    """Work–precision per scene, the paper's panels from the method that declares the paper's
    settings (the LGVI at its step size), and the energy study; their file names."""
    from benchmark import plots, sweep
    from integrators import get_integrator
    from models.diagnostics import evaluate

    figures = [plots.work_precision(runs, request.scene(s).name, request.out).name for s in request.scenes]
    paper = sweep.paper_method()
    for s in request.scenes:
        scene = request.scene(s)
        traj = get_integrator(paper.name).solve(scene, t_end=request.sweep_t_end or scene.t_end, save_every=0.02,
                                                **paper.settings)
        path = plots.paper_panels(scene, traj, evaluate(scene, traj), request.out / f"paper_{scene.name}.png")
        figures.append(path.name)
        log(f"figure: paper_{scene.name}.png ({traj.status})")
    if request.energy_horizon > 0:
        path = run_horizon_study(request.energy_horizon, request.out, request.overrides, request.jobs, log)
        figures.append(path.name)
    return figures


def _sweep_readme(request: SweepRequest, runs, orders, figures: list[str], provenance: Provenance) -> Path:
    from benchmark import runs_report

    compared = ""
    if request.compare_with:
        import pandas as pd

        compared = runs_report.changes_since(pd.read_csv(request.compare_with), runs, f"`{request.compare_with}`")
    horizons = {"sweep": request.sweep_t_end, "energy study": request.energy_horizon if request.figures else 0.0}
    return runs_report.write_readme(request.out, runs, orders, provenance=provenance, figures=figures,
                                    compared=compared, horizons=horizons)


def run_horizon_study(t_end: float, out: Path, overrides: tuple = (), jobs: int | None = None,
                      log: Callable[[str], None] = log_stderr) -> Path:
    """Energy error vs time on the fixed-length scene over a long horizon, one job per method in
    parallel workers (one after another they would be the main job's longest tail):
    energy_horizon.csv and its figure. A method whose worker dies is left out of both (its
    progress line says so)."""
    import os

    from benchmark import horizon, plots, sweep
    from models import load_scene

    methods = sweep.horizon_methods()
    jobs_ = [horizon.Job(m, t_end, tuple(overrides)) for m in methods]
    log(f"horizon: {', '.join(m.name for m in methods)} to t = {t_end:g} s ...")
    rows = engine.run_jobs(horizon.run_job, jobs_, workers=jobs or min(len(methods), os.cpu_count() or 1),
                           crash_row=lambda i, exc: horizon.crash_row(jobs_[i], exc), describe=horizon.describe,
                           log=log)
    store.write_table(out / "energy_horizon.csv", horizon.table(rows))
    histories = {r["label"]: r["history"] for r in rows if r["history"] is not None}
    return plots.energy_horizon(histories, load_scene(horizon.SCENE, **dict(overrides)).name, out)


# ------------------------------------------------------------------------------------------
# stability, check, xval, speed, reel-reversal
# ------------------------------------------------------------------------------------------
def run_stability(scenes=None, integrators=None, *, workers: int = 2, out: Path = Path("results/stability"),
                  command: str = "python -m benchmark stability", log: Callable[[str], None] = log_stderr) -> int:
    """The stability map into ``out``: stability.csv (written after every job), stability.md,
    stability.png and README.md."""
    from benchmark import stability, stability_report
    from benchmark.report import markdown_table
    from models.io import atomic_write_text

    out = Path(out)
    table = store.TableWriter(out / "stability.csv", stability.to_frame)
    try:
        with _exclusive(out, log):
            provenance = Provenance(command, workers=workers or 1)
            jobs = stability.jobs_for(scenes, integrators)  # validates names before any work
            log(f"stability map: {len(jobs)} jobs ({len({j.case.scene for j in jobs})} scenes) on {workers or 1} "
                f"worker(s) -> {out}/")
            df = stability.execute(jobs, workers=workers, on_rows=table, log=log)
            table(df.to_dict("records"))
            atomic_write_text(out / "stability.md", markdown_table(df))
            stability_report.plot(df, out)
            stability_report.write_readme(out, df, provenance=provenance)
            log(f"done in {provenance.wall_time():.0f} s; see {out}/README.md")
            return 0
    except KeyboardInterrupt as exc:
        return engine.stopped(exc, f"the rows finished so far are in {table.path}; run the same command again to "
                                   "compute the map", log)


def run_check(*, update: bool = False, baseline=None, integrators=None, factor: float | None = None,
              order_margin: float | None = None, jobs: int | None = None, executor: str = "process",
              cache_dir: str | None = None, tasks=None, command: str | None = None,
              log: Callable[[str], None] | None = None, echo: Callable[[str], None] = print) -> int:
    """Recompute the check sweep and compare it with the baseline (or with ``update``, rewrite
    the baseline). Returns the exit status: 0 passed or updated, 1 regressions. Bad input
    raises ValueError before any work."""
    from benchmark import check
    from benchmark.reference import CACHE_DIR

    baseline = check.BASELINE if baseline is None else baseline
    provenance = Provenance(command or check.UPDATE_COMMAND)
    tol = check.Tolerance(factor=check.DEFAULT_FACTOR if factor is None else factor,
                          order_margin=check.DEFAULT_ORDER_MARGIN if order_margin is None else order_margin)
    if jobs is not None and jobs < 1:
        raise ValueError(f"--jobs = {jobs!r} is invalid (allowed: >= 1)")
    tasks = check.build_check_tasks(integrators) if tasks is None else tasks
    try:
        old = check.baseline_for(baseline, update=update, warn=log or echo)
        table = old.table if old is not None else None
        current = check.measure(tasks, executor=executor, jobs=jobs, cache_dir=cache_dir or str(CACHE_DIR),
                                costs=check.costs_of(table), log=log)
    except KeyboardInterrupt as exc:
        return engine.stopped(exc, "the baseline was not changed", log or log_stderr)
    cmp = check.compare(table, current, tol) if old is not None else None
    if cmp is not None:
        echo(check.format_report(cmp, tol, baseline, old.header))
    if update:
        path = check.write_baseline(check.merge(table, current), baseline, provenance=provenance,
                                    sweep_note=check.describe(tasks))
        echo(f"baseline written: {path} ({len(current)} rows recomputed)")
        return 0
    return 1 if cmp.failed else 0


def run_xval(scene_name: str, elements, t_end: float, out: Path, *, command: str = "python -m benchmark xval",
             log: Callable[[str], None] = log_stderr) -> Path:
    """The cross-validation against MoorDyn and MuJoCo into ``out``; returns its README."""
    from benchmark import xval, xval_report
    from models import load_scene

    provenance = Provenance(command)
    scene = load_scene(scene_name)
    study = xval.study(scene, elements, t_end, log=log)  # refuses an untranslatable scene before any work
    return xval_report.write_outputs(study, scene, Path(out), provenance)


def run_speed(request, out: Path | None = None, *, command: str = "python -m benchmark speed",
              log: Callable[[str], None] = log_stderr, echo: Callable[[str], None] = print) -> int:
    """The speed tables (a `lgvi_speed.SpeedRequest`), one timing after another in this process:
    echoed, and written to ``out`` when given."""
    from benchmark import lgvi_speed
    from models.io import atomic_write_text

    provenance = Provenance(command)
    rows = engine.run_jobs(lgvi_speed.run_job, lgvi_speed.jobs_for(request), workers=0, describe=lgvi_speed.describe,
                           log=log)
    text = lgvi_speed.document(rows, provenance)
    echo(text)
    if out is not None:
        atomic_write_text(out, text)
    return 0


def run_reel_reversal(scene_name: str = "reel_reversal", elements: int = 5, t_end: float = 0.96, methods=None, *,
                      jobs: int | None = None, cache_dir: str | None = None, log: Callable[[str], None] = log_stderr,
                      echo: Callable[[str], None] = print) -> int:
    """The reel-reversal orders: the reference first, then every (method, step) run on the
    engine (grouped by method: one compilation each); the table is echoed."""
    import os

    from benchmark import reel_reversal
    from benchmark.reference import CACHE_DIR
    from models import load_scene

    cache_dir = str(cache_dir or CACHE_DIR)
    scene = load_scene(scene_name, elements=elements)
    methods = list(methods or reel_reversal.DEFAULT_HS)
    todo = [reel_reversal.Job(m, h, scene_name, elements, t_end, cache_dir)
            for m in methods for h in reel_reversal.DEFAULT_HS[m]]
    ref = reel_reversal.reference(scene, t_end, cache_dir)
    workers = jobs if jobs is not None else min(len(methods), os.cpu_count() or 1)
    rows = engine.run_jobs(reel_reversal.run_job, todo, workers=workers, group=lambda i: todo[i].method,
                           describe=reel_reversal.describe, log=log)
    echo(reel_reversal.table(scene, t_end, ref.flips, rows))
    return 0


# ------------------------------------------------------------------------------------------
# simulate, figures
# ------------------------------------------------------------------------------------------
def simulate(scene, integrator: str, settings: dict, out: Path, *, estimate: float | None = None,
             log: Callable[[str], None] = log_stderr) -> int:
    """One run: the trajectory (.npz) and its diagnostics (.csv beside it); exit status 1 when
    the run did not finish. ``estimate``: its expected seconds (a progress line every 30 s)."""
    import json

    import numpy as np

    from integrators import get_integrator
    from models.diagnostics import evaluate
    from models.io import atomic_write_text

    integ = get_integrator(integrator)
    try:
        with engine.Heartbeat(f"{scene.name} / {integ.name}", estimate, log=log):
            traj = integ.solve(scene, t_end=scene.t_end, **settings)
    except KeyboardInterrupt as exc:
        return engine.stopped(exc, "nothing saved (a trajectory is written when the run ends)", log)
    traj.save(out)
    atomic_write_text(out.with_suffix(".csv"), evaluate(scene, traj).to_csv(index=False))
    log(f"{scene.name} / {integ.name}: status {traj.status} {traj.reason}; {len(traj.t)} saved points; "
        f"stats {json.dumps({k: v for k, v in traj.stats.items() if np.isscalar(v)}, default=str)}")
    log(f"wrote {out} and {out.with_suffix('.csv')}")
    return 0 if traj.ok else 1


def draw_figures(scene, traj, out: Path, log: Callable[[str], None] = log_stderr) -> int:
    """The paper's panels (a)-(d) of a saved trajectory."""
    from benchmark import plots
    from models.diagnostics import evaluate

    plots.paper_panels(scene, traj, evaluate(scene, traj), out)
    log(f"wrote {out}")
    return 0

