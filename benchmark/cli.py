"""Command line: ``python -m benchmark {run,check,simulate,figures,speed,stability,xval,list}`` (also ``reelbench``).

Every command checks all of its input first -- option types and ranges, conflicting options,
the scene (and the plausibility of its values), the output place (created and test-written)
and the size of the run -- and only then imports JAX and starts work. A mistake is answered
in well under a second with ``error: ...`` and exit status 2, without a traceback (set
REELBENCH_DEBUG=1 to see where a ValueError came from); any other exception is an internal
error and keeps its traceback. Ctrl-C or SIGTERM stops a command with one
line saying what was saved (exit status 130 or 143).

The model and the scene format: models/README.md. The integrators: integrators/README.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import threading
import time
from pathlib import Path

from benchmark import options as opt
from benchmark.options import UsageError


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _overrides(items: list[str] | None) -> dict:
    """--set key=value (value parsed as JSON when it can be: numbers, lists, quoted strings)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise UsageError(f"--set {item!r}: expected KEY=VALUE (e.g. --set elements=20)")
        k, v = item.split("=", 1)
        if not k.strip():
            raise UsageError(f"--set {item!r}: the key is empty (expected KEY=VALUE, e.g. --set elements=20)")
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
    return out


def _command() -> str:
    return "python -m benchmark " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def _stopped(exc: KeyboardInterrupt) -> int:
    """Exit status of a stopped command: 143 for SIGTERM, 130 for Ctrl-C (as a shell reports)."""
    return 143 if "SIGTERM" in str(exc) else 130


def _how(exc: KeyboardInterrupt) -> str:
    return "SIGTERM" if "SIGTERM" in str(exc) else "Ctrl-C"


class _Heartbeat:
    """Progress of one long computation that reports nothing itself: a line every ``every``
    seconds with the time spent and what is left of the estimate (``estimate`` s)."""

    def __init__(self, what: str, estimate: float | None, every: float = 30.0):
        self.what, self.estimate, self.every = what, estimate, every
        self._stop = threading.Event()
        self._t0 = time.perf_counter()

    def __enter__(self):
        if self.estimate is not None and self.estimate > self.every:
            threading.Thread(target=self._run, daemon=True).start()
        return self

    def _run(self):
        while not self._stop.wait(self.every):
            spent = time.perf_counter() - self._t0
            left = max(self.estimate - spent, 0.0)
            _log(f"{self.what}: {spent:.0f} s so far; estimated {left:.0f} s left "
                 f"({min(spent / self.estimate, 0.99):.0%} by the estimate)")

    def __exit__(self, *exc):
        self._stop.set()


# ------------------------------------------------------------------------------------------
def cmd_run(args) -> int:
    from models import load_scene

    # 1. everything that needs no JAX
    if args.executor == "dask" and not args.scheduler:
        raise UsageError("--executor dask needs --scheduler ADDRESS (e.g. tcp://host:8786)")
    if args.scheduler and args.executor != "dask":
        raise UsageError(f"--scheduler is only used with --executor dask (got --executor {args.executor})")
    from benchmark import sweep  # no JAX until build_tasks

    scene_names = args.scenes or list(sweep.PAPER_SCENES)
    ov = _overrides(args.set)
    if args.t_end is not None:
        ov = {"t_end": args.t_end, **ov}  # validated (and checked for plausibility) with the scene
    scenes = [load_scene(s, **ov) for s in scene_names]
    sweep.check_settings(args.dts, args.rtols)
    t_end = args.t_end or (sweep.QUICK_T_END if args.quick else None)
    for sc in scenes:
        te = t_end or sc.t_end
        for dt in args.dts or (sweep.QUICK_DTS if args.quick else sweep.FULL_DTS):
            opt.check_size(sc, te, sweep.SAVE_EVERY, dt, warn=_log, what=f"{sc.name} at dt = {dt:g} s")
    out = opt.writable_dir(args.out)

    from benchmark import runner

    saved = [0]
    try:
        with runner.OutputLock(out, log=_log):
            runner.install_stop_handlers()
            return _run(args, scene_names, ov, t_end, out, saved)
    except KeyboardInterrupt as exc:
        what = (f"{saved[0]} finished run(s) are saved in {out / 'runs.csv'}" if saved[0]
                else "no run had finished, nothing saved")
        _log(f"stopped by {_how(exc)}: {what}; run the same command again to resume "
             f"(finished runs are kept), or add --fresh to start over")
        return _stopped(exc)


def _run(args, scene_names, ov, t_end, out: Path, saved: list) -> int:
    from benchmark import runner, sweep
    from benchmark.reference import CACHE_DIR
    from models import load_scene
    from models.io import atomic_write_text

    tasks = sweep.build_tasks(scene_names, args.integrators, quick=args.quick, dts=args.dts, rtols=args.rtols,
                              t_end=args.t_end, overrides={k: v for k, v in ov.items() if k != "t_end"})
    previous = [] if args.fresh else runner.read_previous(out / "runs.csv", log=_log)
    _log(f"{len(tasks)} runs: {len(scene_names)} scene(s) × {len({t.integrator for t in tasks})} integrator(s); "
         f"results -> {out}/")
    t0 = time.perf_counter()

    def write(rows) -> None:
        df = runner.to_frame(rows)
        atomic_write_text(out / "runs.csv", df.drop(columns=[c for c in ("traceback",) if c in df]).to_csv(index=False))
        saved[0] = len(rows)

    runs = runner.execute(tasks, jobs=args.jobs, executor=args.executor, scheduler=args.scheduler,
                          repeats=args.repeats, cache_dir=str(out / CACHE_DIR.name), on_row=write,
                          previous=previous,
                          group=lambda t: (t.scene, t.integrator))  # one worker per (scene, method): one compile
    write(runs.to_dict("records"))
    from benchmark import plots, report
    from benchmark.metrics import observed_orders
    from integrators import get_integrator
    from models.diagnostics import evaluate

    atomic_write_text(out / "runs.md", report.markdown_table(runs.drop(columns=[c for c in ("traceback", "reason", "run_key") if c in runs])))
    orders = observed_orders(runs)
    atomic_write_text(out / "orders.csv", orders.to_csv(index=False))
    figures = []
    horizon = args.horizon if args.horizon is not None else (QUICK_HORIZON if args.quick else FULL_HORIZON)
    if not args.no_figures:
        for s in scene_names:
            figures.append(plots.work_precision(runs, load_scene(s, **ov).name, out).name)
        # the paper's panels from the method that declares the paper's settings (the LGVI at its step size)
        paper, paper_kw = paper_method()
        for s in scene_names:
            scene = load_scene(s, **ov)
            te = t_end or scene.t_end
            traj = get_integrator(paper).solve(scene, t_end=te, save_every=0.02, **paper_kw)
            figures.append(plots.paper_panels(scene, traj, evaluate(scene, traj), out / f"paper_{scene.name}.png").name)
            _log(f"figure: paper_{scene.name}.png ({traj.status})")
        if horizon > 0:
            figures.append(_horizon_study(horizon, out, {k: v for k, v in ov.items() if k != "t_end"}, args.jobs).name)
    wall = time.perf_counter() - t0
    compared = ""
    if args.compare_with:
        import pandas as pd

        compared = report.changes_since(pd.read_csv(args.compare_with), runs, f"`{args.compare_with}`")
    report.write_readme(out, runs, orders, command=_command(), wall_time=wall, figures=figures, compared=compared,
                        horizons={"sweep": t_end, "energy study": horizon if not args.no_figures else 0.0})
    n_bad = int((runs["status"] != "ok").sum())
    _log(f"done in {wall:.0f} s: {len(runs)} runs, {n_bad} not ok; see {out}/README.md")
    return 0


#: length (s) of the long-horizon energy study (run --horizon), full and --quick
FULL_HORIZON, QUICK_HORIZON = 100.0, 10.0



def paper_method() -> tuple[str, dict]:
    """(name, settings) of the method whose run draws the paper's panels: the first default
    integrator declaring `Integrator.paper_settings` (the paper's LGVI at dt = 2.5 ms)."""
    from benchmark.sweep import default_names
    from integrators import get_integrator

    return next((n, dict(s)) for n in default_names() if (s := get_integrator(n).paper_settings))


def horizon_methods() -> tuple[tuple[str, dict], ...]:
    """The methods of the long-horizon energy study, chosen by what they declare
    (`Integrator.horizon_settings`), not by name: every default integrator and plugin with
    settings for it, fixed-step first, then the loosest tolerance first (ties: the sweep's order)."""
    from benchmark.sweep import default_names
    from integrators import get_integrator

    chosen = [(n, dict(s)) for n in default_names() if (s := get_integrator(n).horizon_settings)]
    return tuple(sorted(chosen, key=lambda nk: ("dt" not in nk[1], -nk[1].get("rtol", 0.0))))


def _horizon_run(name: str, kw: dict, t_end: float, ov: dict):
    """One method of the horizon study (a worker task): (label, energy history)."""
    from benchmark.metrics import energy_history
    from integrators import get_integrator
    from models import load_scene

    scene = load_scene("fixed_length", **ov)
    traj = get_integrator(name).solve(scene, t_end=t_end, save_every=0.1, **kw)
    label = f"{name} {', '.join(f'{k}={v:g}' for k, v in kw.items())}" + ("" if traj.ok else f" [{traj.status}]")
    return label, energy_history(scene, traj)


def _horizon_study(t_end: float, out: Path, ov: dict, jobs: int | None = None) -> Path:
    """Energy error vs time on the fixed-length scene over a long horizon (the methods run in
    parallel worker processes: serially they were the main job's longest tail)."""
    import pandas as pd

    from benchmark import plots
    from benchmark.runner import worker_pool
    from models import load_scene
    from models.io import atomic_write_text

    scene = load_scene("fixed_length", **ov)
    histories, frames = {}, []
    methods = horizon_methods()
    _log(f"horizon: {', '.join(name for name, _ in methods)} to t = {t_end:g} s ...")
    with worker_pool(jobs or min(len(methods), os.cpu_count() or 1)) as pool:
        futures = [pool.submit(_horizon_run, name, kw, t_end, ov) for name, kw in methods]
        for fut in futures:
            label, h = fut.result()
            histories[label] = h
            frames.append(h.assign(method=label))
    atomic_write_text(out / "energy_horizon.csv", pd.concat(frames).to_csv(index=False))
    return plots.energy_horizon(histories, scene.name, out)


# ------------------------------------------------------------------------------------------
def cmd_simulate(args) -> int:
    from models import load_scene

    if args.atol is not None and args.rtol is None:
        raise UsageError("--atol needs --rtol (an adaptive method); with --dt the step is fixed and atol is unused")
    scene = load_scene(args.scene, **_overrides(args.set))
    if args.t_end is not None:
        scene = scene.with_(t_end=args.t_end)  # the same range and plausibility rules as the file
    out = opt.writable_file(args.out or Path.cwd() / f"simulate_{scene.name}_{args.integrator}.npz")
    if out.suffix != ".npz":
        raise UsageError(f"--out {str(out)!r}: a trajectory file ends in .npz (the diagnostics go beside it as .csv)")
    if args.save_every > scene.t_end:
        raise UsageError(f"--save-every {args.save_every:g} is longer than the run (t_end = {scene.t_end:g} s): "
                         f"give a save interval <= t_end")
    size = opt.check_size(scene, scene.t_end, args.save_every, args.dt, warn=_log,
                          what=f"{scene.name} to t_end = {scene.t_end:g} s")

    from integrators import get_integrator
    from models.diagnostics import evaluate
    from models.io import atomic_write_text

    integ = get_integrator(args.integrator)
    kw = {"t_end": scene.t_end, "save_every": args.save_every}
    if args.dt is not None:
        kw["dt"] = args.dt
    if args.rtol is not None:
        kw.update(rtol=args.rtol, atol=args.atol if args.atol is not None else args.rtol * 1e-2)
    try:
        with _Heartbeat(f"{scene.name} / {integ.name}", size["seconds"]):
            traj = integ.solve(scene, **kw)
    except KeyboardInterrupt as exc:
        _log(f"stopped by {_how(exc)}: nothing saved (a trajectory is written when the run ends)")
        return _stopped(exc)
    traj.save(out)
    df = evaluate(scene, traj)
    atomic_write_text(out.with_suffix(".csv"), df.to_csv(index=False))
    import numpy as np

    _log(f"{scene.name} / {integ.name}: status {traj.status} {traj.reason}; {len(traj.t)} saved points; "
         f"stats {json.dumps({k: v for k, v in traj.stats.items() if np.isscalar(v)}, default=str)}")
    _log(f"wrote {out} and {out.with_suffix('.csv')}")
    return 0 if traj.ok else 1


def cmd_figures(args) -> int:
    from models import load_scene
    from models.layout import StateLayout

    src = Path(args.trajectory)
    if not src.exists():
        raise UsageError(f"{src}: no such file; give a trajectory written by `simulate` (.npz)")
    if not src.is_file():
        raise UsageError(f"{src}: is not a file; give a trajectory written by `simulate` (.npz)")
    ov = _overrides(args.set)
    if args.scene:
        load_scene(args.scene, **ov)  # a bad scene is refused before the trajectory is read
    out = opt.writable_file(args.out or Path.cwd() / f"{src.stem}.png")

    import zipfile

    if not zipfile.is_zipfile(src):  # .npz is a zip archive; anything else is not a trajectory
        raise UsageError(f"{src}: not a trajectory file (not an .npz archive); give a trajectory written by `simulate`")
    from integrators import Trajectory

    try:
        traj = Trajectory.load(src)
    except Exception as exc:  # whatever the reader trips on, the file is not a trajectory
        raise UsageError(f"{src}: not a trajectory file written by `simulate` "
                         f"({type(exc).__name__}: {str(exc).splitlines()[0][:120] if str(exc) else ''})") from None
    scene = load_scene(args.scene or traj.scene_name, **ov)
    lay = StateLayout.from_scene(scene)
    nx = traj.x.shape[1] if getattr(traj.x, "ndim", 0) == 2 else None
    if nx != lay.nx or (traj.attitude is not None) != lay.has_attitude:
        raise UsageError(f"{src} does not fit scene {scene.name!r} as given: the file has {nx} coordinates per "
                         f"point{' and an attitude' if traj.attitude is not None else ''}, the scene "
                         f"{lay.nx}{' and an attitude' if lay.has_attitude else ''}; give the scene the trajectory "
                         f"was computed with (recorded: {traj.scene_name!r}), with the same --set overrides")
    from benchmark import plots
    from models.diagnostics import evaluate

    plots.paper_panels(scene, traj, evaluate(scene, traj), out)
    _log(f"wrote {out}")
    return 0


def cmd_check(args) -> int:
    from benchmark import check

    if not args.update and args.baseline is None and not Path(check.BASELINE).exists():
        raise UsageError(f"the committed baseline {check.BASELINE} is not in {Path.cwd()}: run `check` from the "
                         f"repository's root directory, or give --baseline PATH")
    # how the baseline was produced, for its header (the options that change its content)
    command = check.UPDATE_COMMAND + "".join(f" --{k} {shlex.quote(v)}" for k, v in
                                             (("integrators", args.integrators), ("baseline", args.baseline)) if v)
    names = [v.strip() for v in args.integrators.split(",") if v.strip()] if args.integrators else None
    try:
        return check.main(update=args.update, baseline=args.baseline or check.BASELINE, integrators=names,
                          factor=check.DEFAULT_FACTOR if args.factor is None else args.factor,
                          order_margin=check.DEFAULT_ORDER_MARGIN if args.order_margin is None else args.order_margin,
                          jobs=args.jobs, command=command, log=_log)
    except KeyboardInterrupt as exc:
        _log(f"stopped by {_how(exc)}: the baseline was not changed")
        return _stopped(exc)


def cmd_stability(args) -> int:
    out = opt.writable_dir(args.out)
    from benchmark import runner

    try:
        with runner.OutputLock(out, log=_log):
            runner.install_stop_handlers()
            from benchmark import stability

            return stability.main(args.scenes, args.integrators, workers=args.jobs, out=str(out), command=_command())
    except KeyboardInterrupt as exc:
        _log(f"stopped by {_how(exc)}: the rows finished so far are in {out / 'stability.csv'}; "
             f"run the same command again to compute the map")
        return _stopped(exc)


def cmd_xval(args) -> int:
    """Cross-validation against MoorDyn and MuJoCo (benchmark/xval.py); exit 2 on a scene it cannot translate."""
    import importlib.util

    ints = args.elements or None
    if ints is not None and (len(ints) < 2 or any(n < 2 for n in ints)):
        raise UsageError(f"--elements {_csv(ints)}: allowed two or more integers >= 2 (e.g. 5,10,20)")
    from benchmark import xval
    from models import load_scene

    xval.check_scene(load_scene(args.scene))  # names what cannot be translated, before any work
    out = opt.writable_dir(args.out)
    missing = [m for m in ("moordyn", "mujoco") if importlib.util.find_spec(m) is None]
    if missing:
        raise UsageError(f"xval needs {', '.join(missing)}: pip install 'reelbench[xval]'")
    readme = xval.main(args.scene, ints or list(xval.DEFAULT_ELEMENTS), args.t_end or xval.DEFAULT_T_END, str(out),
                       command=_command(), log=_log)
    _log(f"wrote {readme}")
    return 0


def cmd_list(args) -> int:
    from integrators import available, get_integrator, plugin_errors
    from models import available_scenes

    print("scenes:", ", ".join(available_scenes()))
    for name in available():
        integ = get_integrator(name)
        caps = ", ".join(sorted(c.value for c in integ.capabilities))
        print(f"  {name:10s} order {integ.order}  [{caps}]  {integ.description}")
    for name, err in plugin_errors().items():
        print(f"  {name:10s} FAILED TO LOAD: {err}")
    from models import EFFECTS
    from models.effects import plugin_errors as effect_plugin_errors

    failed = effect_plugin_errors()  # loads the reelbench.effects plugins first
    print("effects:", ", ".join(EFFECTS))
    for name, err in failed.items():
        print(f"  {name:10s} FAILED TO LOAD: {err}")
    return 0


# ------------------------------------------------------------------------------------------
class _Help(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, except where there is none to show (None, a flag's False)."""

    def _get_help_string(self, action):
        if action.default in (None, False) or isinstance(action, argparse._HelpAction):
            return action.help
        return super()._get_help_string(action)


def _csv(values) -> str:
    return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in values)


def parser() -> argparse.ArgumentParser:
    from benchmark import sweep  # constants only (no JAX): the defaults shown in --help are the real ones

    p = argparse.ArgumentParser(prog="python -m benchmark", description=__doc__, formatter_class=_Help)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name: str, help: str, description: str | None = None) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help, description=description or help, formatter_class=_Help)

    r = add("run", "sweep scenes × integrators × settings; tables, plots and a README into --out",
            "Sweep scenes × integrators × settings. Rows are written to OUT/runs.csv as they finish; a run "
            "into an OUT that holds rows of the same sweep (same scene physics, integrator, setting, horizon "
            "and code) keeps them and computes only the rest (--fresh recomputes all). Ctrl-C stops cleanly.")
    r.add_argument("--scenes", type=opt.names, help="comma-separated scene names or .toml paths "
                                                    f"(default: {_csv(sweep.PAPER_SCENES)})")
    r.add_argument("--integrators", type=opt.names, help="comma-separated integrator names (default: every "
                                                         "registered one; see `list`)")
    r.add_argument("--quick", action="store_true", help=f"reduced sweep: {sweep.QUICK_T_END:g} s horizon, "
                   f"{len(sweep.QUICK_DTS)} step sizes, {len(sweep.QUICK_RTOLS)} tolerances, {QUICK_HORIZON:g} s energy study")
    r.add_argument("--dts", type=opt.positive_floats, help="comma-separated step sizes (s) for fixed-step methods, "
                   f"each dividing the save interval {sweep.SAVE_EVERY:g} s (default: {_csv(sweep.FULL_DTS)}; "
                   f"--quick: {_csv(sweep.QUICK_DTS)})")
    r.add_argument("--rtols", type=opt.tolerances, help="comma-separated relative tolerances for adaptive methods, "
                   f"atol = rtol × {sweep.ATOL_FACTOR:g} (default: {_csv(sweep.FULL_RTOLS)}; implicit methods "
                   f"{_csv(sweep.IMPLICIT_FULL_RTOLS)}; --quick: {_csv(sweep.QUICK_RTOLS)}, implicit "
                   f"{_csv(sweep.IMPLICIT_QUICK_RTOLS)})")
    r.add_argument("--t-end", type=opt.positive_float,
                   help=f"horizon in s (default: each scene's t_end; --quick: {sweep.QUICK_T_END:g})")
    r.add_argument("--set", action="append", metavar="KEY=VALUE", help="scene override, repeatable, e.g. "
                                                                         "--set elements=20")
    r.add_argument("--jobs", type=opt.positive_int, help="worker processes (default: CPU count, at most one per run)")
    r.add_argument("--repeats", type=opt.positive_int, default=3,
                   help="timed repeats per run after the first solve (within a 10 s budget); run_time is their "
                        "minimum, run_time_median their median")
    r.add_argument("--executor", default="process", choices=["process", "serial", "dask"],
                   help="where runs execute: worker processes, this process, or a Dask cluster")
    r.add_argument("--scheduler", help="Dask scheduler address, with --executor dask (e.g. tcp://host:8786)")
    r.add_argument("--horizon", type=opt.nonnegative_float,
                   help=f"length (s) of the long-horizon energy study on fixed_length; 0 = off (default: "
                        f"{FULL_HORIZON:g}; --quick: {QUICK_HORIZON:g})")
    r.add_argument("--no-figures", action="store_true", help="skip the figures and the energy study")
    r.add_argument("--fresh", action="store_true", help="recompute every run, ignoring rows already in OUT/runs.csv")
    r.add_argument("--compare-with", type=opt.runs_table, metavar="RUNS.csv",
                   help="an earlier run's runs.csv: the README then says which conclusions changed and by how much")
    r.add_argument("--out", default="results", help="output directory (created if missing); the default is the "
                                                    "repository's committed results/, which this overwrites")
    r.set_defaults(func=cmd_run)

    c = add("check", "recompute a short sweep and compare its accuracy metrics with the committed baseline; "
                     "exit 1 on a regression (rules in benchmark/check.py)")
    c.add_argument("--update", action="store_true", help="rewrite the baseline from this run instead of failing")
    c.add_argument("--baseline", help="baseline CSV (default: results/baseline/drift.csv, run from the repository root)")
    c.add_argument("--integrators", help="comma-separated names (default: all registered except test_*)")
    c.add_argument("--factor", type=float,
                   help="a drift or error fails when worse than FACTOR x baseline, above its floor (default: 2)")
    c.add_argument("--order-margin", type=float,
                   help="an observed order fails when lower than baseline - MARGIN (default: 0.5)")
    c.add_argument("--jobs", type=int, help="worker processes (default: CPU count)")
    c.set_defaults(func=cmd_check)

    s = add("simulate", "one scene, one integrator, one setting -> trajectory .npz + diagnostics .csv",
            "Run one scene with one integrator at one setting: a fixed step (--dt) or a tolerance (--rtol), "
            "never both. Writes the trajectory (.npz) and its diagnostics (.csv, energies, π3, orthogonality "
            "error, lengths) to --out, by default into the current directory.")
    s.add_argument("scene", help="a shipped scene name (see `list`) or the path of a scene .toml file "
                                 "(format: models/README.md)")
    s.add_argument("--integrator", default="lgvi", help="integrator name (see `list`)")
    setting = s.add_mutually_exclusive_group()
    setting.add_argument("--dt", type=opt.positive_float, help="fixed step size in s (fixed-step methods)")
    setting.add_argument("--rtol", type=opt.tolerance, help="relative tolerance (adaptive methods); atol defaults "
                                                            "to rtol/100")
    s.add_argument("--atol", type=opt.positive_float, help="absolute tolerance, with --rtol (default: rtol/100)")
    s.add_argument("--t-end", type=opt.positive_float, help="horizon in s (default: the scene's t_end)")
    s.add_argument("--save-every", type=opt.positive_float, default=0.02, help="save interval in s")
    s.add_argument("--set", action="append", metavar="KEY=VALUE", help="scene override, repeatable, e.g. "
                                                                         "--set elements=20")
    s.add_argument("--out", help="trajectory file (.npz; default: ./simulate_SCENE_INTEGRATOR.npz)")
    s.set_defaults(func=cmd_simulate)

    f = add("figures", "the paper's panels (a)-(d) from a trajectory file written by `simulate`")
    f.add_argument("trajectory", help="a trajectory .npz written by `simulate`")
    f.add_argument("--scene", help="scene name or path (default: the one recorded in the file)")
    f.add_argument("--set", action="append", metavar="KEY=VALUE", help="scene overrides the trajectory was "
                                                                         "computed with, e.g. --set elements=20")
    f.add_argument("--out", help="figure file (.png; default: ./TRAJECTORY.png in the current directory)")
    f.set_defaults(func=cmd_figures)

    sp = add("speed", "time per step of every fixed-step method and per-call cost of each right-hand side vs N, "
                      "compile time separately (options: `speed --help`)")
    sp.add_argument("rest", nargs=argparse.REMAINDER, help="options of benchmark.lgvi_speed (see `speed --help`)")

    st = add("stability", "stability map of the hard scenes: largest stable dt (fixed step), step statistics "
                          "(adaptive) -> --out")
    st.add_argument("--scenes", type=opt.names, help="comma-separated hard scenes (default: all seven)")
    st.add_argument("--integrators", type=opt.names, help="comma-separated names (default: the shipped methods "
                                                          "of the sweep, implicit baselines last)")
    st.add_argument("--jobs", type=opt.nonnegative_int, default=2, help="worker processes (0: run in this process)")
    st.add_argument("--out", default="results/stability", help="output directory (created if missing)")
    st.set_defaults(func=cmd_stability)

    xv = add("xval", "cross-validation against MoorDyn and MuJoCo at equal N -> --out (needs the [xval] extra)")
    xv.add_argument("--scene", default="fixed_length", help="fixed-length scene name or path")
    xv.add_argument("--elements", type=opt.positive_ints, help="comma-separated N >= 2 (default 5,10,20,40,80; "
                                                               "5,10,20,40,80,160 takes about 4x longer)")
    xv.add_argument("--t-end", type=opt.positive_float, help="horizon in s (default 5)")
    xv.add_argument("--out", default="results/xval", help="output directory (created if missing)")
    xv.set_defaults(func=cmd_xval)

    ls = add("list", "registered integrators and shipped scenes")
    ls.set_defaults(func=cmd_list)
    return p


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        if argv[:1] == ["speed"]:  # its own options (see `speed --help`) pass straight through
            from benchmark import lgvi_speed

            try:
                return lgvi_speed.main(argv[1:]) or 0
            except SystemExit as exc:  # --help (0) or a bad option (2, argparse printed "error: ...")
                return exc.code if isinstance(exc.code, int) else 2
        try:
            args = parser().parse_args(argv)
        except SystemExit as exc:  # --help (0) or a bad option (2, argparse printed "error: ...")
            return exc.code if isinstance(exc.code, int) else 2
        return args.func(args)
    except ValueError as exc:  # bad input (UsageError, SceneError, an integrator's argument check)
        if os.environ.get("REELBENCH_DEBUG"):  # a developer chasing a ValueError gets its traceback
            raise
        _log(f"error: {exc}")
        return 2
    except KeyboardInterrupt as exc:  # a command without its own stop message
        _log(f"stopped by {_how(exc)}")
        return _stopped(exc)
