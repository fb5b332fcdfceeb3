"""Orders of the fixed-step methods across a reel reversal (s_p-dot changes sign).

    python -m benchmark.reel_reversal [--elements 5] [--t-end 0.96] [--methods lgvi,lgvi_sym,...]

Runs the hard scene ``reel_reversal`` (MODEL.md §9.7: ṡ|ṡ| in the Carnot force is only C¹
where ṡ_p = 0) with each method at halving step sizes and prints a markdown table of the
errors against DOP853 (rtol 1e-12, atol 1e-14): maximum over the compared times (every
0.08 s) of the body position |q_{N+1} − q_ref|, of |s_p − s_ref| and of |(E − W) − E0|, with
the observed orders. Also prints when ṡ_p changes sign in the reference.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.integrate import solve_ivp

from integrators import get_integrator
from models import build_model, load_scene
from models.diagnostics import evaluate
from integrators.base import Trajectory

#: step sizes per method (s): each in its asymptotic range on the smooth reel scenes, above round-off
DEFAULT_HS = {"lgvi": (0.004, 0.002, 0.001, 0.0005), "lgvi_sym": (0.004, 0.002, 0.001, 0.0005),
              "lgvi_yoshida4": (0.004, 0.002, 0.001, 0.0005), "lgvi_suzuki4": (0.008, 0.004, 0.002, 0.001),
              "tsit5": (0.016, 0.008, 0.004, 0.002)}  # constant-step Tsit5 (order 5), for comparison
COMPARE_EVERY = 0.08


def reference(scene, t_end, n_save):
    model = build_model(scene)
    lay = model.layout
    f = model.ode_rhs_jit
    sol = solve_ivp(lambda t, y: np.asarray(f(t, y)), (0.0, t_end), model.initial_ode_state(), method="DOP853",
                    rtol=1e-12, atol=1e-14, t_eval=np.linspace(0.0, t_end, n_save), dense_output=True)
    y = sol.y.T
    tr = Trajectory(t=sol.t, x=y[:, lay.y_x], attitude=y[:, lay.y_quat], attitude_kind="quaternion",
                    velocity=y[:, lay.y_w], work=y[:, lay.y_work][:, 0])
    fine = np.linspace(0.0, t_end, 20001)
    sd = sol.sol(fine)[lay.y_w][0]
    flips = fine[1:][np.diff(np.sign(sd)) != 0]
    return tr, flips


def errors(scene, tr, ref, e0):
    nod = build_model(scene).layout.nodes
    i = np.searchsorted(tr.t, ref.t - 1e-9)
    x = tr.x[i]
    ew = evaluate(scene, tr).energy_minus_work.to_numpy()
    return (float(np.linalg.norm(x[:, nod][:, -3:] - ref.x[:, nod][:, -3:], axis=1).max()),
            float(np.abs(x[:, 0] - ref.x[:, 0]).max()), float(np.max(np.abs(ew - e0))))


def table(scene, methods, hs_of, t_end):
    n_save = int(round(t_end / COMPARE_EVERY)) + 1
    ref, flips = reference(scene, t_end, n_save)
    e0 = float(evaluate(scene, ref).energy_minus_work.iloc[0])
    lines = [f"scene {scene.name}, N = {scene.string.elements}, t_end = {t_end} s; s_p-dot changes sign at t = "
             + ", ".join(f"{t:.3f}" for t in flips) + " s",
             "", "| method | h [ms] | body [m] | s_p [m] | E-W [J] | orders (body / s_p / E-W) |", "|---|---|---|---|---|---|"]
    for name in methods:
        prev = None
        for h in hs_of[name]:
            tr = get_integrator(name).solve(scene, t_end=t_end, dt=h, save_every=COMPARE_EVERY)
            if not tr.ok:
                lines.append(f"| {name} | {h * 1e3:g} | {tr.status}: {tr.reason} | | | |")
                continue
            e = errors(scene, tr, ref, e0)
            orders = " / ".join(f"{np.log2(a / b):.2f}" for a, b in zip(prev, e)) if prev else ""
            lines.append(f"| {name} | {h * 1e3:g} | {e[0]:.2e} | {e[1]:.2e} | {e[2]:.2e} | {orders} |")
            prev = e
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="reel_reversal", description=__doc__.splitlines()[0])
    ap.add_argument("--elements", type=int, default=5)
    ap.add_argument("--t-end", type=float, default=0.96)
    ap.add_argument("--methods", default=",".join(DEFAULT_HS))
    ap.add_argument("--scene", default="reel_reversal")
    a = ap.parse_args(argv)
    methods = [m for m in a.methods.split(",") if m]
    for m in methods:
        if m not in DEFAULT_HS:
            raise SystemExit(f"--methods: {m!r} has no step list (allowed: {', '.join(DEFAULT_HS)})")
    if abs(a.t_end / COMPARE_EVERY - round(a.t_end / COMPARE_EVERY)) > 1e-9:
        raise SystemExit(f"--t-end = {a.t_end} is invalid (allowed: a multiple of {COMPARE_EVERY} s)")
    print(table(load_scene(a.scene, elements=a.elements), methods, DEFAULT_HS, a.t_end))


if __name__ == "__main__":
    main()
