"""Speed: time per step of every fixed-step method, and per-call cost of each right-hand side, vs N.

    python -m benchmark speed --elements 10,40,160,640 --scenes fixed_length,deployment --steps 2000

Two tables:

1. Every registered method with `Capability.FIXED_STEP` (read from the registry, so a method
   another module registers appears here without a code change), at a constant step: compile
   time, time per step (median over repeats of the whole ``solve()`` after compilation,
   divided by the steps: the run time the benchmark reports), Newton iterations per step where
   the method reports them. The step is each scene's stable step at N = 10, times 10/N (the
   elastic frequency grows like N); a method whose run does not finish at it is retried at
   half the step (up to `MAX_HALVINGS` times) and the table says which step ran.
2. Each right-hand side of the ODE baselines (`integrators.rhs`: closed form, autodiff), per
   call from numpy through its jitted function (how scipy calls it): median µs per call.
   The autodiff one is O(N³) (dense mass matrix and solve); above ``--autodiff-max-n`` it is
   skipped.

Per method and scene: the ratio of time per step at the largest N ≤ 160 to N = 10 (the issue
#11 target: ≤ 24, linear in N would be 16) and the log-log slope over all N. Pin to one core
for the one-core figure: ``taskset -c 0 python -m benchmark speed``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from benchmark import options as opt

#: step at N = 10 per scene, scaled by 10/N: the LGVI is explicit in the elastic forces, so it
#: needs h ω_max < 2 with ω_max ∝ N (fixed_length N = 10: h < ~9 ms; deployment: h < ~2.7 ms).
DEFAULT_DT10 = {"fixed_length": 0.005, "deployment": 0.002, "retrieval": 0.004}
#: a method that does not finish at the scene's step is retried at half of it, this many times at most
MAX_HALVINGS = 3


def fixed_step_methods() -> list[str]:
    """Every registered fixed-step method (test plugins aside)."""
    from integrators import Capability, available, get_integrator

    return [n for n in available() if not n.startswith("test_") and get_integrator(n).has(Capability.FIXED_STEP)]


def measure(scene_name: str, n: int, steps: int, repeats: int, dt: float | None = None, method: str = "lgvi") -> dict:
    """Time per step of ``method`` at a constant step on ``scene_name`` with N = n."""
    from integrators import get_integrator  # JAX: only once the options are known good
    from models import load_scene

    scene = load_scene(scene_name, elements=n)
    h = dt or DEFAULT_DT10.get(scene_name, 0.002) * 10.0 / n
    integ = get_integrator(method)
    for _ in range(MAX_HALVINGS + 1):
        kw = dict(t_end=steps * h, dt=h, save_every=steps * h / 10)
        first = integ.solve(scene, **kw)  # compiles (and warms up)
        if first.ok:
            break
        h /= 2
    times = []
    tr = first
    for _ in range(repeats if first.ok else 0):
        tr = integ.solve(scene, **kw)
        times.append(tr.stats["wall_time"] / max(tr.stats["steps"], 1))
    per = statistics.median(times) if times else float("nan")
    newton = tr.stats.get("newton_iterations")
    return {"method": method, "scene": scene_name, "N": n, "dt": h, "compile_s": first.stats.get("compile_time", np.nan),
            "us_per_step": per * 1e6, "steps_per_s": 1.0 / per if per > 0 else np.nan,
            "newton_per_step": newton / max(tr.stats["steps"], 1) if newton is not None else np.nan,
            "status": tr.status}


def measure_rhs(scene_name: str, n: int, rhs: str, calls: int = 200, budget_s: float = 2.0) -> dict:
    """Median µs per call of the jitted right-hand side ``rhs`` from numpy (as scipy calls it)."""
    from integrators.rhs import rhs_jit
    from models import build_model, load_scene

    model = build_model(load_scene(scene_name, elements=n))
    y = np.asarray(model.initial_ode_state())
    f = rhs_jit(model, rhs)
    tc = time.perf_counter()
    np.asarray(f(0.0, y))
    compile_s = time.perf_counter() - tc
    times, spent = [], 0.0
    while len(times) < calls and spent < budget_s:
        t0 = time.perf_counter()
        np.asarray(f(0.0, y))
        dt = time.perf_counter() - t0
        times.append(dt)
        spent += dt
    return {"scene": scene_name, "N": n, "rhs": rhs, "compile_s": compile_s, "us_per_call": statistics.median(times) * 1e6,
            "calls": len(times)}


def _ratio(rows, key):
    by_n = {r["N"]: r[key] for r in rows if np.isfinite(r[key])}
    small = [m for m in by_n if m <= 160 and m > 10]
    if 10 not in by_n or not small:
        return np.nan, None
    big = max(small)
    return by_n[big] / by_n[10], big


def _slope(rows, key):
    pts = [(r["N"], r[key]) for r in rows if np.isfinite(r[key]) and r[key] > 0]
    if len(pts) < 2:
        return np.nan
    return float(np.polyfit(np.log([p[0] for p in pts]), np.log([p[1] for p in pts]), 1)[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmark speed", description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--elements", type=opt.positive_ints, default=[10, 40, 160, 640], help="comma-separated N values")
    ap.add_argument("--scenes", type=opt.names, default=["fixed_length", "deployment"], help="comma-separated scene names")
    ap.add_argument("--methods", type=opt.names, default=None,
                    help="comma-separated fixed-step methods (default: every registered one with the fixed_step capability)")
    ap.add_argument("--steps", type=opt.positive_int, default=2000, help="steps per timed run")
    ap.add_argument("--repeats", type=opt.positive_int, default=3, help="timed repeats (median)")
    ap.add_argument("--dt", type=opt.positive_float, default=None,
                    help="step size (default: per-scene stable step at N = 10, times 10/N)")
    ap.add_argument("--rhs", default="closed_form,autodiff", help="right-hand sides to time per call ('' = none)")
    ap.add_argument("--autodiff-max-n", type=opt.positive_int, default=160,
                    help="largest N for the O(N^3) autodiff right-hand side")
    ap.add_argument("--out", help="also write the tables (Markdown, with the command and machine) to this file")
    args = ap.parse_args(argv)
    ns, scenes = args.elements, args.scenes
    rhs_kinds = [v.strip() for v in args.rhs.split(",") if v.strip()]
    from models import load_scene

    for sc in scenes:  # every scene and N is checked (names, plausibility) before any work
        for n in ns:
            load_scene(sc, elements=n)
    if args.out:
        opt.writable_file(args.out)
    from integrators import Capability, get_integrator
    from integrators.rhs import check_rhs

    methods = args.methods or fixed_step_methods()
    for m in methods:
        if not get_integrator(m).has(Capability.FIXED_STEP):
            raise ValueError(f"--methods: {m!r} is not a fixed-step method (allowed: {', '.join(fixed_step_methods())})")
    for r in rhs_kinds:
        check_rhs(r)

    print(f"{'method':<10}{'scene':<14}{'N':>6}{'dt':>10}{'compile s':>11}{'us/step':>10}{'newton/step':>13}  status")
    md = ["| method | scene | N | dt (s) | compile (s) | µs/step | steps/s | Newton iterations/step | status |",
          "|---|---|---|---|---|---|---|---|---|"]
    summary = ["| method | scene | µs/step at N = 10 | ratio N=160 / N=10 | log-log slope |", "|---|---|---|---|---|"]
    for method in methods:
        for sc in scenes:
            rows = []
            for n in ns:
                r = measure(sc, n, args.steps, args.repeats, args.dt, method)
                rows.append(r)
                print(f"{method:<10}{sc:<14}{n:>6}{r['dt']:>10.3g}{r['compile_s']:>11.2f}{r['us_per_step']:>10.2f}"
                      f"{r['newton_per_step']:>13.2f}  {r['status']}", flush=True)
                md.append(f"| {method} | {sc} | {n} | {r['dt']:.3g} | {r['compile_s']:.2f} | {r['us_per_step']:.2f} "
                          f"| {r['steps_per_s']:.0f} | {r['newton_per_step']:.2f} | {r['status']} |")
            ratio, big = _ratio(rows, "us_per_step")
            slope = _slope(rows, "us_per_step")
            at10 = next((r["us_per_step"] for r in rows if r["N"] == 10), np.nan)
            print(f"{method:<10}{sc:<14} ratio N={big}/N=10: {ratio:.1f}; log-log slope: {slope:.2f}")
            summary.append(f"| {method} | {sc} | {at10:.2f} | {ratio:.1f} (N = {big}) | {slope:.2f} |")
    rhs_md = ["| scene | N | right-hand side | compile (s) | µs/call | calls |", "|---|---|---|---|---|---|"]
    for sc in scenes if rhs_kinds else []:
        for rhs in rhs_kinds:
            for n in ns:
                if rhs == "autodiff" and n > args.autodiff_max_n:
                    rhs_md.append(f"| {sc} | {n} | {rhs} | | skipped (O(N³), N > --autodiff-max-n {args.autodiff_max_n}) | |")
                    continue
                r = measure_rhs(sc, n, rhs)
                print(f"rhs {rhs:<12}{sc:<14}{n:>6}  compile {r['compile_s']:.2f} s  {r['us_per_call']:.1f} us/call", flush=True)
                rhs_md.append(f"| {sc} | {n} | {rhs} | {r['compile_s']:.2f} | {r['us_per_call']:.1f} | {r['calls']} |")
    if args.out:
        import shlex

        from benchmark.report import environment, utc_now
        from models.io import atomic_write_text

        command = "python -m benchmark speed " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
        text = (f"# Speed of the fixed-step methods and of the right-hand sides\n\nGenerated by `{command.strip()}` on "
                f"{utc_now()}.\n{environment()}\n\n"
                "Time per step: the whole `solve()` after compilation (output conversion included), divided by the "
                "steps, median of repeats; compile time apart.\n\n"
                + "\n".join(md) + "\n\n## Scaling with N\n\n" + "\n".join(summary)
                + "\n\n## Right-hand side per call (jitted, called from numpy)\n\n" + "\n".join(rhs_md) + "\n")
        atomic_write_text(Path(args.out), text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
