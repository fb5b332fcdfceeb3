"""`python -m benchmark run`: the grid sweep's input checked (its scenes, settings and size, and
where its rows go: the committed results/grid/ only for the default sweep or when named), then
its pipeline, `benchmark.studies.grid.run_sweep`.
"""

from __future__ import annotations

from pathlib import Path

from reelbench.benchmark.cli import common
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar
from reelbench.benchmark.core.options import UsageError


def cmd_run(args) -> int:
    from reelbench.benchmark.runs import sweep  # no JAX until the pipeline builds the tasks
    from reelbench.models import load_scene

    if args.with_plugins:
        if args.integrators:
            raise UsageError("--with-plugins adds every installed plugin to the default methods: with --integrators "
                             "name the plugins you want instead")
        every = sweep.default_sweep_names(plugins=True)
        if sweep.plugin_names(every):  # none installed: this is the default sweep
            args.integrators = every
    if args.extended and args.scenes:
        raise UsageError("--extended and --scenes are alternatives: give one")
    scene_names = args.scenes or list(sweep.EXTENDED_SCENES if args.extended else sweep.PAPER_SCENES)
    ov = common.overrides(args.set)
    with_t_end = {"t_end": args.t_end, **ov} if args.t_end is not None else ov  # validated with the scene
    scenes = [load_scene(s, **with_t_end) for s in scene_names]  # --dts, --rtols: in range (parsed)
    t_end = sweep.sweep_t_end(args.t_end, args.quick)
    for sc in scenes:
        if (t_end or sc.t_end) < policy.SAVE_EVERY:  # every run would end in an error row
            raise UsageError(f"{'--t-end' if t_end else sc.name + ': t_end'} = {t_end or sc.t_end:g} s is shorter than "
                             f"the sweep's save interval {policy.SAVE_EVERY:g} s: give --t-end >= {policy.SAVE_EVERY:g}")
        for dt in sweep.sweep_dts(args.dts, args.quick):
            if dt > (t_end or sc.t_end):  # any smaller step is allowed (the last one lands on t_end)
                raise UsageError(f"--dts: dt = {dt:g} s is longer than the run ({sc.name}: t_end = {t_end or sc.t_end:g} s; "
                                 "allowed: 0 < dt <= t_end)")
            opt.check_size(sc, t_end or sc.t_end, policy.SAVE_EVERY, dt, warn=_log, what=f"{sc.name} at dt = {dt:g} s",
                           save_option=None)  # run saves every SAVE_EVERY: no option to raise
    out = opt.writable_dir(_run_out(args))
    opt.no_directory_at(out, ("runs.csv", "runs.md", "orders.csv", "README.md", "figures.json"))
    _check_horizon_size(args, ov)  # the energy study's plan and settings (no JAX)

    from reelbench.benchmark.studies import grid

    return grid.run_sweep(grid.SweepRequest(
        out=out, scenes=tuple(scene_names), integrators=tuple(args.integrators) if args.integrators else None,
        quick=args.quick, dts=tuple(args.dts) if args.dts else None, rtols=tuple(args.rtols) if args.rtols else None,
        t_end=args.t_end, overrides=tuple(sorted((k, v) for k, v in ov.items() if k != "t_end")), jobs=args.jobs,
        executor=args.executor, scheduler=args.scheduler, repeats=args.repeats, horizon=args.horizon,
        figures=not args.no_figures, fresh=args.fresh, compare_with=tuple(args.compare_with or ()),
        command=common.command(args), accept_legacy=args.accept_legacy, budget=common.budget(args)), log=_log)


def _check_horizon_size(args, overrides: dict) -> None:
    """The energy study `run` makes when --horizon asks for one fits, as any run must
    (`options.check_size`): e.g. --horizon 1e9 would take 2e11 steps at dt = 0.005 s (it crashed
    its worker). Without --horizon (or with 0) there is no study to check."""
    from reelbench.benchmark.studies import horizon
    from reelbench.models import load_scene

    t_end = args.horizon
    if args.no_figures or not t_end:
        return
    ov = {k: v for k, v in overrides.items() if k not in ("t_end", "elements")}
    sizes = (int(overrides["elements"]),) if "elements" in overrides else horizon.ELEMENTS
    for _, n, m in horizon.runs(args.integrators, sizes, ("",)):
        opt.check_size(load_scene(horizon.DEFAULT_SCENE, elements=n, **ov), t_end, horizon.SAVE_EVERY,
                       m.settings.get("dt"), warn=_log, save_option=None, t_end_option="--horizon",
                       what=f"--horizon {t_end:g}: the energy study of {m.name} at N = {n}")


#: `run`'s default output directory: the committed grid sweep (`benchmark.studies.grid.COMMITTED_RESULTS`).
GRID_OUT = str(policy.GRID_DIR)


#: The options of `run` that make it something other than the default sweep (other rows).
_SWEEP_OPTIONS = (("scenes", "--scenes"), ("integrators", "--integrators"), ("quick", "--quick"), ("dts", "--dts"),
                  ("rtols", "--rtols"), ("t_end", "--t-end"), ("set", "--set"), ("extended", "--extended"))


def _run_out(args) -> str:
    """`run`'s output directory: the committed results/grid/ only for the default sweep or when
    named (`--out results/grid`); any other sweep must say where its results go."""
    from reelbench.benchmark.runs.sweep import plugin_names

    guests = plugin_names(args.integrators or ())
    if args.out is not None:
        if guests and Path(args.out).resolve() == Path(GRID_OUT).resolve():
            _log(f"note: {Path(args.out)}/ gets the rows of plugin(s) {_describe(guests)}, as --out asks")
        return args.out
    if guests:
        raise UsageError(f"this run would add the rows of plugin(s) {_describe(guests)} to the committed {GRID_OUT}/, "
                         "which hold only the project's own methods: give --out DIR for them (e.g. a scratch "
                         f"directory), or --out {GRID_OUT} to add them there")
    given = [flag for attr, flag in _SWEEP_OPTIONS if getattr(args, attr)]
    if given:
        raise UsageError(f"this run is not the default sweep ({', '.join(given)}): give --out DIR for its results "
                         f"(e.g. a scratch directory), or --out {GRID_OUT} to merge its rows into the committed "
                         "results (the rows of other scenes, methods and settings are kept)")
    return GRID_OUT


def _describe(names) -> str:
    """"a (package p 0.1), b (...)": plugins with their provenance, for messages."""
    from reelbench.integrators import origin

    return ", ".join(f"{n} ({origin(n).label().removeprefix('plugin, ')})" for n in names)


def add_run(sub) -> None:
    from reelbench.benchmark.runs import sweep  # constants only (no JAX): the defaults shown in --help are the real ones

    r = sub("run", "sweep scenes × integrators × settings; tables, plots and a README into --out",
            "Sweep scenes × integrators × settings. Rows are written to OUT/runs.csv as they finish and join "
            "the rows already there: rows of other scenes, methods or settings are kept, and the figures and "
            "README are written from the whole table. A row of the same run (same scene physics, integrator, "
            "setting, horizon and code) that passes its checks is kept instead of recomputed (--fresh "
            "recomputes this run's rows). Ctrl-C stops cleanly.")
    common.add_scenes(r, f"(default: {common.csv_of(sweep.PAPER_SCENES)})")
    r.add_argument("--extended", action="store_true", help="the paper's scenes and the fluid scenes "
                                                           f"({common.csv_of(sweep.FLUID_SCENES)}: buoyancy and drag)")
    common.add_integrators(r, "(default: the project's own methods; installed plugins join when named here or with "
                              "--with-plugins)")
    r.add_argument("--with-plugins", action="store_true", help="sweep every installed plugin too (with the default "
                   "methods); its rows go to --out, which must then be given")
    r.add_argument("--quick", action="store_true", help=f"reduced sweep: {sweep.QUICK_T_END:g} s horizon, "
                   f"{len(sweep.QUICK_DTS)} step sizes, {len(sweep.QUICK_RTOLS)} tolerances, "
                   "no energy study unless --horizon is given")
    r.add_argument("--dts", type=opt.positive_floats, help="comma-separated step sizes (s) for fixed-step methods, "
                   f"any size (saved at the step points nearest the save times; default: {common.csv_of(sweep.FULL_DTS)}; "
                   f"--quick: {common.csv_of(sweep.QUICK_DTS)})")
    r.add_argument("--rtols", type=opt.tolerances, help="comma-separated relative tolerances for adaptive methods, "
                   f"atol = rtol × {policy.ATOL_FACTOR:g} (default: {common.csv_of(sweep.FULL_RTOLS)}; implicit methods "
                   f"{common.csv_of(sweep.IMPLICIT_FULL_RTOLS)}; --quick: {common.csv_of(sweep.QUICK_RTOLS)}, implicit "
                   f"{common.csv_of(sweep.IMPLICIT_QUICK_RTOLS)})")
    common.add_t_end(r, f"(default: each scene's t_end; --quick: {sweep.QUICK_T_END:g})")
    common.add_set(r)
    common.add_jobs(r, "the CPU count, at most one per run",
                    workers_only="run times its runs in worker processes; --executor serial runs them in this process")
    r.add_argument("--repeats", type=opt.positive_int, default=sweep.MIN_REPEATS,
                   help=f"the least timed solves per run: as many as fit in {sweep.TIMING_BUDGET:g} s, at least this "
                        f"many and at most {sweep.MAX_REPEATS} (one when a single solve takes longer); run_time is "
                        "their median, run_time_low / run_time_high the fastest / the 90th percentile or slowest")
    common.add_executor(r, "runs")
    r.add_argument("--horizon", type=opt.nonnegative_float,
                   help="run the long-horizon energy study too, this long (s), on the run's fixed-length scenes "
                        "(default: none; the study is its own command, `energy`, e.g. --horizon "
                        f"{sweep.FULL_HORIZON:g} as it runs by default, {sweep.QUICK_HORIZON:g} for a quick look)")
    common.add_budget(r, "the sweep goes on (such a row is recomputed on resume)")
    r.add_argument("--no-figures", action="store_true", help="skip the figures and the energy study")
    common.add_fresh(r, "OUT/runs.csv")
    r.add_argument("--accept-legacy", action="store_true",
                   help="keep the rows of OUT/runs.csv written before row digests covered every column (checked by "
                        "range only, then written with digests); without it such a table is refused")
    r.add_argument("--compare-with", type=opt.runs_table, metavar="RUNS.csv", action="append",
                   help="an earlier run's runs.csv: the README then says which conclusions changed and by how much "
                        "(give it more than once to compare with several, e.g. the last committed run and a second "
                        "fresh run of the same code)")
    common.add_out(r, f"output directory, created if missing (default: {GRID_OUT}); the run's rows join the table "
                      "there (rows of other scenes, methods and settings are kept). A run that is not the default "
                      f"sweep (--quick, --scenes, ...) writes into {GRID_OUT}/ only when named: --out {GRID_OUT}")
    r.set_defaults(func=cmd_run)
