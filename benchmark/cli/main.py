"""Command line: ``python -m benchmark {run,check,simulate,figures,speed,stability,answer,xval,reel-reversal,orders,energy,verify,work-rule,list}``
(also ``reelbench``).

Every command checks all of its input first -- option types and ranges, conflicting options,
integrator and study names, the scene (and the plausibility of its values), the output place
(proved writable, but created only when the work starts, so a refused command leaves no
--out behind) and the size of the run -- and only then imports JAX and calls its pipeline,
which lives with what it does (`benchmark.studies.grid.run_sweep`, `benchmark.core.study.run`
for the studies on the one runner, `benchmark.studies.check.run_check`, ...). A mistake is
answered in well under a second with ``error: ...`` and exit status 2, without a traceback
(set REELBENCH_DEBUG=1 to see where a ValueError came from); a file-system fault during the work (a full disk, a read-only place) is one
``error: cannot write FILE: ...`` line and exit status 1, with the rows finished so far kept;
any other exception is an internal error and keeps its traceback. Ctrl-C or SIGTERM stops
every command with one line saying what was saved (exit status 130 or 143).

The options that several commands share (--scenes, --integrators, --jobs, --fresh, the solve
budgets, --executor, --set, --t-end, --elements, --out) are declared once, with their help, default
and parse function, in `benchmark.cli.common`; each command's builder below calls the ones it has.

The model and the scene format: models/README.md. The integrators: integrators/README.md.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import threading
from pathlib import Path

from benchmark.cli import common
from benchmark.core import options as opt
from benchmark.core import policy
from benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar
from benchmark.core.options import UsageError
from models.io import inside, printable


def _command(args) -> str:
    """The command as the user typed it, for the headers of the files it writes."""
    return "python -m benchmark " + " ".join(shlex.quote(a) for a in args.argv)


def _csv(values) -> str:
    return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in values)


def _any_finite(values) -> bool:
    import numpy as np

    try:
        return bool(np.isfinite(np.asarray(values, dtype=float)).any())
    except (TypeError, ValueError):
        return False


def _check_integrator(name: str):
    """The integrator ``name``, or UsageError for an unknown one (the registry lists names and
    capabilities without importing JAX)."""
    from integrators import get_integrator

    return get_integrator(name)


def _check_setting(integ, dt, rtol, t_end: float) -> None:
    """simulate's --dt / --rtol as the method takes them (from its declared capabilities)."""
    from integrators import Capability

    fixed, adaptive = integ.has(Capability.FIXED_STEP), integ.has(Capability.ADAPTIVE)
    takes = " or ".join(o for o, ok in (("--dt (a fixed step)", fixed), ("--rtol (a tolerance)", adaptive)) if ok)
    if dt is None and rtol is None:
        raise UsageError(f"{integ.name} needs a setting: give {takes}")
    if dt is not None and not fixed:
        raise UsageError(f"--dt: {integ.name} is adaptive and takes no fixed step: give {takes} instead")
    if rtol is not None and not adaptive:
        raise UsageError(f"--rtol: {integ.name} is a fixed-step method: give {takes} instead")
    if dt is not None and dt > t_end:
        raise UsageError(f"--dt {dt:g} is longer than the run (t_end = {t_end:g} s): give --dt <= t_end")


# ------------------------------------------------------------------------------------------
# Each command: check its input, then call its pipeline
# ------------------------------------------------------------------------------------------
def cmd_run(args) -> int:
    from benchmark.runs import sweep  # no JAX until the pipeline builds the tasks
    from models import load_scene

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

    from benchmark.studies import grid

    return grid.run_sweep(grid.SweepRequest(
        out=out, scenes=tuple(scene_names), integrators=tuple(args.integrators) if args.integrators else None,
        quick=args.quick, dts=tuple(args.dts) if args.dts else None, rtols=tuple(args.rtols) if args.rtols else None,
        t_end=args.t_end, overrides=tuple(sorted((k, v) for k, v in ov.items() if k != "t_end")), jobs=args.jobs,
        executor=args.executor, scheduler=args.scheduler, repeats=args.repeats, horizon=args.horizon,
        figures=not args.no_figures, fresh=args.fresh, compare_with=tuple(args.compare_with or ()),
        command=_command(args), accept_legacy=args.accept_legacy, budget=common.budget(args)), log=_log)


def _check_horizon_size(args, overrides: dict) -> None:
    """The energy study `run` makes when --horizon asks for one fits, as any run must
    (`options.check_size`): e.g. --horizon 1e9 would take 2e11 steps at dt = 0.005 s (it crashed
    its worker). Without --horizon (or with 0) there is no study to check."""
    from benchmark.studies import horizon
    from models import load_scene

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
    from benchmark.runs.sweep import plugin_names

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
    from integrators import origin

    return ", ".join(f"{n} ({origin(n).label().removeprefix('plugin, ')})" for n in names)


def cmd_simulate(args) -> int:
    from models import load_scene

    scene = load_scene(args.scene, **common.overrides(args.set))  # --integrators: a registered name (parsed)
    if args.t_end is not None:
        scene = scene.with_(t_end=args.t_end)  # the same range and plausibility rules as the file
    out = opt.writable_file(args.out if args.out is not None else
                            inside(Path.cwd(), f"simulate_{scene.name}_{args.integrator}.npz"))
    if out.suffix != ".npz":
        raise UsageError(f"--out {str(out)!r}: a trajectory file ends in .npz (the diagnostics go beside it as .csv)")
    if args.save_every > scene.t_end:
        raise UsageError(f"--save-every {args.save_every:g} is longer than the run (t_end = {scene.t_end:g} s): "
                         f"give a save interval <= t_end")
    size = opt.check_size(scene, scene.t_end, args.save_every, args.dt, warn=_log,
                          what=f"{scene.name} to t_end = {scene.t_end:g} s")
    _check_setting(_check_integrator(args.integrator), args.dt, args.rtol, scene.t_end)
    settings = {"save_every": args.save_every, "max_steps": args.max_steps, "time_limit": args.time_limit}
    if args.dt is not None:
        settings["dt"] = args.dt
    if args.rtol is not None:
        settings.update(policy.Setting.adaptive(args.rtol, args.atol).solve_kwargs())

    from benchmark.cli import simulate

    return simulate.simulate(scene, args.integrator, settings, out, estimate=size["seconds"], log=_log)


def cmd_figures(args) -> int:
    from benchmark.core.store import UnreadableFile, read_trajectory
    from models import load_scene
    from models.layout import StateLayout

    src = Path(args.trajectory)
    if not src.exists():
        raise UsageError(f"{src}: no such file; give a trajectory written by `simulate` (.npz)")
    if not src.is_file():
        raise UsageError(f"{src}: is not a file; give a trajectory written by `simulate` (.npz)")
    ov = common.overrides(args.set)
    if args.scene:
        load_scene(args.scene, **ov)  # a bad scene is refused before the trajectory is read
    # beside the trajectory (as simulate puts its .csv beside it), unless --out says where
    out = opt.writable_file(args.out if args.out is not None else inside(src.resolve().parent, f"{src.stem}.png"))
    try:
        traj = read_trajectory(src)
    except UnreadableFile as exc:
        raise UsageError(f"{src}: not a trajectory file ({exc}); give a trajectory written by `simulate`") from None
    if not _any_finite(traj.x):  # a figure of nothing would look like a result
        raise UsageError(f"{src}: the trajectory has no finite point (status {getattr(traj, 'status', '?')}): "
                         "nothing to draw; give a trajectory of a run that computed something")
    _check_trajectory(src, traj)
    from models.schema import is_safe_name
    from models.scene import scene_from_dict

    recorded = getattr(traj, "scene", None)
    if not args.scene and isinstance(recorded, dict) and recorded:  # the scene the trajectory was computed with
        try:
            scene = scene_from_dict(recorded, source=str(src), **ov)
        except ValueError as exc:
            raise UsageError(f"{src}: the scene recorded in the file is not valid ({exc}); give --scenes") from None
    else:
        if not args.scene and not is_safe_name(traj.scene_name):  # a name read from a file is data, not a path
            raise UsageError(f"{src} records the scene {traj.scene_name!r}, which is not a scene name: give --scenes "
                             "(the scene name or .toml path the trajectory was computed with)")
        scene = load_scene(args.scene or traj.scene_name, **ov)
    lay = StateLayout.from_scene(scene)
    nx = traj.x.shape[1] if getattr(traj.x, "ndim", 0) == 2 else None
    if nx != lay.nx or (traj.attitude is not None) != lay.has_attitude:
        raise UsageError(f"{src} does not fit scene {scene.name!r} as given: the file has {nx} coordinates per "
                         f"point{' and an attitude' if traj.attitude is not None else ''}, the scene "
                         f"{lay.nx}{' and an attitude' if lay.has_attitude else ''}; give the scene the trajectory "
                         f"was computed with (recorded: {traj.scene_name!r}), with the same --set overrides")
    from benchmark.cli import simulate

    return simulate.draw_figures(scene, traj, out, log=_log)


def _check_trajectory(src: Path, traj) -> None:
    """A trajectory `figures` draws: its status one a run can end with, and every saved value
    finite (a run keeps only the finite part of what it computed: anything else was not written
    by `simulate`)."""
    import numpy as np

    from benchmark.runs.table import statuses

    status = getattr(traj, "status", None)
    if not isinstance(status, str) or status not in statuses():
        raise UsageError(f"{src}: its metadata says status {status!r}, which is not a status a run ends with "
                         f"({', '.join(statuses())}): not a trajectory written by `simulate`")
    for name in ("t", "x", "attitude", "velocity", "work"):
        values = getattr(traj, name, None)
        if values is None:
            continue
        try:
            bad = int(np.size(values) - np.isfinite(np.asarray(values, dtype=float)).sum())
        except (TypeError, ValueError):
            raise UsageError(f"{src}: its {name} array is not numbers: not a trajectory written by "
                             "`simulate`") from None
        if bad:
            raise UsageError(f"{src}: its {name} array holds {bad} value(s) that are not finite (inf or nan): not a "
                             "trajectory written by `simulate` (a run keeps only what it computed finitely)")


def cmd_check(args) -> int:
    from benchmark.studies import check

    if not args.update and args.baseline is None and not Path(check.BASELINE).exists():
        raise UsageError(f"the committed baseline {check.BASELINE} is not in {Path.cwd()}: run `check` from the "
                         f"repository's root directory, or give --baseline PATH")
    # how the baseline was produced, for its header (the options that change its content)
    command = check.UPDATE_COMMAND + "".join(f" --{k} {shlex.quote(v)}" for k, v in
                                             (("integrators", ",".join(args.integrators or ())),
                                              ("baseline", args.baseline)) if v)
    # --integrators and --allow-new: registered names, --factor and --order-margin in range (parsed)
    return check.run_check(update=args.update, baseline=args.baseline, integrators=args.integrators,
                           factor=args.factor, order_margin=args.order_margin, jobs=args.jobs, command=command,
                           allow_new=tuple(args.allow_new or ()), budget=common.budget(args), log=_log)


def cmd_speed(args) -> int:
    from models import load_scene

    from benchmark.studies.lgvi_speed import SpeedRequest  # JAX-free until a measurement runs

    default = SpeedRequest()
    elements, scenes = tuple(args.elements or default.elements), tuple(args.scenes or default.scenes)
    horizon = {"t_end": args.dt * args.steps} if args.dt is not None else {}  # what each timed run covers
    for sc in scenes:  # every scene and N is checked (names, plausibility) before any work
        for n in elements:
            try:
                load_scene(sc, elements=n, **horizon)
            except ValueError as exc:
                if not horizon or "'t_end'" not in str(exc):
                    raise
                raise UsageError(f"--dt {args.dt:g} x --steps {args.steps} = {horizon['t_end']:g} s per timed run: "
                                 f"{exc}; give a smaller --dt or fewer --steps") from None
    if args.out.strip() == "-":  # each measurement is saved as it finishes: the tables always go to a file
        raise UsageError("--out -: the speed tables are saved (and printed): give a Markdown file, e.g. speed.md")
    out = opt.writable_file(args.out)
    from benchmark.core import study
    from benchmark.studies import lgvi_speed

    if out.is_file() and not lgvi_speed.rows_file(out).exists():
        raise UsageError(f"--out {out}: the file exists without its rows table {lgvi_speed.rows_file(out)}, "
                         "so its rows could not be kept; this run would overwrite them: give another --out, or move "
                         "it away")
    opt.no_directory_at(out.parent, (out.name, lgvi_speed.rows_file(out).name))
    from integrators.rhs import check_rhs

    rhs = tuple(v.strip() for v in args.rhs.split(",") if v.strip())
    for r in rhs:
        check_rhs(r)
    if args.integrators:
        lgvi_speed.check_methods(args.integrators)
    request = SpeedRequest(elements=elements, scenes=scenes, methods=tuple(args.integrators) if args.integrators else None,
                           steps=args.steps, repeats=args.repeats, dt=args.dt, rhs=rhs, autodiff_max_n=args.autodiff_max_n)
    return study.run(lgvi_speed.study(request, out), out.parent, command=_command(args), fresh=args.fresh, log=_log)


def cmd_stability(args) -> int:
    from benchmark.core import study
    from benchmark.studies import stability

    # the study checks its scene and integrator names
    the_study = stability.study(args.scenes, args.integrators, workers=args.jobs, budget=common.budget(args))
    out = opt.writable_dir(args.out)
    opt.no_directory_at(out, ("stability.csv", "stability.md", "stability.png", "README.md"))
    return study.run(the_study, out, command=_command(args), fresh=args.fresh, log=_log)


def cmd_answer(args) -> int:
    """The main job: the cheapest setting of every method at every target by search, and paired timing."""
    from benchmark.answer import answer
    from benchmark.runs import sweep
    from benchmark.answer.answer import AnswerRequest
    from models import load_scene

    targets = args.targets or tuple((m, t) for m, t, _ in answer.TARGETS)  # parsed: `_targets`
    scenes = tuple(args.scenes or (sweep.EXTENDED_SCENES if args.extended else sweep.PAPER_SCENES))
    elements = tuple(args.elements or (answer.EXTENDED_ELEMENTS if args.extended else answer.ELEMENTS))
    for sc in scenes:
        for n in elements:
            load_scene(sc, elements=n, **({"t_end": args.t_end} if args.t_end else {}))  # validated before work
    out = opt.writable_dir(args.out)
    names = tuple(args.integrators) if args.integrators else answer.default_methods(args.extended)
    return answer.run_answer(AnswerRequest(out=out, scenes=scenes, integrators=names, elements=elements,
                                           targets=targets, t_end=args.t_end, max_runs=args.max_runs,
                                           timing_budget=args.timing_budget, jobs=args.jobs, fresh=args.fresh,
                                           command=_command(args), compare_with=tuple(args.compare_with or ()),
                                           executor=args.executor, scheduler=args.scheduler), log=_log)


def _targets(text: str) -> tuple:
    """``metric=target,...`` -> ((metric, target), ...): each metric one of the runs table's
    accuracy metrics, each target a positive number."""
    from benchmark.runs.metrics import ACCURACY

    out = []
    for part in text.split(","):
        metric, _, value = part.strip().partition("=")
        if metric not in ACCURACY:
            raise UsageError(f"{text!r}: {metric!r} is not a metric (allowed: {', '.join(ACCURACY)}), "
                             "e.g. --targets energy_error=1e-5,position_error_final=1e-7")
        try:
            target = float(value)
        except ValueError:
            target = float("nan")
        if not (0 < target < float("inf")):
            raise UsageError(f"{text!r}: the target of {metric} must be a positive number (got {value!r})")
        out.append((metric, target))
    if len({m for m, _ in out}) != len(out):
        raise UsageError(f"{text!r}: each metric at most once (e.g. --targets energy_error=1e-5)")
    return tuple(out)


def cmd_xval(args) -> int:
    """Cross-validation against MoorDyn and MuJoCo; exit 2 on a scene it cannot translate."""
    import importlib.util

    ints = args.elements or None  # two or more N >= 2 (parsed)
    from benchmark.studies import xval
    from models import load_scene

    scene = load_scene(args.scene, **({"t_end": args.t_end} if args.t_end else {}))  # plausible horizon
    unknown = [c for c in args.cases or () if c not in xval.CASES]
    if unknown:
        raise UsageError(f"--cases {_csv(unknown)}: allowed {_csv(xval.CASES)}")
    xval.check_scene(scene)  # names what cannot be translated, before any work
    opt.check_size(scene, args.t_end or xval.DEFAULT_T_END, xval.OUTPUT_INTERVAL, what=f"xval of {scene.name}",
                   save_option=None)
    out = opt.writable_dir(args.out)
    missing = [m for m in ("moordyn", "mujoco") if importlib.util.find_spec(m) is None]
    if missing:
        raise UsageError(f"xval needs {', '.join(missing)}: pip install 'reelbench[xval]'")
    return xval.run_xval(args.scene, ints or list(xval.DEFAULT_ELEMENTS), args.t_end or xval.DEFAULT_T_END, out,
                         command=_command(args), log=_log, cases=args.cases)


def cmd_reel_reversal(args) -> int:
    from benchmark.studies import reel_reversal
    from models import load_scene

    reel_reversal.check_methods(args.integrators or ())
    reel_reversal.check_horizon(args.t_end)
    scene = load_scene(args.scene, elements=args.elements)
    if not scene.has("reel"):  # its "error" column would be a node coordinate, its sign changes noise
        raise UsageError(f"--scenes {scene.name!r} has no reel (effects: {', '.join(scene.effects)}): the reel-reversal "
                         "study follows the reel rate through its change of sign; give a scene with the reel effect, "
                         "e.g. --scenes reel_reversal")
    from benchmark.core import study
    from benchmark.core.reference import CACHE_DIR

    cache = opt.writable_dir(args.cache_dir or CACHE_DIR, option="--cache-dir")
    out = opt.writable_dir(args.out)
    opt.no_directory_at(out, ("reel_reversal.csv", "reel_reversal.md"))
    the_study = reel_reversal.study(args.scene, args.elements, args.t_end, args.integrators, workers=args.jobs,
                                    cache_dir=str(cache))
    return study.run(the_study, out, command=_command(args), fresh=args.fresh, log=_log)


def cmd_orders(args) -> int:
    from benchmark.studies import orders
    from models import load_scene

    for sc in args.scenes or ():
        load_scene(sc)  # an unknown scene is refused before any work
    the_study = orders.study(args.scenes, args.integrators, workers=args.jobs)  # an adaptive-only method likewise
    out = opt.writable_dir(args.out)
    opt.no_directory_at(out, ("orders_errors.csv", "orders.csv"))
    from benchmark.core import study

    return study.run(the_study, out, command=_command(args), fresh=args.fresh, log=_log)


def cmd_energy(args) -> int:
    from benchmark.core import study
    from benchmark.studies import horizon
    from models import load_scene

    for sc in args.scenes or ():
        load_scene(sc)
    horizon.methods(args.integrators)  # an unknown name is refused (one outside the plan makes no runs)
    variants = tuple(args.variants) if args.variants else tuple(horizon.VARIANTS)
    unknown = [v for v in variants if v not in horizon.VARIANTS and v != "plain"]
    if unknown:
        raise ValueError(f"unknown string variant(s) {', '.join(unknown)}: choose from plain, "
                         + ", ".join(v for v in horizon.VARIANTS if v))
    the_study = horizon.study(args.horizon, args.scenes, selected=args.integrators, workers=args.jobs, text=True,
                              variants=tuple("" if v == "plain" else v for v in variants))
    out = opt.writable_dir(args.out)
    opt.no_directory_at(out, (horizon.TABLE, "energy_horizon.md", "README.md"))
    if not the_study.jobs:
        _log("horizon: none of the selected methods is in the energy study's plan; nothing written")
        return 0
    return study.run(the_study, out, command=_command(args), fresh=args.fresh, log=_log)


def cmd_verify(args) -> int:
    """The plugin contract (benchmark/contract/verify.py): exit 0 when every check holds, 1 otherwise."""
    from benchmark.contract import verify

    ov = common.overrides(args.set)
    for name in args.names:  # an unknown name, a scene without the effect or a bad one: exit 2 before any work
        kind = verify.kind_of(name)
        if kind == "integrator" and (args.scene or ov):
            raise UsageError(f"--scenes/--set are for an effect; {name} is an integrator, checked on its own "
                             "small scenes")
        if kind == "effect":
            verify.effect_scene(name, args.scene, ov)
    return max(verify.verify(name, scene=args.scene, overrides=ov, log=print) for name in args.names)


def cmd_work_rule(args) -> int:
    """The flop rule against compiled floors (`benchmark.work.work_rule`); --floor, --elements and
    --steps are checked by their parse functions."""
    out = None if args.out == "-" else opt.writable_file(args.out)  # --out -: print only
    from benchmark.work import work_rule
    from models.io import atomic_write_text

    text = work_rule.report(args.floor, args.elements, args.steps, args.repeats, command=_command(args))
    if out is None:
        print(text)
    else:
        atomic_write_text(out, text)
        _log(f"wrote {out}")
    return 0


def cmd_list(args) -> int:
    from benchmark.runs.sweep import EXTENDED_METHODS
    from integrators import available, get_integrator, origin, plugin_errors
    from models import available_scenes

    print("scenes:", ", ".join(available_scenes()))
    names, failed_methods = available(), plugin_errors()
    width = max(map(len, [*names, *failed_methods]), default=10)  # one column of names, however long
    for name in names:
        integ = get_integrator(name)
        caps = ", ".join(sorted(c.value for c in integ.capabilities))
        own = origin(name).own
        # a plugin is a guest: it joins no sweep unasked
        sweep = ("extended" if name in EXTENDED_METHODS else "default") if own else "plugins"
        guest = "" if own else f"  ({origin(name).label()})"
        print(f"  {name:{width}s}  order {integ.order}  {sweep:10s}  [{caps}]  {integ.description}{guest}")
    for name, err in failed_methods.items():
        print(f"  {name:{width}s}  FAILED TO LOAD: {err}")
    print("  (default: in the default sweep; extended: only in the extended sweep, or when --integrators names it; "
          "plugins: a plugin, swept with --with-plugins or when --integrators names it)")
    from models import EFFECTS
    from models.effects import effect_origin, plugin_errors as effect_plugin_errors

    failed = effect_plugin_errors()  # loads the reelbench.effects plugins first
    print("effects:", ", ".join(n if effect_origin(n).own else f"{n} ({effect_origin(n).label()})" for n in EFFECTS))
    for name, err in failed.items():
        print(f"  {name:{max(map(len, failed))}s}  FAILED TO LOAD: {err}")
    return 0


# ------------------------------------------------------------------------------------------
# The parser: one builder per command
# ------------------------------------------------------------------------------------------
class _Help(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, except where there is none to show (None, a flag's False)."""

    def _get_help_string(self, action):
        if action.default in (None, False) or isinstance(action, argparse._HelpAction):
            return action.help
        return super()._get_help_string(action)


def _add_run(sub) -> None:
    from benchmark.runs import sweep  # constants only (no JAX): the defaults shown in --help are the real ones

    r = sub("run", "sweep scenes × integrators × settings; tables, plots and a README into --out",
            "Sweep scenes × integrators × settings. Rows are written to OUT/runs.csv as they finish and join "
            "the rows already there: rows of other scenes, methods or settings are kept, and the figures and "
            "README are written from the whole table. A row of the same run (same scene physics, integrator, "
            "setting, horizon and code) that passes its checks is kept instead of recomputed (--fresh "
            "recomputes this run's rows). Ctrl-C stops cleanly.")
    common.add_scenes(r, f"(default: {_csv(sweep.PAPER_SCENES)})")
    r.add_argument("--extended", action="store_true", help="the paper's scenes and the fluid scenes "
                                                           f"({_csv(sweep.FLUID_SCENES)}: buoyancy and drag)")
    common.add_integrators(r, "(default: the project's own methods; installed plugins join when named here or with "
                              "--with-plugins)")
    r.add_argument("--with-plugins", action="store_true", help="sweep every installed plugin too (with the default "
                   "methods); its rows go to --out, which must then be given")
    r.add_argument("--quick", action="store_true", help=f"reduced sweep: {sweep.QUICK_T_END:g} s horizon, "
                   f"{len(sweep.QUICK_DTS)} step sizes, {len(sweep.QUICK_RTOLS)} tolerances, "
                   "no energy study unless --horizon is given")
    r.add_argument("--dts", type=opt.positive_floats, help="comma-separated step sizes (s) for fixed-step methods, "
                   f"any size (saved at the step points nearest the save times; default: {_csv(sweep.FULL_DTS)}; "
                   f"--quick: {_csv(sweep.QUICK_DTS)})")
    r.add_argument("--rtols", type=opt.tolerances, help="comma-separated relative tolerances for adaptive methods, "
                   f"atol = rtol × {policy.ATOL_FACTOR:g} (default: {_csv(sweep.FULL_RTOLS)}; implicit methods "
                   f"{_csv(sweep.IMPLICIT_FULL_RTOLS)}; --quick: {_csv(sweep.QUICK_RTOLS)}, implicit "
                   f"{_csv(sweep.IMPLICIT_QUICK_RTOLS)})")
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


def _add_check(sub) -> None:
    c = sub("check", "recompute a short sweep and compare its accuracy metrics with the committed baseline; "
                     "exit 1 on a regression (rules in benchmark/studies/check.py)")
    c.add_argument("--update", action="store_true", help="rewrite the baseline from this run instead of failing")
    common.add_budget(c, "the check goes on")
    c.add_argument("--baseline", help=f"baseline CSV (default: {policy.BASELINE_FILE}, run from the repository root)")
    common.add_integrators(c, "(default: all registered except test_*)")
    c.add_argument("--factor", type=common.ruled(opt.number, opt.check_factor, "factor"),
                   help=f"a drift or error fails when worse than FACTOR x baseline, above its floor (default: "
                        f"{policy.CHECK_FACTOR:g})")
    c.add_argument("--order-margin", type=common.ruled(opt.number, opt.check_order_margin, "margin"),
                   help="an observed order fails when lower than baseline - MARGIN (default: "
                        f"{policy.CHECK_ORDER_MARGIN:g})")
    common.add_jobs(c, "the CPU count", workers_only="check runs its sweep in worker processes")
    c.add_argument("--allow-new", type=common.integrator_names, metavar="NAMES",
                   help="comma-separated integrators that may lack baseline rows (new methods); any other selected "
                        "integrator without rows to compare fails the check (exit 2)")
    common.add_check(c, _allow_new_checks_against_the_baseline)
    c.set_defaults(func=cmd_check)


def _allow_new_checks_against_the_baseline(args) -> None:
    if args.allow_new and args.update:
        raise UsageError("--allow-new is for a check against the baseline; --update writes the rows of every "
                         "integrator it runs")


def _atol_needs_rtol(args) -> None:
    if args.atol is not None and args.rtol is None:
        raise UsageError("--atol needs --rtol (an adaptive method); with --dt the step is fixed and atol is unused")


def _add_simulate(sub) -> None:
    s = sub("simulate", "one scene, one integrator, one setting -> trajectory .npz + diagnostics .csv",
            "Run one scene with one integrator at one setting: a fixed step (--dt) or a tolerance (--rtol), "
            "never both. Writes the trajectory (.npz) and its diagnostics (.csv, energies, π3, orthogonality "
            "error, lengths) to --out, by default into the current directory.")
    s.add_argument("scene", help="a shipped scene name (see `list`) or the path of a scene .toml file "
                                 "(format: models/README.md)")
    common.add_integrators(s, "", one=True, default="lgvi")
    setting = s.add_mutually_exclusive_group()
    setting.add_argument("--dt", type=opt.positive_float, help="fixed step size in s (fixed-step methods)")
    setting.add_argument("--rtol", type=opt.tolerance, help="relative tolerance (adaptive methods); atol defaults "
                                                            f"to rtol × {policy.ATOL_FACTOR:g}")
    s.add_argument("--atol", type=opt.positive_float,
                   help=f"absolute tolerance, with --rtol (default: rtol × {policy.ATOL_FACTOR:g})")
    common.add_check(s, _atol_needs_rtol)
    common.add_t_end(s, "(default: the scene's t_end)")
    s.add_argument("--save-every", type=opt.positive_float, default=policy.SAVE_EVERY, help="save interval in s")
    common.add_budget(s, "its trajectory is saved (a first Ctrl-C ends the run the same way, a second at once)")
    common.add_set(s)
    common.add_out(s, "trajectory file (.npz; default: ./simulate_SCENE_INTEGRATOR.npz)")
    s.set_defaults(func=cmd_simulate)


def _add_figures(sub) -> None:
    f = sub("figures", "the paper's panels (a)-(d) from a trajectory file written by `simulate`")
    f.add_argument("trajectory", help="a trajectory .npz written by `simulate`")
    common.add_scenes(f, "the one the trajectory was computed with (default: the one recorded in the file)", one=True)
    common.add_set(f, "scene overrides the trajectory was computed with, e.g. --set elements=20")
    common.add_out(f, "figure file (.png; default: TRAJECTORY.png beside the trajectory file)")
    f.set_defaults(func=cmd_figures)


def _add_speed(sub) -> None:
    from benchmark.studies.lgvi_speed import SpeedRequest  # JAX-free: the defaults shown in --help are the real ones

    default = SpeedRequest()
    sp = sub("speed", "time per step of every fixed-step method and per-call cost of each right-hand side vs N, "
                      "compile time separately",
             "Time per step of every fixed-step method (chosen by capability from the registry) and per-call cost "
             "of each right-hand side, vs N; compile time separately (see benchmark/studies/lgvi_speed.py).")
    common.add_elements(sp, f"(default: {_csv(default.elements)})")
    common.add_scenes(sp, f"(default: {_csv(default.scenes)})")
    common.add_integrators(sp, "fixed-step methods only (default: every registered one with the fixed_step "
                               "capability)", registered=False)
    sp.add_argument("--steps", type=opt.positive_int, default=default.steps, help="steps per timed run")
    sp.add_argument("--repeats", type=opt.positive_int, default=default.repeats, help="timed repeats (median)")
    sp.add_argument("--dt", type=opt.positive_float,
                    help="step size (default: per-scene stable step at N = 10, times 10/N)")
    sp.add_argument("--rhs", default=_csv(default.rhs), help="right-hand sides to time per call ('' = none)")
    sp.add_argument("--autodiff-max-n", type=opt.positive_int, default=default.autodiff_max_n,
                    help="largest N for the O(N^3) autodiff right-hand side")
    common.add_fresh(sp, "the rows table beside --out")
    common.add_out(sp, "the tables (Markdown, with the command and machine; also printed): this run's rows join "
                       "those of the rows table beside it (.csv; rows of other methods, scenes and N are kept) and "
                       "the file is written from the whole table", default=str(policy.LGVI_SPEED_FILE))
    sp.set_defaults(func=cmd_speed)


def _add_stability(sub) -> None:
    st = sub("stability", "stability map of the hard scenes: largest stable dt (fixed step), step statistics "
                          "(adaptive) -> --out")
    common.add_scenes(st, "the hard scenes of the map (default: all eight)")
    common.add_integrators(st, "(default: the project's own methods, implicit baselines last; a plugin runs when "
                               "named)", registered=False)  # the study checks its own names
    common.add_jobs(st, "", default=2)
    common.add_budget(st, "the map goes on (such a row is recomputed on resume)")
    common.add_fresh(st, "OUT/stability.csv")
    common.add_out(st, "output directory (created if missing)", default=str(policy.STABILITY_DIR))
    st.set_defaults(func=cmd_stability)


def _add_answer(sub) -> None:
    from benchmark.answer import answer
    from benchmark.answer import search  # constants only (no JAX)

    an = sub("answer", "the main job: each method's cheapest setting at each target by search, wall-time verdicts "
                       "by paired timing -> --out/cheapest.csv, README.md, figures (and the README's answer block)",
             "For every scene x N x method x target, search the cheapest setting meeting the target that stands "
             f"(bracket, bisect to {policy.RESOLUTION * 100:g} % in cost, confirm the three settings just finer; "
             "benchmark/answer/search.py), then time the compiled methods at their settings paired and interleaved "
             "on one pinned core, racing (benchmark/answer/paired.py). Default: the paper's three scenes at N = 10 "
             "with the default methods and dopri8; --extended: every method, the scenes in water and the off-centre "
             "tow too, at N = 10 and 40, its rows merged into the same table. Resumable: rerun to continue.")
    an.add_argument("--extended", action="store_true",
                    help="every one of the project's methods on the paper's and the fluid scenes at N = 10 and 40")
    common.add_scenes(an, "(default: the paper's three)")
    common.add_integrators(an, "(default: the default sweep's and dopri8; --extended: all of the project's)")
    common.add_elements(an, "(default: 10; --extended: 10,40)")
    an.add_argument("--targets", type=common.as_type(_targets, "targets"),
                    help="comma-separated metric=target pairs on any accuracy metric of the runs table (default: "
                         f"{','.join(f'{m}={t:g}' for m, t, _ in answer.TARGETS)})")
    common.add_t_end(an, "(default: each scene's t_end)")
    an.add_argument("--max-runs", type=opt.positive_int, default=search.MAX_RUNS, help="runs per search at most")
    an.add_argument("--timing-budget", type=opt.positive_float, default=policy.PAIRED_BUDGET,
                    help="seconds of paired timing per scene x N x target at most")
    common.add_jobs(an, "one per CPU", workers_only="answer searches in worker processes; --executor serial "
                                                    "searches in this process")
    common.add_executor(an, "the searches (the paired timing stays in this process, on one pinned core)")
    common.add_fresh(an, "OUT/cheapest.csv")
    an.add_argument("--compare-with", type=opt.answer_table, action="append", metavar="CHEAPEST.csv",
                    help="an earlier answer table: README.md says which answers agree (repeatable)")
    common.add_out(an, "output directory (created if missing; results/ also rewrites the README's answer)",
                   default=str(answer.COMMITTED_ANSWER))
    an.set_defaults(func=cmd_answer)


def _add_xval(sub) -> None:
    xv = sub("xval", "cross-validation against MoorDyn and MuJoCo at equal N -> --out (needs the [xval] extra)")
    common.add_scenes(xv, "a fixed-length scene", one=True, default="fixed_length")
    common.add_elements(xv, "two or more N >= 2 (default: 5,10,20,40,80; 5,10,20,40,80,160 takes about 4x longer)",
                        least=2, two_or_more=True)
    common.add_t_end(xv, "(default: 5)")
    xv.add_argument("--cases", type=opt.names, help="comma-separated cases of point_mass, rigid_body, in_water "
                                                    "(default: every case the scene has)")
    common.add_out(xv, "output directory (created if missing)", default=str(policy.XVAL_DIR))
    xv.set_defaults(func=cmd_xval)


def _add_reel_reversal(sub) -> None:
    from benchmark.studies import reel_reversal  # constants only (no JAX)

    rr = sub("reel-reversal", "orders of the fixed-step methods across a reel reversal (ṡ_p changes sign), errors "
                              "against the reference -> --out/reel_reversal.csv, reel_reversal.md (also printed)")
    common.add_scenes(rr, "a scene with the reel effect", one=True, default="reel_reversal")
    common.add_elements(rr, "", one=True, default=5)
    common.add_t_end(rr, f"a multiple of the compared interval {reel_reversal.COMPARE_EVERY:g} s", default=0.96)
    common.add_integrators(rr, f"fixed-step methods with a step list (default: {_csv(reel_reversal.DEFAULT_HS)})",
                           registered=False)
    common.add_jobs(rr, "one per method, at most the CPU count")
    rr.add_argument("--cache-dir", help="where the reference is cached (default: the user's cache, shared by every "
                                        "study; created if missing)")
    common.add_fresh(rr, "OUT/reel_reversal.csv")
    common.add_out(rr, "output directory (created if missing); rows of other cases, methods and steps are kept",
                   default=str(reel_reversal.OUT_DIR))
    rr.set_defaults(func=cmd_reel_reversal)


def _add_orders(sub) -> None:
    from benchmark.studies import orders  # constants only (no JAX)

    o = sub("orders", "observed orders of the fixed-step methods on a short horizon, against a reference "
                      "100x more accurate -> OUT/orders.csv",
            f"Each fixed-step method at {orders.HALVINGS} halvings of its step on a {orders.T_END:g} s horizon of "
            f"each scene (N = {orders.ELEMENTS}), against constant-step {orders.REFERENCE_METHOD}; the order is the "
            "slope of the last halving above the reference's floor, flagged when not asymptotic (see "
            "benchmark/studies/orders.py). Rows of other scenes and methods in OUT/orders.csv are kept.")
    common.add_scenes(o, f"(default: {_csv(orders.SCENES)}, one per situation)")
    common.add_integrators(o, "fixed-step methods only (default: every registered one)", registered=False)
    common.add_jobs(o, "one per method, at most the CPU count")
    common.add_fresh(o, "OUT/orders_errors.csv")
    common.add_out(o, "output directory (created if missing)", default=str(policy.RESULTS))
    o.set_defaults(func=cmd_orders)


def _add_energy(sub) -> None:
    from benchmark.studies import horizon  # constants only (no JAX)

    e = sub("energy", "the long-horizon energy study: energy error vs time beside the axial vibration and "
                      "the least tension, the modified-energy offset told apart from drift -> "
                      "OUT/energy_horizon.csv, figures and OUT/energy_horizon.md",
            "The energy study (benchmark/studies/horizon.py): the runs of its plan (horizon.PLAN: methods, N = "
            f"{_csv(horizon.ELEMENTS)}, each method's setting in horizon.SETTINGS and {horizon.FINER:g}x finer), "
            "on each scene and with the tension-only string (`slack`); the histories already in "
            "OUT/energy_horizon.csv for the same settings and code are kept, rows of other methods and scenes too.")
    common.add_scenes(e, f"(default: {horizon.DEFAULT_SCENE})")
    common.add_integrators(e, "(default: every method of the study's plan)", registered=False)
    e.add_argument("--horizon", type=opt.positive_float, default=horizon.HORIZON, help="length in s")
    e.add_argument("--variants", type=opt.names, help="comma-separated string laws: plain (the scene as it is), "
                                                      "slack (tension-only) (default: both)")
    common.add_jobs(e, "one per run, at most the CPU count")
    common.add_fresh(e, "OUT/energy_horizon.csv")
    common.add_out(e, "output directory (created if missing)", default=str(policy.RESULTS))
    e.set_defaults(func=cmd_energy)


def _add_verify(sub) -> None:
    v = sub("verify", "check an integrator or an effect (a plugin's, or one of the project's) against the plugin "
                      "contract: one line per check with its figure; exit 1 on a failure",
            "Check an integrator or an effect against the plugin contract (benchmark/contract/verify.py): for an "
            "integrator its declared order on a fixed-length and a reeling scene, its statuses and guards, its "
            "capabilities, determinism and its flop count; for an effect its gradients against autodiff, its power, "
            "the energy balance with a reference method and the validation of its scene keys. Small scenes: seconds "
            "to tens of seconds, mostly compilation.")
    v.add_argument("names", nargs="+", metavar="NAME", help="registered integrators or effects (see `list`)")
    common.add_scenes(v, "for an effect: a scene that lists it (default: a small scene with the effect and what it "
                         "needs; required when its keys have no default)", one=True)
    common.add_set(v, "for an effect: a scene override, repeatable, e.g. --set stiffness=20")
    v.set_defaults(func=cmd_verify)


def _add_work_rule(sub) -> None:
    from benchmark.work import work_rule  # constants only (no JAX)

    w = sub("work-rule", "the flop rule against compiled floors: does the work column charge methods in the "
                         "proportion their compiled steps take time? -> --out (results/work_rule.md)",
            "The flops of one step by the project's rule (benchmark/work/flops.py), and by the earlier rule, against "
            "the time of one step of numba floors of the same equations kept outside the repository (--floor), "
            "timed interleaved; the floors' own flops counted exactly (benchmark/work/opcount.py). Pin one core "
            "(taskset -c 0) on a quiet machine: floor times on a loaded one are noisy.")
    w.add_argument("--floor", required=True, type=common.as_type(work_rule.floor_dir, "floor directory"),
                   help=f"directory of the numba floors ({', '.join(work_rule.FLOORS)})")
    common.add_elements(w, "", least=2, default=_csv(work_rule.ELEMENTS))
    w.add_argument("--steps", type=common.ruled(opt.positive_int, work_rule.check_steps, "steps"),
                   default=work_rule.STEPS, help="steps per timed floor run at N = 10, fewer in proportion above")
    w.add_argument("--repeats", type=opt.positive_int, default=work_rule.REPEATS, help="interleaved repeats (the "
                                                                                       "least time counts)")
    common.add_out(w, "the Markdown table; - = only print it", default=str(policy.WORK_RULE_FILE))
    w.set_defaults(func=cmd_work_rule)


#: The commands, in the order `--help` lists them.
BUILDERS = (_add_run, _add_check, _add_simulate, _add_figures, _add_speed, _add_stability, _add_answer, _add_xval,
            _add_reel_reversal, _add_orders, _add_energy, _add_verify, _add_work_rule)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmark", description=__doc__, formatter_class=_Help)
    commands = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def sub(name: str, help: str, description: str | None = None) -> argparse.ArgumentParser:
        return commands.add_parser(name, help=help, description=description or help, formatter_class=_Help)

    for add in BUILDERS:
        add(sub)
    sub("list", "registered integrators and shipped scenes").set_defaults(func=cmd_list)
    return p


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        try:
            args = parser().parse_args(argv)
        except SystemExit as exc:  # --help (0) or a bad option (2, argparse printed "error: ...")
            return exc.code if isinstance(exc.code, int) else 2
        args.argv = argv
        common.run_checks(args)  # the checks that need a second option (`common.add_check`)
        if threading.current_thread() is threading.main_thread():
            from benchmark.core.engine import install_stop_handlers

            install_stop_handlers()  # SIGTERM stops every command like Ctrl-C: one line, exit 143
        return args.func(args)
    except ValueError as exc:  # bad input (UsageError, SceneError, an integrator's argument check)
        if os.environ.get("REELBENCH_DEBUG"):  # a developer chasing a ValueError gets its traceback
            raise
        _log(f"error: {printable(exc)}")  # input quoted in it (a path with a newline, U+202E) stays one line
        return 2
    except OSError as exc:  # the file system failed during work (full, read-only, ...): no traceback
        if os.environ.get("REELBENCH_DEBUG"):
            raise
        _log(f"error: {printable(exc)}")
        return 1
    except KeyboardInterrupt as exc:  # a command without its own stop message
        from benchmark.core.engine import stop_cause, stop_status

        _log(f"stopped by {stop_cause(exc)}: no result was written (this command writes its results when it ends)")
        return stop_status(exc)
