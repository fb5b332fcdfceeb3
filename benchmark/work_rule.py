"""The flop rule checked against compiled floors: does the work column charge methods in the
proportion their compiled steps take time?

For each element count N and each of the LGVI, ``lie_rk4`` (RK4), Tsit5 and Dopri8 at one
constant step h (the same for all), this measures

* the flops of one step by the project's rule (`benchmark.flops`: the whole compiled step,
  the LGVI's Newton loop at the iterations it took at h), and, for contrast, what the earlier
  rule charged (right-hand-side evaluations × one isolated compiled right-hand side);
* the time of one step of the *floor* of the same work: numba implementations of the same
  equations outside this repository (a directory given with ``--floor``, e.g.
  ../shared/floor: ``lgvi_nb2`` for the LGVI step, ``rhs_nb.erk_run`` for the explicit
  Runge–Kutta steps with the classical RK4 tableau and diffrax's Tsit5 and Dopri8 tableaux),
  timed interleaved (every repeat times every method once, the least time of the repeats
  counts), on whatever core the command is pinned to;

and, for every pair of methods, the agreement factor (flops ratio) / (floor time ratio), which
the rule must keep within [1/1.5, 1.5] (`TOLERANCE`). Floor times on a loaded machine are noisy:
pin one core (``taskset -c 0``) and re-run on a quiet one; the load is written with the table.

    PYTHONPATH=. taskset -c 0 python -m benchmark.work_rule --floor ../shared/floor --out results/work_rule.md

The LGVI floor is the fixed-length step with a rigid body, so the scene is ``fixed_length``.
``lie_rk4``'s floor is a classical RK4 on the quaternion ODE state (the same four evaluations
and stage arithmetic; the Lie group update of its attitude is a few dozen flops of the step).
"""

from __future__ import annotations

import argparse
import itertools
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

#: The agreement the rule must reach: flops ratio / floor time ratio within [1/1.5, 1.5].
TOLERANCE = 1.5
METHODS = ("lgvi", "lie_rk4", "tsit5", "dopri8")
SCENE = "fixed_length"
#: Right-hand-side evaluations per step at a constant step (the earlier rule's count).
EVALS_PER_STEP = {"lie_rk4": 4, "tsit5": 6, "dopri8": 13}


def step_size(n: int) -> float:
    """The constant step at N elements: 0.25 ms at N = 10, shorter in proportion above (the
    explicit methods' stability limit falls with the element length)."""
    return 2.5e-4 * (10.0 / n if n > 10 else 1.0)


def rule_flops(n: int, h: float) -> dict[str, dict[str, float]]:
    """method -> {"flops": per step by the rule, "old_flops": by evaluations × one right-hand side,
    "newton": mean Newton iterations per step (LGVI)}."""
    from benchmark import flops
    from integrators import get_integrator
    from integrators.rhs import DEFAULT_RHS
    from models import build_model, load_scene

    scene = load_scene(SCENE, elements=n)
    model = build_model(scene)
    one_rhs = flops.rhs_flops(model, DEFAULT_RHS)
    out = {}
    tr = get_integrator("lgvi").solve(scene, t_end=200 * h, dt=h, save_every=200 * h)
    per_step, _ = flops.run_flops("lgvi", model, tr.stats, None)
    newton = tr.stats["newton_iterations"] / tr.stats["steps"]
    out["lgvi"] = {"flops": per_step / tr.stats["steps"], "old_flops": per_step / tr.stats["steps"], "newton": newton}
    out["lie_rk4"] = {"flops": flops.step_cost("lie_rk4", model, DEFAULT_RHS)[0]}
    for name in ("tsit5", "dopri8"):
        out[name] = {"flops": flops.diffrax_step_cost(name, model, DEFAULT_RHS, False)}
    for name, k in EVALS_PER_STEP.items():
        out[name].update(old_flops=k * one_rhs, newton=np.nan)
    return out


def _tableaux():
    """(A, b, fsal) of the explicit methods' floors: classical RK4, diffrax's Tsit5 and Dopri8."""
    import diffrax as dfx

    def of(solver):
        t = solver.tableau
        s = len(t.a_lower) + 1
        A = np.zeros((s, s))
        for i, row in enumerate(t.a_lower):
            A[i + 1, : len(row)] = np.asarray(row)
        return A, np.asarray(t.b_sol, float), bool(getattr(t, "fsal", False))

    rk4 = (np.array([[0, 0, 0, 0], [0.5, 0, 0, 0], [0, 0.5, 0, 0], [0, 0, 1.0, 0]]),
           np.array([1, 2, 2, 1]) / 6.0, False)
    return {"lie_rk4": rk4, "tsit5": of(dfx.Tsit5()), "dopri8": of(dfx.Dopri8())}


def floor_times(floor: Path, n: int, h: float, steps: int, repeats: int) -> dict[str, dict[str, float]]:
    """method -> {"us": least µs per step of the floor over ``repeats`` interleaved repeats,
    "newton": the LGVI floor's Newton iterations per step}."""
    sys.path.insert(0, str(floor))
    import lgvi_nb  # noqa: E402  (measuring tools outside the project)
    import lgvi_nb2
    import rhs_nb

    from models import build_model, load_scene
    from models.closed_form import ClosedFormEOM

    model = build_model(load_scene(SCENE, elements=n))
    x0, R0, w0 = (np.asarray(v, float) for v in model.initial_state())
    p0 = np.asarray(ClosedFormEOM(model).momentum(x0, R0, w0))
    sc, rho, J_o, J_d = lgvi_nb.Params(model).pack()
    P = rhs_nb.Params(model).pack()
    y0 = np.asarray(model.initial_ode_state(), float)
    tableaux = _tableaux()
    newton = []

    def lgvi():
        q = x0.reshape(n, 3).copy(); pq = p0[: 3 * n].reshape(n, 3).copy()
        Pi = p0[3 * n: 3 * n + 3].copy(); R = R0.copy()
        Qo, Ro, Po = np.zeros((10, n, 3)), np.zeros((10, 3, 3)), np.zeros((10, n + 1, 3))
        t0 = time.perf_counter()
        its, code, k = lgvi_nb2.run(steps, steps // 10, q, R, pq, Pi, sc, rho, J_o, J_d, h, 1e-12, 20, Qo, Ro, Po)
        dt = time.perf_counter() - t0
        if code != 0 or k != steps:
            raise RuntimeError(f"the LGVI floor stopped (code {code}) at step {k} of {steps}")
        newton.append(its / steps)
        return dt / steps

    def erk(name):
        A, b, fsal = tableaux[name]

        def run():
            t0 = time.perf_counter()
            rhs_nb.erk_run(A, b, fsal, y0, h, steps, *P)
            return (time.perf_counter() - t0) / steps
        return run

    timers = {"lgvi": lgvi, **{m: erk(m) for m in ("lie_rk4", "tsit5", "dopri8")}}
    for f in timers.values():  # compile and warm up
        f()
    samples = {m: [] for m in timers}
    for _ in range(repeats):  # interleaved: the load moves every method alike
        for m, f in timers.items():
            samples[m].append(f())
    return {m: {"us": 1e6 * min(v), "newton": (float(np.median(newton)) if m == "lgvi" else np.nan)}
            for m, v in samples.items()}


def _within(agreement: float) -> bool:
    return 1 / TOLERANCE <= agreement <= TOLERANCE


def measure(floor: Path, elements=(10, 160), steps: int = 20000, repeats: int = 5) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per-method table, per-pair table) for each N in ``elements``: the rule's flops with
    each program count (`benchmark.flops.PROGRAM_COUNTS`, the runs table's first) and the
    earlier rule's, against the floors' times."""
    from benchmark import flops

    rows, pairs = [], []
    used = flops.PROGRAM_COUNT
    counts = (used, *[c for c in flops.PROGRAM_COUNTS if c != used])
    for n in elements:
        h = step_size(n)
        fe = floor_times(floor, n, h, max(200, steps * 10 // n), repeats)  # about as long a run at every N
        fl = {}
        try:
            for c in counts:
                flops.use_program_count(c)
                fl[c] = rule_flops(n, h)
        finally:
            flops.use_program_count(used)
        for m in METHODS:
            rows.append({"N": n, "h": h, "method": m, **{f"flops_{c}": fl[c][m]["flops"] for c in counts},
                         "old_flops": fl[used][m]["old_flops"], "floor_us": fe[m]["us"],
                         "newton_project": fl[used][m]["newton"], "newton_floor": fe[m]["newton"]})
        for a, b in itertools.combinations(METHODS, 2):
            time_ratio = fe[b]["us"] / fe[a]["us"]
            row = {"N": n, "pair": f"{b} / {a}", "floor_time_ratio": time_ratio}
            for c, key in [(c, "flops") for c in counts] + [(used, "old_flops")]:
                label = c if key == "flops" else "old"
                ratio = fl[c][b][key] / fl[c][a][key]
                row.update({f"ratio_{label}": ratio, f"agreement_{label}": ratio / time_ratio,
                            f"within_{label}": _within(ratio / time_ratio)})
            pairs.append(row)
    return pd.DataFrame(rows), pd.DataFrame(pairs)


def markdown(methods: pd.DataFrame, pairs: pd.DataFrame, *, load: str, command: str) -> str:
    from benchmark import flops
    from benchmark.report import markdown_table

    labels = [c[len("within_"):] for c in pairs if c.startswith("within_")]
    passed = {c: int(pairs[f"within_{c}"].sum()) for c in labels}
    counted = "; ".join(f"{'the earlier rule (evaluations × one isolated right-hand side)' if c == 'old' else c + ' program'}"
                        f": **{passed[c]} of {len(pairs)}**" for c in labels)

    def fmt(df):
        return df.assign(**{c: df[c].map(lambda v: f"{v:.4g}") for c in df
                            if df[c].dtype.kind == "f" and c not in ("N",)})

    return f"""# The flop rule against compiled floors

Generated by `{command}`; machine load when it ran: `{load}`. Floor times on a loaded machine are
noisy (their ratios less so: the repeats are interleaved and the least of them counts): re-run on a
quiet machine before quoting a figure.

The rule (`benchmark/flops.py`): flops of a run = its attempted steps × XLA's count of the method's
whole compiled step, loops at their trip counts (the LGVI's Newton loop at its measured iterations,
diffrax's stage loop at its stages), counting the {flops.PROGRAM_COUNT} program in runs.csv
(`benchmark.flops.PROGRAM_COUNT`; both are shown here). The floors: numba implementations of the
same steps (the LGVI's chord Newton, explicit Runge–Kutta with the methods' tableaux) on one core.
For every pair of methods the agreement (flops ratio / floor time ratio) should lie within
[1/{TOLERANCE:g}, {TOLERANCE:g}]. Pairs within it: {counted}.

## Per method (one constant step h, the same for all; flops and µs per step)

{markdown_table(fmt(methods))}

## Per pair

{markdown_table(fmt(pairs))}
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmark.work_rule", description=__doc__.split("\n\n")[0])
    ap.add_argument("--floor", required=True, type=Path, help="directory of the numba floors (lgvi_nb, lgvi_nb2, rhs_nb)")
    ap.add_argument("--elements", default="10,40,160", help="comma-separated element counts (default: 10,40,160)")
    ap.add_argument("--steps", type=int, default=20000, help="steps per timed floor run at N = 10, fewer in "
                    "proportion above (default: 20000)")
    ap.add_argument("--repeats", type=int, default=11, help="interleaved repeats (default: 11)")
    ap.add_argument("--out", type=Path, default=None, help="write the Markdown table here (default: print it)")
    a = ap.parse_args(argv)
    missing = [f for f in ("lgvi_nb.py", "lgvi_nb2.py", "rhs_nb.py") if not (a.floor / f).is_file()]
    if missing:
        print(f"error: --floor {a.floor}: no {', '.join(missing)} there (allowed: the directory of the numba floors)",
              file=sys.stderr)
        return 2
    try:
        elements = tuple(int(v) for v in a.elements.split(","))
        if any(n < 2 for n in elements):
            raise ValueError
    except ValueError:
        print(f"error: --elements {a.elements!r} is invalid (allowed: comma-separated integers >= 2)", file=sys.stderr)
        return 2
    if a.steps < 10 or a.repeats < 1:
        print("error: --steps must be >= 10 and --repeats >= 1", file=sys.stderr)
        return 2
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    methods, pairs = measure(a.floor.resolve(), elements, a.steps, a.repeats)
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    command = ("python -m benchmark.work_rule " + " ".join(argv if argv is not None else sys.argv[1:])
               + (f" (pinned to cores {cpus})" if cpus else ""))
    text = markdown(methods, pairs, load=load, command=command)
    if a.out:
        from models.io import atomic_write_text

        atomic_write_text(a.out, text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
