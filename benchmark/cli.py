"""Command line: ``python -m benchmark {run,check,simulate,figures,speed,stability,list}`` (also ``reelbench``)."""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _floats(text: str | None):
    return None if text is None else [float(v) for v in text.split(",") if v.strip()]


def _names(text: str | None):
    return None if text is None else [v.strip() for v in text.split(",") if v.strip()]


def _overrides(items: list[str] | None) -> dict:
    """--set key=value (value parsed as JSON when it can be: numbers, lists)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"--set {item!r}: expected KEY=VALUE (e.g. elements=20)")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
    return out


# ------------------------------------------------------------------------------------------
def cmd_run(args) -> int:
    from benchmark import plots, report, runner, sweep
    from benchmark.metrics import observed_orders
    from benchmark.reference import CACHE_DIR
    from integrators import get_integrator
    from models import load_scene
    from models.diagnostics import evaluate
    from models.io import atomic_write_text

    out = Path(args.out)
    scenes = _names(args.scenes) or list(sweep.PAPER_SCENES)
    ov = _overrides(args.set)
    for s in scenes:  # validate everything before any work
        load_scene(s, **ov)
    tasks = sweep.build_tasks(scenes, _names(args.integrators), quick=args.quick, dts=_floats(args.dts),
                              rtols=_floats(args.rtols), t_end=args.t_end, overrides=ov)
    command = "python -m benchmark " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    _log(f"{len(tasks)} runs: {len(scenes)} scene(s) × {len({t.integrator for t in tasks})} integrator(s); "
         f"results -> {out}/")
    t0 = time.perf_counter()

    def write(rows) -> None:
        df = runner.to_frame(rows)
        atomic_write_text(out / "runs.csv", df.drop(columns=[c for c in ("traceback",) if c in df]).to_csv(index=False))

    runs = runner.execute(tasks, jobs=args.jobs, executor=args.executor, scheduler=args.scheduler,
                          repeats=args.repeats, cache_dir=str(out / CACHE_DIR.name), on_row=write,
                          group=lambda t: (t.scene, t.integrator))  # one worker per (scene, method): one compile
    write(runs.to_dict("records"))
    atomic_write_text(out / "runs.md", report.markdown_table(runs.drop(columns=[c for c in ("traceback", "reason") if c in runs])))
    orders = observed_orders(runs)
    atomic_write_text(out / "orders.csv", orders.to_csv(index=False))
    figures = []
    if not args.no_figures:
        for s in scenes:
            figures.append(plots.work_precision(runs, load_scene(s, **ov).name, out).name)
        # the paper's panels from the LGVI at the paper's step size
        for s in scenes:
            scene = load_scene(s, **ov)
            t_end = args.t_end or (sweep.QUICK_T_END if args.quick else scene.t_end)
            traj = get_integrator("lgvi").solve(scene, t_end=t_end, dt=PAPER_DT, save_every=0.02)
            figures.append(plots.paper_panels(scene, traj, evaluate(scene, traj), out / f"paper_{scene.name}.png").name)
            _log(f"figure: paper_{scene.name}.png ({traj.status})")
        if args.horizon > 0:
            figures.append(_horizon_study(args.horizon, out, ov, args.jobs).name)
    wall = time.perf_counter() - t0
    report.write_readme(out, runs, orders, command=command, wall_time=wall, figures=figures)
    n_bad = int((runs["status"] != "ok").sum())
    _log(f"done in {wall:.0f} s: {len(runs)} runs, {n_bad} not ok; see {out}/README.md")
    return 0


# LGVI step for the paper figures: inside its stability limit (h ω_max < 2) on all three
# scenes at N = 10 (deployment's short elements diverge at 5 ms, measured).
PAPER_DT = 0.0025

HORIZON_METHODS = (("lgvi", {"dt": 0.005}), ("rk45", {"rtol": 1e-6, "atol": 1e-8}),
                   ("tsit5", {"rtol": 1e-6, "atol": 1e-8}), ("dop853", {"rtol": 1e-8, "atol": 1e-10}))


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
    _log(f"horizon: {', '.join(name for name, _ in HORIZON_METHODS)} to t = {t_end:g} s ...")
    with worker_pool(jobs or min(len(HORIZON_METHODS), os.cpu_count() or 1)) as pool:
        futures = [pool.submit(_horizon_run, name, kw, t_end, ov) for name, kw in HORIZON_METHODS]
        for fut in futures:
            label, h = fut.result()
            histories[label] = h
            frames.append(h.assign(method=label))
    atomic_write_text(out / "energy_horizon.csv", pd.concat(frames).to_csv(index=False))
    return plots.energy_horizon(histories, scene.name, out)


# ------------------------------------------------------------------------------------------
def cmd_simulate(args) -> int:
    from integrators import get_integrator
    from models import load_scene
    from models.diagnostics import evaluate
    from models.io import atomic_write_text

    scene = load_scene(args.scene, **_overrides(args.set))
    integ = get_integrator(args.integrator)
    kw = {"t_end": args.t_end, "save_every": args.save_every}
    if args.dt is not None:
        kw["dt"] = args.dt
    if args.rtol is not None:
        kw.update(rtol=args.rtol, atol=args.atol if args.atol is not None else args.rtol * 1e-2)
    traj = integ.solve(scene, **kw)
    out = Path(args.out or f"results/simulate_{scene.name}_{integ.name}.npz")
    traj.save(out)
    df = evaluate(scene, traj)
    atomic_write_text(out.with_suffix(".csv"), df.to_csv(index=False))
    _log(f"{scene.name} / {integ.name}: status {traj.status} {traj.reason}; {len(traj.t)} saved points; "
         f"stats {json.dumps({k: v for k, v in traj.stats.items() if np.isscalar(v)}, default=str)}")
    _log(f"wrote {out} and {out.with_suffix('.csv')}")
    return 0 if traj.ok else 1


def cmd_figures(args) -> int:
    from benchmark import plots
    from integrators import Trajectory
    from models import load_scene
    from models.diagnostics import evaluate

    traj = Trajectory.load(args.trajectory)
    scene = load_scene(args.scene or traj.scene_name, **_overrides(args.set))
    out = Path(args.out or Path(args.trajectory).with_suffix(".png"))
    plots.paper_panels(scene, traj, evaluate(scene, traj), out)
    _log(f"wrote {out}")
    return 0


def cmd_check(args) -> int:
    from benchmark import check

    # how the baseline was produced, for its header (the options that change its content)
    command = check.UPDATE_COMMAND + "".join(f" --{k} {shlex.quote(v)}" for k, v in
                                             (("integrators", args.integrators), ("baseline", args.baseline)) if v)
    return check.main(update=args.update, baseline=args.baseline or check.BASELINE,
                      integrators=_names(args.integrators),
                      factor=check.DEFAULT_FACTOR if args.factor is None else args.factor,
                      order_margin=check.DEFAULT_ORDER_MARGIN if args.order_margin is None else args.order_margin,
                      jobs=args.jobs, command=command, log=_log)


def cmd_speed(args) -> int:
    from benchmark import lgvi_speed

    return lgvi_speed.main(args.rest) or 0


def cmd_stability(args) -> int:
    from benchmark import stability

    command = "python -m benchmark " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    return stability.main(_names(args.scenes), _names(args.integrators), workers=args.jobs, out=args.out,
                          command=command)


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
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmark", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="sweep scenes × integrators × settings; tables and plots into --out")
    r.add_argument("--scenes", help="comma-separated scene names or paths (default: the paper's three)")
    r.add_argument("--integrators", help="comma-separated names (default: all registered)")
    r.add_argument("--quick", action="store_true", help="reduced sweep, short horizon, a few minutes on 2 cores")
    r.add_argument("--dts", help="comma-separated step sizes for fixed-step methods")
    r.add_argument("--rtols", help="comma-separated relative tolerances for adaptive methods (atol = rtol/100)")
    r.add_argument("--t-end", type=float, help="horizon (default: each scene's t_end)")
    r.add_argument("--set", action="append", metavar="KEY=VALUE", help="scene override, e.g. elements=20")
    r.add_argument("--jobs", type=int, help="worker processes (default: CPU count)")
    r.add_argument("--repeats", type=int, default=3, help="timed repeats per run (min is reported)")
    r.add_argument("--executor", default="process", choices=["process", "serial", "dask"])
    r.add_argument("--scheduler", help="Dask scheduler address, with --executor dask")
    r.add_argument("--horizon", type=float, default=None, help="long-horizon energy study length (s); 0 = off")
    r.add_argument("--no-figures", action="store_true")
    r.add_argument("--out", default="results")
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("check", help="recompute a short sweep and compare its accuracy metrics with the committed "
                                     "baseline; exit 1 on a regression (see benchmark/check.py for the rules)")
    c.add_argument("--update", action="store_true", help="rewrite the baseline from this run instead of failing")
    c.add_argument("--baseline", help="baseline CSV (default: results/baseline/drift.csv)")
    c.add_argument("--integrators", help="comma-separated names (default: all registered except test_*)")
    c.add_argument("--factor", type=float,
                   help="a drift or error fails when worse than FACTOR x baseline, above its floor (default 2)")
    c.add_argument("--order-margin", type=float,
                   help="an observed order fails when lower than baseline - MARGIN (default 0.5)")
    c.add_argument("--jobs", type=int, help="worker processes (default: CPU count)")
    c.set_defaults(func=cmd_check)

    s = sub.add_parser("simulate", help="one scene, one integrator, one setting -> trajectory .npz + diagnostics .csv")
    s.add_argument("scene")
    s.add_argument("--integrator", default="lgvi")
    s.add_argument("--dt", type=float)
    s.add_argument("--rtol", type=float)
    s.add_argument("--atol", type=float)
    s.add_argument("--t-end", type=float)
    s.add_argument("--save-every", type=float, default=0.02)
    s.add_argument("--set", action="append", metavar="KEY=VALUE")
    s.add_argument("--out")
    s.set_defaults(func=cmd_simulate)

    f = sub.add_parser("figures", help="the paper's panels (a)-(d) from a trajectory file")
    f.add_argument("trajectory")
    f.add_argument("--scene", help="scene name or path (default: the one recorded in the file)")
    f.add_argument("--set", action="append", metavar="KEY=VALUE")
    f.add_argument("--out")
    f.set_defaults(func=cmd_figures)

    sp = sub.add_parser("speed", help="time per step of every fixed-step method and per-call cost of each right-hand "
                                       "side vs N, compile time separately (see `speed --help`)")
    sp.add_argument("rest", nargs=argparse.REMAINDER)
    sp.set_defaults(func=cmd_speed)

    st = sub.add_parser("stability", help="stability map of the hard scenes: largest stable dt (fixed step), "
                                          "step statistics (adaptive) -> results/stability/")
    st.add_argument("--scenes", help="comma-separated hard scenes (default: all seven)")
    st.add_argument("--integrators", help="comma-separated names (default: lgvi, rk45, dop853, tsit5, radau, kvaerno5)")
    st.add_argument("--jobs", type=int, default=2, help="worker processes (0: run in this process)")
    st.add_argument("--out", default="results/stability")
    st.set_defaults(func=cmd_stability)

    ls = sub.add_parser("list", help="registered integrators and shipped scenes")
    ls.set_defaults(func=cmd_list)
    return p


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["speed"]:  # its own options (see `speed --help`) pass straight through
        from benchmark import lgvi_speed

        return lgvi_speed.main(argv[1:]) or 0
    args = parser().parse_args(argv)
    if getattr(args, "horizon", 0) is None:
        args.horizon = 10.0 if args.quick else 100.0
    try:
        return args.func(args)
    except ValueError as exc:  # bad input: a clear message, no traceback
        _log(f"error: {exc}")
        return 2
