"""The flop rule checked against compiled floors: does the work column charge methods in the
proportion their compiled steps take time?

For each element count N and each of the LGVI, ``lie_rk4`` (RK4), Tsit5 and Dopri8 at one
constant step h (the same for all), this measures

* the flops of one step by the project's rule (`benchmark.work.flops`: the whole compiled step,
  the LGVI's Newton loop at the iterations it took at h), and, for contrast, what the earlier
  rule charged (right-hand-side evaluations × one isolated compiled right-hand side);
* the time of one step of the *floor* of the same work: numba implementations of the same
  equations outside this repository (a directory given with ``--floor``, e.g.
  ../shared/floor: ``lgvi_nb2`` for the LGVI step, ``rhs_nb.erk_run`` for the explicit
  Runge–Kutta steps with the classical RK4 tableau and diffrax's Tsit5 and Dopri8 tableaux),
  timed interleaved (every repeat times every method once, the least time of the repeats
  counts), on whatever core the command is pinned to;

* the floors' *own* flops per step, counted exactly by running their source on counting
  scalars (`benchmark.work.opcount`), and their rate in GFlop/s;

and, for every pair of methods, the agreement factor (flops ratio) / (floor time ratio), which
the rule must keep within [1/1.5, 1.5] (`TOLERANCE`). The floors' own count is the control: a
pair it misses is one where the floors' time per flop differs by more than the tolerance, which
no count of the same arithmetic can follow. Floor times on a loaded machine are noisy:
pin one core (``taskset -c 0``) and re-run on a quiet one; the load is written with the table.

    taskset -c 0 python -m benchmark work-rule --floor DIR

(the command line's `work-rule`, which writes results/work_rule.md).

The LGVI floor is the fixed-length step with a rigid body, so the scene is ``fixed_length``.
``lie_rk4``'s floor is a classical RK4 on the quaternion ODE state (the same four evaluations
and stage arithmetic; the Lie group update of its attitude is a few dozen flops of the step).
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pandas as pd  # imported where a table is made: `--help` of the command line stays light

#: The agreement the rule must reach: flops ratio / floor time ratio within [1/1.5, 1.5].
TOLERANCE = 1.5
METHODS = ("lgvi", "lie_rk4", "tsit5", "dopri8")
SCENE = "fixed_length"
#: Right-hand-side evaluations per step at a constant step (the earlier rule's count).
EVALS_PER_STEP = {"lie_rk4": 4, "tsit5": 6, "dopri8": 13}
#: The floors' modules, in the directory given with --floor.
FLOORS = ("lgvi_nb", "lgvi_nb2", "rhs_nb")
#: The command's defaults: element counts, steps per timed floor run at N = 10 (fewer in
#: proportion above), interleaved repeats; and the fewest steps a timed run may take.
ELEMENTS, STEPS, REPEATS, MIN_STEPS = (10, 40, 160), 20000, 11, 10


def floor_dir(text: str) -> Path:
    """The directory of the floors (--floor), or ValueError naming what is missing there."""
    path = Path(text)
    missing = [f"{m}.py" for m in FLOORS if not (path / f"{m}.py").is_file()]
    if missing:
        raise ValueError(f"{text!r}: no {', '.join(missing)} there (allowed: the directory of the numba floors)")
    return path


def check_steps(steps: int) -> None:
    if steps < MIN_STEPS:
        raise ValueError(f"{steps} is invalid (allowed: an integer >= {MIN_STEPS}, e.g. {STEPS})")


def step_size(n: int) -> float:
    """The constant step at N elements: 0.25 ms at N = 10, shorter in proportion above (the
    explicit methods' stability limit falls with the element length)."""
    return 2.5e-4 * (10.0 / n if n > 10 else 1.0)


def rule_flops(n: int, h: float, steps: int = 200) -> dict[str, dict[str, float]]:
    """method -> {"flops": per step by the rule, "old_flops": by evaluations × one right-hand side,
    "newton": mean Newton iterations per step (LGVI, over ``steps`` steps: as many as its floor
    takes, whose iterations per step drift with the motion)}."""
    from reelbench.benchmark.work import flops
    from reelbench.integrators import get_integrator
    from reelbench.integrators.rhs import DEFAULT_RHS
    from reelbench.models import build_model, load_scene

    scene = load_scene(SCENE, elements=n)
    model = build_model(scene)
    one_rhs = flops.rhs_flops(model, DEFAULT_RHS)
    out = {}
    tr = get_integrator("lgvi").solve(scene, t_end=steps * h, dt=h, save_every=steps * h)
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
    lgvi_nb, lgvi_nb2, rhs_nb = (_import_from(floor, name) for name in ("lgvi_nb", "lgvi_nb2", "rhs_nb"))

    from reelbench.models import build_model, load_scene
    from reelbench.models.closed_form import ClosedFormEOM

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


def floor_flops(floor: Path, n: int, h: float, newton: float) -> dict[str, dict[str, float]]:
    """method -> {"flops": the floor's own flops per step, "div", "sqrt": its divisions and square
    roots}, counted exactly by running the floors' source on counting scalars (`benchmark.work.opcount`):
    the right-hand-side floors' steps as the difference of 3 and 1 steps over 2 (the start's
    evaluation left out), the LGVI floor's step as its Newton-free part + ``newton`` (its measured
    mean iterations per step) × one Newton iteration. Each counted run must end where the compiled
    kernel ends from the same start (to 1e-12), else it did not execute the same operations."""
    from reelbench.benchmark.work.opcount import Counted, OpCounter, counted, counted_array, load_plain
    from reelbench.models import build_model, load_scene
    from reelbench.models.closed_form import ClosedFormEOM

    plain = load_plain(floor, ("lgvi_nb", "lgvi_nb2", "rhs_nb"))
    rhs_nb, lgvi_nb, lgvi_nb2 = plain["rhs_nb"], plain["lgvi_nb"], plain["lgvi_nb2"]
    model = build_model(load_scene(SCENE, elements=n))
    y0 = np.asarray(model.initial_ode_state(), float)

    def count(fn) -> OpCounter:
        with OpCounter(plain.values()) as ops:
            fn()
        return ops

    def per_step(a: OpCounter, b: OpCounter, steps: float) -> dict:
        """What run ``b`` counted beyond run ``a``, per step."""
        return {"flops": (b.flops - a.flops) / steps, **{k: (b.counts[k] - a.counts[k]) / steps for k in ("div", "sqrt")}}

    compiled = {name: _import_from(floor, name) for name in plain}  # the numba kernels, to compare with

    def same_end(what: str, counted_values, compiled_values) -> None:
        got = np.vectorize(float, otypes=[float])(counted_values)
        want = np.asarray(compiled_values, float)
        if not np.allclose(got, want, rtol=1e-12, atol=1e-12):
            raise RuntimeError(f"the counted run of the {what} floor at N = {n} ends "
                               f"{np.max(np.abs(got - want)):.3g} away from the compiled one's: not the same operations")

    out, packed = {}, compiled["rhs_nb"].Params(model).pack()
    P = counted(packed)  # the same parameters, as counting scalars
    for name, (A, b, fsal) in _tableaux().items():
        def erk(k, A=A, b=b, fsal=fsal):
            end = {}
            ops = count(lambda: end.update(y=rhs_nb.erk_run(counted_array(A), counted_array(b), fsal,
                                                            counted_array(y0), Counted(h), k, *P)[0]))
            return ops, end["y"]
        (one, _), (three, y3) = erk(1), erk(3)
        same_end(name, y3, compiled["rhs_nb"].erk_run(A, b, fsal, y0, h, 3, *packed)[0])
        out[name] = per_step(one, three, 2.0)

    x0, R0, w0 = (np.asarray(v, float) for v in model.initial_state())
    p0 = np.asarray(ClosedFormEOM(model).momentum(x0, R0, w0))
    sc, rho, J_o, J_d = lgvi_nb.Params(model).pack()

    def lgvi(steps, tol=1e-12, maxit=20):
        q, pq = counted_array(x0.reshape(n, 3)), counted_array(p0[: 3 * n].reshape(n, 3))
        Pi, R = counted_array(p0[3 * n: 3 * n + 3]), counted_array(R0)
        saved = [counted_array(np.zeros(s)) for s in ((1, n, 3), (1, 3, 3), (1, n + 1, 3))]
        result = {}
        ops = count(lambda: result.update(its=lgvi_nb2.run(steps, steps, q, R, pq, Pi, *counted((sc, rho, J_o, J_d)),
                                                           Counted(h), Counted(tol), maxit, *saved)[0]))
        return ops, result["its"], q

    # one Newton iteration: a step forced to take 1, then 2 (a negative tolerance never converges)
    one_it, _, _ = lgvi(1, tol=-1.0, maxit=1)
    two_its, _, _ = lgvi(1, tol=-1.0, maxit=2)
    iteration = per_step(one_it, two_its, 1.0)
    (first, its1, _), (second, its2, q2) = lgvi(1), lgvi(2)
    q = x0.reshape(n, 3).copy()
    compiled["lgvi_nb2"].run(2, 2, q, R0.copy(), p0[: 3 * n].reshape(n, 3).copy(), p0[3 * n: 3 * n + 3].copy(),
                             sc, rho, J_o, J_d, h, 1e-12, 20, np.zeros((1, n, 3)), np.zeros((1, 3, 3)),
                             np.zeros((1, n + 1, 3)))
    same_end("lgvi", q2, q)
    second_step = per_step(first, second, 1.0)  # its Newton-free part + its own iterations
    out["lgvi"] = {k: second_step[k] + (newton - (its2 - its1)) * iteration[k] for k in second_step}
    return out


def _import_from(directory: Path, name: str):
    """The module ``name`` from ``directory`` (the floors: measuring tools outside the project)."""
    import importlib

    if str(directory) not in sys.path:
        sys.path.insert(0, str(directory))
    return importlib.import_module(name)


def _within(agreement: float) -> bool:
    return 1 / TOLERANCE <= agreement <= TOLERANCE


#: Livermore's normalised operation count (McMahon's Livermore Fortran Kernels): a division or
#: square root counts 4 flops. Shown for the floors to test whether weighting slow operations
#: brings their flops in line with their times.
NORMALISED_EXTRA = 3.0

#: The counts compared with the floors' times, as the table names them.
COUNT_LABELS = {
    "lowered": "lowered program",
    "compiled": "compiled program",
    "old": "the earlier rule (evaluations × one isolated right-hand side)",
    "floor": "the floors' own flops (counted exactly)",
    "floor_normalised": "the floors' own flops, ÷ and √ as 4 (Livermore's normalisation)",
}


def measure(floor: Path, elements=(10, 160), steps: int = STEPS, repeats: int = 5) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per-method table, per-pair table) for each N in ``elements``: the rule's flops with
    each program count (`benchmark.work.flops.PROGRAM_COUNTS`, the runs table's first), the
    earlier rule's and the floors' own, against the floors' times."""
    import pandas as pd

    from reelbench.benchmark.work import flops

    rows, pairs = [], []
    used = flops.PROGRAM_COUNT
    programs = (used, *[c for c in flops.PROGRAM_COUNTS if c != used])
    for n in elements:
        h = step_size(n)
        run_steps = max(200, steps * 10 // n)  # about as long a run at every N
        fe = floor_times(floor, n, h, run_steps, repeats)
        fl = {}
        try:
            for c in programs:
                flops.use_program_count(c)
                fl[c] = rule_flops(n, h, run_steps)
        finally:
            flops.use_program_count(used)
        own = floor_flops(floor, n, h, fe["lgvi"]["newton"])
        counts = {m: {**{c: fl[c][m]["flops"] for c in programs}, "old": fl[used][m]["old_flops"],
                      "floor": own[m]["flops"],
                      "floor_normalised": own[m]["flops"] + NORMALISED_EXTRA * (own[m]["div"] + own[m]["sqrt"])}
                  for m in METHODS}
        for m in METHODS:
            rows.append({"N": n, "h": h, "method": m, **{f"flops_{c}": counts[m][c] for c in programs},
                         "old_flops": counts[m]["old"], "floor_flops": counts[m]["floor"],
                         f"{used}_per_floor_flop": counts[m][used] / counts[m]["floor"],
                         "floor_us": fe[m]["us"], "floor_gflop_s": counts[m]["floor"] / fe[m]["us"] / 1e3,
                         "newton_project": fl[used][m]["newton"], "newton_floor": fe[m]["newton"]})
        for a, b in itertools.combinations(METHODS, 2):
            time_ratio = fe[b]["us"] / fe[a]["us"]
            row = {"N": n, "pair": f"{b} / {a}", "floor_time_ratio": time_ratio}
            for label in (*programs, "old", "floor", "floor_normalised"):
                ratio = counts[b][label] / counts[a][label]
                row.update({f"ratio_{label}": ratio, f"agreement_{label}": ratio / time_ratio,
                            f"within_{label}": _within(ratio / time_ratio)})
            # the rule's agreement = (its ratio / the floors' flop ratio) × (the floors' own agreement):
            # how differently the project's programs and the floors compute the pair, times the rate
            row[f"{used}_over_floor_flops"] = row[f"ratio_{used}"] / row["ratio_floor"]
            pairs.append(row)
    return pd.DataFrame(rows), pd.DataFrame(pairs)


def markdown(methods: pd.DataFrame, pairs: pd.DataFrame, *, load: str, command: str) -> str:
    from reelbench.benchmark.work import flops
    from reelbench.benchmark.core.report import markdown_table

    labels = [c[len("within_"):] for c in pairs if c.startswith("within_")]
    passed = {c: int(pairs[f"within_{c}"].sum()) for c in labels}
    counted = "; ".join(f"{COUNT_LABELS.get(c, c)}: **{passed[c]} of {len(pairs)}**" for c in labels)

    def fmt(df):
        return df.assign(**{c: df[c].map(lambda v: f"{v:.4g}") for c in df
                            if df[c].dtype.kind == "f" and c not in ("N",)})

    # the pairs as agreements, each marked within (✓) or not (✗) the tolerance
    shown = pairs[["N", "pair", "floor_time_ratio"]].assign(
        floor_time_ratio=pairs["floor_time_ratio"].map(lambda v: f"{v:.3g}"),
        **{f"{c}": [f"{a:.3g} {'✓' if w else '✗'}" for a, w in zip(pairs[f"agreement_{c}"], pairs[f"within_{c}"])]
           for c in labels})
    used_over = f"{flops.PROGRAM_COUNT}_over_floor_flops"
    finding = ""
    if "floor" in labels and "floor_gflop_s" in methods and used_over in pairs:
        shown[used_over] = [f"{v:.3g} {'✓' if _within(v) else '✗'}" for v in pairs[used_over]]
        rate, per_flop = methods["floor_gflop_s"], methods[f"{flops.PROGRAM_COUNT}_per_floor_flop"]
        worst = pairs.loc[(np.log(pairs["agreement_floor"])).abs().idxmax()]
        misses = ~pairs[f"within_{flops.PROGRAM_COUNT}"]
        both = int((misses & ~pairs["within_floor"]).sum())
        finding = f"""
**What the floors' own arithmetic says.** Counted exactly (`benchmark.work.opcount`: the floors' source
run on counting scalars, every operation the compiled kernel executes counted once), the floors
run at {rate.min():.2g}–{rate.max():.2g} GFlop/s (`floor_gflop_s`), so their own flop ratios keep
{passed["floor"]} of {len(pairs)} pairs within the tolerance (the farthest: {worst["pair"]} at N = {worst["N"]},
{worst["agreement_floor"]:.3g}); counting ÷ and √ as 4 flops, {passed.get("floor_normalised", "—")} of {len(pairs)}. A pair that the floors'
own count misses cannot be met by any count of the same arithmetic: there the tolerance tests the
processor's rate per kind of operation, not the count.

**Where the rule's misses come from.** A pair's agreement is the product of two factors: the
floors' own agreement (above) and `{used_over}`, the project's flop ratio over the floors' flop
ratio for the same pair, i.e. how differently the project's programs and the floors apportion the
arithmetic. Of the {flops.PROGRAM_COUNT} count's {int(misses.sum())} misses, {both} are pairs the floors' own count
misses too; per method the project's step counts {per_flop.min():.2g}–{per_flop.max():.2g}× the floor's flops
(`{flops.PROGRAM_COUNT}_per_floor_flop`): what the project's program computes for the step beyond, or short
of, the floor's.
"""
    return f"""# The flop rule against compiled floors

Generated by `{command}`; machine load when it ran: `{load}`. Floor times on a loaded machine are
noisy (their ratios less so: the repeats are interleaved and the least of them counts): re-run on a
quiet machine before quoting a figure.

The rule (`benchmark/work/flops.py`): flops of a run = its attempted steps × XLA's count of the method's
whole compiled step, loops at their trip counts (the LGVI's Newton loop at its measured iterations,
diffrax's stage loop at its stages), counting the {flops.PROGRAM_COUNT} program in runs.csv
(`benchmark.work.flops.PROGRAM_COUNT`; both are shown here). The floors: numba implementations of the
same steps (the LGVI's chord Newton, explicit Runge–Kutta with the methods' tableaux) on one core.
For every pair of methods the agreement (flops ratio / floor time ratio) should lie within
[1/{TOLERANCE:g}, {TOLERANCE:g}]. Pairs within it: {counted}.
{finding}
## Per method (one constant step h, the same for all; flops and µs per step)

{markdown_table(fmt(methods))}

## Per pair: agreement (flops ratio / floor time ratio), ✓ within [1/{TOLERANCE:g}, {TOLERANCE:g}]

{markdown_table(shown)}
"""


def report(floor: Path, elements=ELEMENTS, steps: int = STEPS, repeats: int = REPEATS, *, command: str) -> str:
    """Measure (`measure`) and return the Markdown table, headed by ``command`` with the cores it
    was pinned to and the machine's load when it started."""
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    methods, pairs = measure(Path(floor).resolve(), tuple(elements), steps, repeats)
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    return markdown(methods, pairs, load=load, command=command + (f" (pinned to cores {cpus})" if cpus else ""))
