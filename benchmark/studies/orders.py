"""The observed orders of convergence, measured where they are defined: `orders.csv`.

    python -m benchmark orders [--scenes fixed_length,...] [--integrators lgvi,...] [--max-steps N] [--out results]

Each fixed-step method (`Capability.FIXED_STEP`: the LGVI family, RATTLE, the Lie group
Runge–Kutta methods and the compiled baselines at constant step) runs a short horizon
(`T_END`, a quarter of the sweep's: at 1.28 s Tsit5's slope is still 5.33 at the last halving
above the floor) of each scene (`SCENES`) at `HALVINGS` + 1 step sizes, each half the one before, from a
coarsest step set by the order it declares for the scene's situation (`coarsest_step`). The
string is short (`ELEMENTS`): its fastest axial mode is then slow enough for an eighth-order
method to reach its asymptotic range above round-off (at N = 10, dopri8's error falls below
1e-13 before its slope settles). A run's error is the largest |x − x_ref| over the saved times
(x: s_p and every node, `Trajectory.x`).

The reference is the eighth-order `REFERENCE_METHOD` at a step 4× below the finest run's; its
own error is bounded by its distance to the same method at twice its step (`reference_error`),
and the independent DOP853 at rtol 1e-13 is compared with it too (column
``reference_check``). A run's error counts only when it is at least `FLOOR_FACTOR` times the
reference's bound, so every counted run is ≥ 100× less accurate than the reference. The order
is the slope of the last halving whose two errors count; the halving before it says whether the
error has settled (two slopes within `ASYMPTOTIC_SPREAD`: column ``asymptotic``). Over the 10 s
chaotic horizons of the sweep, with two or three points, such slopes are not orders (they gave
dopri8 21.8): the sweep's table is not used for orders any more.

As a study on the one runner (`study`, `benchmark.core.study.run`) one job is one method's ladder
on one scene (the jobs of a method in one worker: one compile; each worker computes a scene's
reference once). Its runs go to ``orders_errors.csv`` as the job finishes, in place of that
ladder's earlier runs (the other ladders are kept); ``orders.csv`` (`summarise`) and the echoed
section (`section`) are written from the whole table, also when stopped. A rerun computes only
the ladders the table lacks from the same code and settings (`key`); ``--fresh`` all of them.
A ladder whose worker died is one row with its status ("crashed") and reason. Each run of a
ladder is bounded by the job's budget (`benchmark.studies.budget`: --max-steps, --time-limit); a
run past it is a ladder row with status max_steps / time_limit, and the ladder's key holds a
budget other than the defaults.

Methods that only adapt their step (scipy's RK45, DOP853, Radau; Kvaerno5) have no order in h
and no constant-step mode: they are not in the table (their declared order is their tableau's).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from reelbench.benchmark.core.order import successive_orders
from reelbench.benchmark.core.policy import ORDERS_CHECK_METHOD, ORDERS_REFERENCE_DT, ORDERS_REFERENCE_METHOD, Setting
from reelbench.benchmark.studies import budget as _budget

#: One scene per situation (`integrators.base.SITUATIONS`): fixed length, and the reel retrieving.
#: Deployment is left out by default: it starts with 3 m deployed, two 1.5 m elements with an
#: 84 rad/s axial mode, so the coarse steps do not finish and dopri8's slope is still 8.5 at the
#: last halving above the floor (its asymptotic range lies below round-off); `--scenes deployment`
#: measures it all the same, and the rows say so.
SCENES = ("fixed_length", "retrieval")
#: Horizon (s) and interval between compared times: every step of every ladder divides both.
T_END, SAVE_EVERY = 2.56, 0.16
#: Elements of the string (see the module's docstring).
ELEMENTS = 2
#: Halvings of the step: HALVINGS + 1 runs per method and scene.
HALVINGS = 5
#: The ladders' own reference and its independent check (`benchmark.core.policy`: why they differ from
#: the runs table's): constant-step dopri8 at `REFERENCE_DT`, its error bounded against twice that
#: step, and scipy's DOP853, another eighth-order tableau.
REFERENCE_METHOD, REFERENCE_DT = ORDERS_REFERENCE_METHOD, ORDERS_REFERENCE_DT
CHECK_METHOD = ORDERS_CHECK_METHOD
#: A run's error counts when it is at least this many times the reference's error bound.
FLOOR_FACTOR = 100.0
#: Two consecutive slopes closer than this: the error is in its asymptotic range.
ASYMPTOTIC_SPREAD = 0.2
#: |observed − declared| at most this: the method shows its order (tests/test_orders_table.py).
THEORY_TOLERANCE = 0.3
#: Identity of a ladder row; a rerun replaces a (scene, integrator)'s rows as a whole.
LADDER_KEY = ("scene", "integrator")


def coarsest_step(order: int) -> float:
    """The largest step of a method's ladder, by its declared order: an eighth-order error falls
    by 256 per halving, so its ladder starts coarser to stay above the reference's floor; a
    first-order error (the LGVI while reeling) hides under its second-order term until the step
    is small (the reel starts near rest: measured slopes 1.44, 1.27, 1.16 from 5 ms down, 1.02 at
    0.16 ms), so its ladder starts at 2.5 ms."""
    return 0.16 if order >= 6 else 0.0025 if order <= 1 else 0.08


def steps(order: int) -> tuple[float, ...]:
    return tuple(coarsest_step(order) / 2 ** k for k in range(HALVINGS + 1))


def fixed_step_methods(selected=None) -> list[str]:
    """The registered fixed-step methods (test-only ``test_*`` plugins excepted), or those of
    ``selected`` (an unknown or adaptive-only name raises ValueError before any work)."""
    from reelbench.benchmark.runs.sweep import default_names
    from reelbench.integrators import Capability, available, get_integrator

    if selected:
        for name in selected:
            if not get_integrator(name).has(Capability.FIXED_STEP):
                raise ValueError(f"--integrators: {name!r} has no constant-step mode, so no order in h "
                                 "(allowed: a fixed-step method, see `python -m benchmark list`)")
        return list(selected)
    names = default_names() + [n for n in available() if n not in default_names() and not n.startswith("test_")]
    return [n for n in dict.fromkeys(names) if get_integrator(n).has(Capability.FIXED_STEP)]


def load(scene_name: str, elements: int = ELEMENTS):
    from reelbench.models import load_scene

    return load_scene(scene_name, elements=elements)


class Reference(NamedTuple):
    scene: str
    x: np.ndarray  # (saved times, nx)
    error_bound: float  # max |x(h) − x(2h)| of the reference method
    check: float  # max |x − x_DOP853|


def reference(scene_name: str, elements: int = ELEMENTS, t_end: float = T_END) -> Reference:
    """The reference of one scene (see the module's docstring); ValueError when it fails."""
    from reelbench.integrators import get_integrator

    scene = load(scene_name, elements)
    ref = get_integrator(REFERENCE_METHOD)
    fine = ref.solve(scene, t_end=t_end, dt=REFERENCE_DT, save_every=SAVE_EVERY)
    twice = ref.solve(scene, t_end=t_end, dt=2 * REFERENCE_DT, save_every=SAVE_EVERY)
    check = get_integrator(CHECK_METHOD["integrator"]).solve(scene, t_end=t_end, rtol=CHECK_METHOD["rtol"],
                                                             atol=CHECK_METHOD["atol"], save_every=SAVE_EVERY)
    for tr in (fine, twice, check):
        if not tr.ok:
            raise ValueError(f"the orders' reference of {scene_name} ({tr.integrator}) did not finish: {tr.reason}")
    x = np.asarray(fine.x)
    return Reference(scene_name, x, float(np.abs(np.asarray(twice.x) - x).max()),
                     float(np.abs(np.asarray(check.x) - x).max()))


@functools.lru_cache(maxsize=None)
def _reference(scene_name: str, elements: int, t_end: float) -> Reference:
    """`reference`, computed once per process (a worker runs every scene of its method)."""
    return reference(scene_name, elements, t_end)


class Job(NamedTuple):
    scene: str
    integrator: str
    reference: Reference | None = None  # None: computed by the job (once per process)
    elements: int = ELEMENTS
    t_end: float = T_END
    budget: object = None  # of each run of the ladder (`runner.SolveBudget`); None: the defaults


#: The columns of a ladder row (orders_errors.csv), in order.
LADDER_COLUMNS = ("scene", "integrator", "situation", "declared_order", "elements", "t_end", "setting", "dt", "status",
                  "reason", "error", "reference_error", "reference_check")


def run_job(job: Job) -> dict:
    """One method's ladder on one scene: a row per step (status, error) in ``ladder``."""
    from reelbench.integrators import get_integrator
    from reelbench.integrators.base import Status, situation

    ref = job.reference or _reference(job.scene, job.elements, job.t_end)
    scene = load(job.scene, job.elements)
    integ = get_integrator(job.integrator)
    declared = integ.order_for(scene)
    ladder = []
    for h in steps(declared or 1):
        tr = integ.solve(scene, t_end=job.t_end, dt=h, save_every=SAVE_EVERY, **_budget.solve_kwargs(job.budget))
        same = tr.ok and np.shape(tr.x) == np.shape(ref.x)
        ladder.append({"scene": job.scene, "integrator": job.integrator, "situation": situation(scene),
                       "declared_order": declared, "elements": job.elements, "t_end": job.t_end,
                       "setting": Setting.fixed(h).label(), "dt": h, "status": tr.status, "reason": tr.reason,
                       "error": float(np.abs(np.asarray(tr.x) - ref.x).max()) if same else np.nan,
                       "reference_error": ref.error_bound, "reference_check": ref.check})
    return {"scene": job.scene, "integrator": job.integrator, "status": Status.OK.value, "ladder": ladder}


def crash_row(job: Job, exc: BaseException) -> dict:
    from reelbench.benchmark.core.engine import crash_reason
    from reelbench.integrators.base import CRASHED

    return {"scene": job.scene, "integrator": job.integrator, "status": CRASHED, "reason": crash_reason(exc),
            "elements": job.elements, "t_end": job.t_end, "ladder": []}


def ladder_rows(row: dict) -> list[dict]:
    """The table rows of a job's row (`Study.expand`): its ladder's runs, or, when its worker
    died, the job's row itself (its status and reason)."""
    return list(row["ladder"]) or [{k: v for k, v in row.items() if k != "ladder"}]


def to_frame(rows: list[dict]) -> pd.DataFrame:
    """orders_errors.csv: the ladder rows, in order (`in_order`)."""
    from reelbench.benchmark.core.store import frame

    table = frame(rows, list(LADDER_COLUMNS))
    return in_order(table) if len(table) else table


def key(job: Job) -> str:
    """What determines a ladder: the scene's physics, the method, N and the horizon, the budget
    (`budget.key_settings`), the code."""
    from reelbench.benchmark.core.study import job_key

    return job_key({"scene": load(job.scene, job.elements).key(), "integrator": job.integrator,
                    "elements": job.elements, "t_end": job.t_end, **_budget.key_settings(job.budget)},
                   "benchmark/studies/orders.py")


def study(scenes=None, integrators=None, *, workers: int | None = None, budget=None, echo=print):
    """The observed orders as a study of `benchmark.core.study.run` (see the module's docstring):
    orders_errors.csv, merged ladder by ladder, then orders.csv and the echoed section. An
    adaptive-only method is refused here, before any work. ``workers``: None, one per method
    (`engine.default_workers`); ``budget``: of each run (None: the defaults)."""
    from pathlib import Path

    from reelbench.benchmark.core.engine import default_workers
    from reelbench.benchmark.core.study import Study

    methods = fixed_step_methods(integrators)
    jobs = [Job(s, m, budget=budget) for s in (scenes or SCENES) for m in methods]

    def report(out, rows: list[dict], provenance) -> str:
        from reelbench.benchmark.core.store import write_table

        summary = summarise(to_frame(rows))
        write_table(Path(out) / "orders.csv", summary)
        echo(section(summary))
        return f"wrote {out}/orders.csv ({len(rows)} runs in {out}/orders_errors.csv)"

    return Study(name="orders", table="orders_errors.csv", identity=LADDER_KEY, jobs=jobs, run_job=run_job,
                 identity_of=lambda j: (j.scene, j.integrator), frame=to_frame, report=report, describe=describe,
                 key=key, crash_row=crash_row, group=lambda j: j.integrator, expand=ladder_rows,
                 text_columns=("scene", "integrator", "situation", "setting", "status", "reason"),
                 workers=workers if workers is not None else default_workers(len(methods)))


def describe(row: dict) -> str:
    errs = ", ".join(f"{r['error']:.1e}" if np.isfinite(r["error"]) else r["status"] for r in row["ladder"])
    return f"orders {row['scene']} / {row['integrator']}: {errs or row['status']}"


def in_order(ladder: pd.DataFrame) -> pd.DataFrame:
    """The ladder rows by scene (`SCENES` first) and method (`fixed_step_methods`' order), each
    ladder coarsest step first: a merged table reads like a fresh one."""
    scenes = list(dict.fromkeys([*SCENES, *ladder["scene"]]))
    methods = list(dict.fromkeys([*fixed_step_methods(), *ladder["integrator"]]))
    rank = ladder.assign(_s=ladder["scene"].map(scenes.index), _m=ladder["integrator"].map(methods.index))
    return rank.sort_values(["_s", "_m", "dt"], ascending=[True, True, False], kind="stable").drop(
        columns=["_s", "_m"]).reset_index(drop=True)


def summarise(ladder: pd.DataFrame) -> pd.DataFrame:
    """orders.csv from the ladder rows: per scene and method, the slope of the last halving above
    the reference's floor, the one before it, and the flags (see the module's docstring)."""
    import pandas as pd  # not at import: the command line reads this module's constants without it

    from reelbench.integrators.base import FINISHED_STATUSES  # here too: the command line imports this module at start
    rows = []
    for (scene, name), g in ladder.groupby(list(LADDER_KEY), sort=False):
        g = g.sort_values("dt", ascending=False)
        floor = FLOOR_FACTOR * float(g["reference_error"].max())
        counted = g["status"].isin(FINISHED_STATUSES) & np.isfinite(g["error"]) & (g["error"] >= floor)
        s = successive_orders(g["dt"].to_numpy(), g["error"].to_numpy())
        pair_ok = counted.to_numpy()[:-1] & counted.to_numpy()[1:]
        valid = [k for k in range(len(s)) if pair_ok[k]]
        last = valid[-1] if valid else None
        before = last - 1 if last is not None and last - 1 in valid else None
        order = float(s[last]) if last is not None else np.nan
        prev = float(s[before]) if before is not None else np.nan
        declared = g["declared_order"].iloc[0]
        asymptotic = bool(np.isfinite(prev) and abs(order - prev) <= ASYMPTOTIC_SPREAD)
        note = []
        if last is None:
            note.append("no halving above the reference's floor")
        elif not asymptotic:
            note.append("not asymptotic: the last two slopes differ by more than "
                        f"{ASYMPTOTIC_SPREAD:g}" if np.isfinite(prev) else "one halving only: not confirmed")
        if (~counted).any():
            below = g.loc[~counted & g["status"].isin(FINISHED_STATUSES), "dt"]
            failed = g.loc[~g["status"].isin(FINISHED_STATUSES), "dt"]
            if failed.notna().any():
                note.append("did not finish at dt = " + ", ".join(f"{h:g}" for h in failed.dropna()))
            for r in g[g["dt"].isna()].itertuples():  # a job whose worker died: no ladder
                note.append(f"{r.status}: {r.reason}")
            if len(below):
                note.append("below the floor at dt = " + ", ".join(f"{h:g}" for h in below))
        rows.append({"scene": scene, "integrator": name, "situation": g["situation"].iloc[0],
                     "declared_order": declared, "observed_order": order, "previous_slope": prev,
                     "halvings_run": len(g) - 1, "halvings_counted": len(valid), "asymptotic": asymptotic,
                     "finest_dt_counted": float(g["dt"].to_numpy()[last + 1]) if last is not None else np.nan,
                     "finest_error_counted": float(g["error"].to_numpy()[last + 1]) if last is not None else np.nan,
                     "reference_error": float(g["reference_error"].max()),
                     "reference_check": float(g["reference_check"].max()),
                     "within_theory": bool(not pd.isna(declared) and np.isfinite(order)
                                           and abs(order - float(declared)) <= THEORY_TOLERANCE),
                     "elements": int(g["elements"].iloc[0]), "t_end": float(g["t_end"].iloc[0]),
                     "note": "; ".join(note)})
    return pd.DataFrame(rows)


def section(summary: pd.DataFrame | None) -> str:
    """The "Observed convergence orders" section of results/README.md from orders.csv."""
    from reelbench.benchmark.core.report import markdown_table

    head = "## Observed convergence orders\n\n"
    if summary is None or summary.empty:
        return head + ("Not measured in this directory: `python -m benchmark orders --out DIR` writes `orders.csv` "
                       "(the sweep's own horizons are chaotic and too long for orders).\n")
    n, t = int(summary["elements"].max()), float(summary["t_end"].max())
    off = summary[~summary["within_theory"].astype(bool)]
    flagged = summary[~summary["asymptotic"].astype(bool)]
    verdict = ("Every method shows its declared order within ±{:g}.".format(THEORY_TOLERANCE) if off.empty else
               "Not within ±{:g} of the declared order: {}.".format(
                   THEORY_TOLERANCE, ", ".join(f"`{r.integrator}` on {r.scene} ({r.observed_order:.2f} against "
                                               f"{r.declared_order})" for r in off.itertuples())))
    flags = ("" if flagged.empty else " Not asymptotic (the last two slopes differ by more than "
             f"{ASYMPTOTIC_SPREAD:g}, or only one halving counted): "
             + ", ".join(f"`{r.integrator}` on {r.scene}" for r in flagged.itertuples()) + ".")
    shown = summary[["scene", "integrator", "situation", "declared_order", "observed_order", "previous_slope",
                     "halvings_counted", "asymptotic", "finest_error_counted", "reference_error", "note"]]
    shown = shown.assign(**{c: shown[c].map(lambda v: f"{v:.3g}" if np.isfinite(v) else "")
                            for c in ("observed_order", "previous_slope", "finest_error_counted", "reference_error")})
    return (head + f"From `orders.csv` (`python -m benchmark orders`): each fixed-step method at {HALVINGS} halvings "
            f"of its step on a {t:g} s horizon of each scene, N = {n}, against constant-step {REFERENCE_METHOD} at "
            f"{REFERENCE_DT * 1e3:g} ms (its error bounded by its distance to twice that step, `reference_error`; "
            f"a run counts when its error is at least {FLOOR_FACTOR:g}× that). `observed_order`: the slope of the last "
            "halving that counts; `previous_slope`: the one before. Methods that only adapt their step have no "
            f"order in h and are not listed. {verdict}{flags}\n\n" + markdown_table(shown))
