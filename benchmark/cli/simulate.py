"""`python -m benchmark simulate` and `python -m benchmark figures`: one run of one method on one
scene saved as a trajectory (.npz) and its diagnostics (.csv), and the paper's panels drawn from
a saved trajectory. A first Ctrl-C / SIGTERM ends the running solve where it is and saves it
(`_finish_on_stop`); a second stops at once.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable

from reelbench.benchmark.cli import common
from reelbench.benchmark.core import engine
from reelbench.benchmark.core import options as opt
from reelbench.benchmark.core import policy
from reelbench.benchmark.core.engine import log_stderr as _log  # the engine's: its lines go above a progress bar
from reelbench.benchmark.core.options import UsageError
from reelbench.models.io import inside


def _any_finite(values) -> bool:
    import numpy as np

    try:
        return bool(np.isfinite(np.asarray(values, dtype=float)).any())
    except (TypeError, ValueError):
        return False


def _check_integrator(name: str):
    """The integrator ``name``, or UsageError for an unknown one (the registry lists names and
    capabilities without importing JAX)."""
    from reelbench.integrators import get_integrator

    return get_integrator(name)


def _check_setting(integ, dt, rtol, t_end: float) -> None:
    """simulate's --dt / --rtol as the method takes them (from its declared capabilities)."""
    from reelbench.integrators import Capability

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


def cmd_simulate(args) -> int:
    from reelbench.models import load_scene

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

    return simulate(scene, args.integrator, settings, out, estimate=size["seconds"], log=_log)


def cmd_figures(args) -> int:
    from reelbench.benchmark.core.store import UnreadableFile, read_trajectory
    from reelbench.models import load_scene
    from reelbench.models.layout import StateLayout

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
    from reelbench.models.schema import is_safe_name
    from reelbench.models.scene import scene_from_dict

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
    return draw_figures(scene, traj, out, log=_log)


def _check_trajectory(src: Path, traj) -> None:
    """A trajectory `figures` draws: its status one a run can end with, and every saved value
    finite (a run keeps only the finite part of what it computed: anything else was not written
    by `simulate`)."""
    import numpy as np

    from reelbench.benchmark.runs.table import statuses

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


def _atol_needs_rtol(args) -> None:
    if args.atol is not None and args.rtol is None:
        raise UsageError("--atol needs --rtol (an adaptive method); with --dt the step is fixed and atol is unused")


def add_simulate(sub) -> None:
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


def add_figures(sub) -> None:
    f = sub("figures", "the paper's panels (a)-(d) from a trajectory file written by `simulate`")
    f.add_argument("trajectory", help="a trajectory .npz written by `simulate`")
    common.add_scenes(f, "the one the trajectory was computed with (default: the one recorded in the file)", one=True)
    common.add_set(f, "scene overrides the trajectory was computed with, e.g. --set elements=20")
    common.add_out(f, "figure file (.png; default: TRAJECTORY.png beside the trajectory file)")
    f.set_defaults(func=cmd_figures)


@contextlib.contextmanager
def _finish_on_stop(log: Callable[[str], None]):
    """A first Ctrl-C / SIGTERM ends the running solve at its next clock check, as its time budget
    would (`integrators.lifecycle.request_stop`): it returns what it has, to be saved; a second
    stops at once (KeyboardInterrupt). Yields the list that receives the first signal's name."""
    import signal
    import threading

    from reelbench.integrators import lifecycle

    caught: list[str] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return

    def soft(signum, frame):
        name = signal.Signals(signum).name
        if caught:
            raise KeyboardInterrupt(f"signal {name}")
        caught.append(name)
        lifecycle.request_stop()
        log(f"stopping ({'Ctrl-C' if name == 'SIGINT' else name}): the run ends at its next check and what it "
            "has is saved; stop again to quit at once, without saving")

    old = {sig: signal.signal(sig, soft) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield caught
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        lifecycle.request_stop(False)


def simulate(scene, integrator: str, settings: dict, out: Path, *, estimate: float | None = None,
             log: Callable[[str], None] = _log) -> int:
    """One run: the trajectory (.npz) and its diagnostics (.csv beside it); exit status 1 when
    the run did not finish (its budget ran out: ``max_steps`` / ``time_limit`` in ``settings``),
    130 / 143 when stopped by Ctrl-C / SIGTERM: a first stop ends the run where it is and saves
    it. ``estimate``: its expected seconds (a progress line every 30 s)."""
    import json

    import numpy as np

    from reelbench.integrators import get_integrator
    from reelbench.models.diagnostics import evaluate
    from reelbench.models.io import atomic_write_text

    integ = get_integrator(integrator)
    try:
        with _finish_on_stop(log) as caught, engine.Heartbeat(f"{scene.name} / {integ.name}", estimate, log=log):
            traj = integ.solve(scene, t_end=scene.t_end, **settings)
    except KeyboardInterrupt as exc:
        return engine.stopped(exc, "nothing saved (stopped twice: the run did not reach a point to save)", log)
    stop = KeyboardInterrupt(f"signal {caught[0]}") if caught else None
    if stop is not None:
        reached = float(traj.t[-1]) if len(traj.t) else 0.0
        traj.reason = f"stopped by {engine.stop_cause(stop)} at t = {reached:.6g} s (t_end = {scene.t_end:g} s)"
    traj.scene = scene.to_dict()  # `figures` draws it without the scene file
    try:
        traj.save(out)
        atomic_write_text(out.with_suffix(".csv"), evaluate(scene, traj).to_csv(index=False))
    except OSError as exc:
        log(f"error: {exc}; the run ended ({traj.status}) but is not saved: free space and run it again")
        return 1
    log(f"{scene.name} / {integ.name}: status {traj.status} {traj.reason}; {len(traj.t)} saved points; "
        f"stats {json.dumps({k: v for k, v in traj.stats.items() if np.isscalar(v)}, default=str)}")
    if stop is not None:
        return engine.stopped(stop, f"the run up to t = {traj.t[-1] if len(traj.t) else 0:.6g} s is saved in {out} "
                                    f"and {out.with_suffix('.csv')}", log)
    log(f"wrote {out} and {out.with_suffix('.csv')}")
    return 0 if traj.ok else 1


def draw_figures(scene, traj, out: Path, log: Callable[[str], None] = _log) -> int:
    """The paper's panels (a)-(d) of a saved trajectory."""
    from reelbench.benchmark.figures import plots
    from reelbench.models.diagnostics import evaluate

    plots.paper_panels(scene, traj, evaluate(scene, traj), out)
    log(f"wrote {out}")
    return 0

