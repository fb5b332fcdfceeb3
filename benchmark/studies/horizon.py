"""The long-horizon energy study (`python -m benchmark energy`): energy error vs time, with the
physics that drives it, one engine job per run of `PLAN`. Its table is energy_horizon.csv (one
history per run; a rerun replaces its own runs' histories and keeps the others), analysed by
`benchmark.studies.energy_drift.energy_table`.

Each saved time records, beside the signed energy error (E − E0)/max T, what the state says
about it (`axial_measures`, relative to max T): the energy in the string's axial vibration, P =
Σ_a EA l (dε_a/dt)² (1/s²), the transverse part G of the elastic Hessian along the velocity
(U''(v, v) = P + G), the fourth-order companion P4 = Σ_a EA l (d²ε_a/dt²)² (1/s⁴), the body's
spin S = |Ω|² T_rot and the least element tension. A symplectic method conserves a modified
energy Ẽ = E + h^p H_p + …; averaged over the string's fast modes ⟨H_p⟩ = c_p ⟨P_p⟩
(`benchmark.studies.energy_drift`), so its energy error carries an offset −c_p h^p ⟨P_p⟩ that grows
whenever energy flows into those modes, without any drift of Ẽ. With `slack` only taut elements
count (a slack one stores no energy and has no stiffness).

The plan: every run goes to `HORIZON` s on the fixed-length scenes it is given (default
`DEFAULT_SCENE`; a scene with a reel ends when the reel reaches its limit, too soon for a long
horizon: `energy_scenes`) and on the same scene with the tension-only string (`VARIANTS`). Which
method at which N and step is listed in `PLAN` with why; the accurate reference is `REFERENCE`.

As a study of the one runner (`study`, `benchmark.core.study.run`) one job is one run: its row's
history becomes that run's rows of energy_horizon.csv (`expand`: a rerun replaces them as a
whole), saved after every run; a run already in the table for the same settings, size, horizon,
scene and code (`key`) is kept; a run whose worker died makes no rows and is reported
(`failure`); an earlier table keeps only the runs the study still makes (`read_earlier`). Its
figures and text are `benchmark.studies.horizon_report`'s.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from reelbench.benchmark.core import store
from reelbench.benchmark.core.engine import log_stderr
from reelbench.benchmark.core.policy import SOLVE_MAX_STEPS
from reelbench.benchmark.runs.sweep import MethodSettings
from reelbench.benchmark.studies import budget as _budget

DEFAULT_SCENE = "fixed_length"
SAVE_EVERY = 0.1
#: The table keeps one row per block of this many seconds (`blocks`): the largest |E − E0| and the
#: least tension in it, and the means of the rest over its saved times (ten at `SAVE_EVERY`);
#: a 1000-s history is 1001 rows, not 10,001.
BLOCK_S = 1.0
#: The sizes of the string: the paper's N = 10 and a coarse N = 4 (whether what is seen depends on N).
ELEMENTS = (4, 10)
#: The study's horizon (s): long enough for the growth of the axial energy to show at N = 4 and 10.
HORIZON = 1000.0
#: The string laws: the scene as it is (two-sided elasticity) and with the `slack` effect added
#: (tension-only); a variant's runs are tabled under the scene's name plus "_" + the variant's.
VARIANTS = {"": (), "slack": ("slack",)}
#: The step the compositions run at: the LGVI's (the LGVI stands for its family in the sweep).
COMPOSITION_STEP = 0.005
#: The accurate reference solve, drawn beside the methods (its energy error is in the table).
REFERENCE = "dopri8"
#: The setting of each method of `PLAN` (its second, where it has one, follows by `finer`). A
#: method without an entry makes no runs, and a method outside `PLAN` (a plugin too) is none of
#: the study's, even when ``--integrators`` names it: the study's runs are chosen for what they
#: show, so a method joins by a row of `PLAN` and an entry here.
SETTINGS = {
    "lgvi": {"dt": 0.005},
    "lgvi_yoshida4": {"dt": COMPOSITION_STEP},
    "lgvi_suzuki4": {"dt": COMPOSITION_STEP},
    "rattle": {"dt": 0.005},
    "lie_rk4": {"dt": 0.005},
    REFERENCE: {"rtol": 1e-8, "atol": 1e-10},
}
#: (variant, method, sizes, settings) of each run group: settings 2 is the method's setting
#: (`SETTINGS`) and one `FINER` (the h-scaling of the offset needs two steps), 1 that one alone.
#: Chosen to keep the study to minutes of CPU at 1000 s (its measured cost: README.md, the
#: `energy` command): the LGVI, the cheapest, at both sizes and steps; the compositions at N = 10
#: and both steps; RATTLE (its Newton iteration makes it the dearest) and the non-symplectic
#: lie_rk4 once at N = 10; the reference at both sizes; with `slack`: the LGVI at both steps,
#: Suzuki and the reference at N = 10. Left out: tsit5 adds nothing dopri8 and lie_rk4 do not
#: show (both drift); scipy's rk45 and dop853 step in Python (rk45's 100 s took 52 s, the
#: study's longest job, measured) where the compiled pairs stand for them; lgvi_sym and
#: crouch_grossman3, whose families the LGVI and lie_rk4 represent.
PLAN = (
    ("", "lgvi", ELEMENTS, 2),
    ("", "lgvi_yoshida4", (10,), 2),
    ("", "lgvi_suzuki4", (10,), 2),
    ("", "rattle", (10,), 1),
    ("", "lie_rk4", (10,), 1),
    ("", REFERENCE, ELEMENTS, 1),
    ("slack", "lgvi", (10,), 2),
    ("slack", "lgvi_suzuki4", (10,), 1),
    ("slack", REFERENCE, (10,), 1),
)
#: The second setting of a fixed-step method: its step / FINER (an adaptive one: its tolerances / TIGHTER).
FINER, TIGHTER = 2.0, 100.0
#: The step budget of each run by default: every solve's (`benchmark.core.policy.SOLVE_MAX_STEPS`),
#: not a library's default (diffrax's 100,000 stopped Tsit5 at rtol 1e-8 short of 100 s at N = 10);
#: --max-steps and --time-limit give a job another budget (`Job.budget`).
MAX_STEPS = SOLVE_MAX_STEPS
#: Identity of one run in energy_horizon.csv (a rerun replaces the rows of the same run).
RUN_KEY = ("scene", "elements", "integrator", "setting")
#: The study's table: the history of each run, in blocks of `BLOCK_S`, then the run's columns.
TABLE = "energy_horizon.csv"
COLUMNS = ["t", "energy_error", "energy_dev", "axial_P", "geometric_G", "axial_P4", "spin_S", "tension_min",
           "method", "integrator", "scene", "elements", "setting", "status", "t_end", "job_key"]


def finer(method: MethodSettings) -> MethodSettings:
    s = dict(method.settings)
    if "dt" in s:
        s["dt"] = s["dt"] / FINER
    else:
        s = {k: v / TIGHTER for k, v in s.items()}
    return MethodSettings(method.name, s)


def declared(name: str) -> MethodSettings | None:
    """The method's energy-study setting (`SETTINGS`), None for a method without one."""
    return MethodSettings(name, dict(SETTINGS[name])) if name in SETTINGS else None


def methods(selected=None) -> list[MethodSettings]:
    """The study's methods (those of `PLAN`) among ``selected`` (None: all); ValueError for a
    selected name that is unknown (the registry's message)."""
    from reelbench.integrators import get_integrator

    for name in selected or ():
        get_integrator(name)
    names = dict.fromkeys(name for _, name, _, _ in PLAN if selected is None or name in selected)
    return [m for m in map(declared, names) if m is not None]


def runs(selected=None, elements=None, variants=None) -> list[tuple[str, int, MethodSettings]]:
    """(variant, N, settings) of every run of `PLAN` among ``selected`` methods, ``elements``
    (None: each group's own sizes; a tuple: those sizes only, for every group) and ``variants``
    (None: all), the method's setting (`SETTINGS`) first."""
    out = []
    for variant, name, sizes, settings in PLAN:
        if (selected is not None and name not in selected) or (variants is not None and variant not in variants):
            continue
        m = declared(name)
        if m is None:
            continue
        for n in (elements if elements is not None else sizes):
            out += [(variant, n, s) for s in (m, finer(m))[:settings] if (variant, n, s) not in out]
    return out


def variant_overrides(scene, variant: str) -> tuple:
    """The scene overrides of ``variant`` (`VARIANTS`) for the loaded ``scene``: () for the scene
    as it is, else its effects with the variant's added."""
    extra = [e for e in VARIANTS[variant] if e not in scene.effects]
    return (("effects", tuple(scene.effects) + tuple(extra)),) if extra else ()


def table_scene(name: str, variant: str) -> str:
    """The scene's name in the table and the figure's file name: "fixed_length_slack"."""
    return f"{name}_{variant}" if variant else name


def setting_of(method: MethodSettings) -> str:
    return ", ".join(f"{k}={v:g}" for k, v in method.settings.items())


def label(scene: str, elements: int, method: MethodSettings) -> str:
    """The run's name in tables and legends: "lgvi dt=0.005 N=10" (the scene is its own column)."""
    return f"{method.label} N={elements}"


class Job(NamedTuple):
    """One run: the scene (a name or path) at N ``elements`` with ``overrides``, one method's
    setting, to ``t_end``; tabled under ``tabled`` (`table_scene`: with the variant's name)."""

    scene: str
    elements: int
    method: MethodSettings
    t_end: float
    overrides: tuple  # ((key, value), ...) of the scene (the variant's effects included)
    tabled: str = ""  # the scene's name in the table; "": ``scene``
    budget: object = None  # of the solve (`runner.SolveBudget`); None: the defaults (`MAX_STEPS`)

    @property
    def tabled_as(self) -> str:
        return self.tabled or self.scene

    def identity(self) -> tuple:
        """The run's place in the table (`RUN_KEY`)."""
        return self.tabled_as, self.elements, self.method.name, setting_of(self.method)


def axial_measures(scene, traj) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(P, G, P4, S) at each saved time, over the elements (with `slack`: the taut ones):
    P = Σ_a EA l (dε_a/dt)² and G = Σ_a (T_a/|Δ_a|) |Δv_a⊥|², the axial and the transverse
    (geometric) parts of the elastic energy's Hessian along the velocity, U''(v, v) = P + G, in
    J/s²; P4 = Σ_a EA l (d²ε_a/dt²)² in J/s⁴; and the body's S = |Ω|² T_rot in J/s². For a
    fixed length l, dε_a/dt = ê_a·Δv_a / l and d²ε_a/dt² = (ê_a·Δa_a + |Δv_a⊥|²/|Δ_a|) / l, with
    the accelerations of the model's equations of motion at the saved state. Averaged over a
    linear mode of the string of frequency ω and energy E_m, U''(v, v) is ω² E_m and P4 (an axial
    mode) ω⁴ E_m."""
    import jax
    import jax.numpy as jnp

    from reelbench.models.model import build_model, quat_to_rot

    model = build_model(scene)
    slack = scene.has("slack")
    n = len(traj.t)
    if n == 0:
        return np.zeros(0), np.zeros(0)
    from_momentum = traj.velocity is None
    v = traj.momentum if from_momentum else traj.velocity
    has_att = model.layout.has_attitude and traj.attitude is not None
    att = traj.attitude if has_att else np.zeros((n, 3, 3))
    quaternion = has_att and traj.attitude_kind == "quaternion"

    def one(t, x, a, vel):
        R = quat_to_rot(a) if quaternion else (a if has_att else jnp.eye(3))
        w = model.velocity_from_momentum(x, R, vel) if from_momentum else vel
        acc = model.accelerations(t, x, R, w)
        delta, stretch, l = model.elements(x)
        e = delta / stretch[:, None]
        vn, an = model.node_velocities(w), model.node_velocities(acc)
        dv, da = vn[1:] - vn[:-1], an[1:] - an[:-1]
        along = jnp.sum(e * dv, axis=1)
        rate = along / l
        accel = (jnp.sum(e * da, axis=1) + (jnp.sum(dv * dv, axis=1) - along ** 2) / stretch) / l
        taut = stretch > l if slack else jnp.ones_like(stretch, dtype=bool)
        k = model.EA * l
        geometric = model.EA * (stretch / l - 1.0) / stretch * (jnp.sum(dv * dv, axis=1) - along ** 2)
        om = model.omega(w)
        spin = jnp.sum(om * om) * 0.5 * om @ (jnp.asarray(model.J_c) @ om)  # |Ω|² T_rot (Ω = 0 without a body)
        return (jnp.sum(jnp.where(taut, k * rate ** 2, 0.0)), jnp.sum(jnp.where(taut, geometric, 0.0)),
                jnp.sum(jnp.where(taut, k * accel ** 2, 0.0)), spin)

    out = jax.jit(jax.vmap(one))(jnp.asarray(traj.t, dtype=float), jnp.asarray(traj.x), jnp.asarray(att),
                                 jnp.asarray(v))
    return tuple(np.asarray(o, float) for o in out)


def run_job(job: Job) -> dict:
    """One run's row: its label (with the status when the run stopped early) and its history at
    each saved time: the energy error |E − E0|/max T (`benchmark.runs.metrics.energy_history`), its
    sign (``energy_dev``), P, G, P4 and S of `axial_measures` over max T and the least element
    tension (N; < 0: compression), in blocks of `BLOCK_S` (`blocks`)."""
    import time

    from reelbench.benchmark.runs.metrics import energy_history
    from reelbench.integrators import get_integrator
    from reelbench.models import load_scene
    from reelbench.models.diagnostics import evaluate

    started = time.perf_counter()
    scene = load_scene(job.scene, **dict(job.overrides), elements=job.elements)
    traj = get_integrator(job.method.name).solve(scene, t_end=job.t_end, save_every=SAVE_EVERY,
                                                 **_budget.solve_kwargs(job.budget), **job.method.settings)
    name = label(job.scene, job.elements, job.method) + ("" if traj.ok else f" [{traj.status}]")
    diag = evaluate(scene, traj)
    tmax = float(diag["kinetic"].max()) if len(diag) else np.nan
    P, G, P4, S = axial_measures(scene, traj)
    history = energy_history(scene, traj).assign(
        energy_dev=((diag["energy"] - diag["energy"].iloc[0]) / tmax).to_numpy() if len(diag) else [],
        axial_P=P / tmax, geometric_G=G / tmax, axial_P4=P4 / tmax, spin_S=S / tmax,
        tension_min=diag["tension_min"].to_numpy())
    return {**_run_columns(job), "label": name, "status": traj.status, "history": blocks(history),
            "task_time": time.perf_counter() - started}


def _run_columns(job: Job) -> dict:
    return {**dict(zip(RUN_KEY, job.identity())), "t_end": job.t_end}


def blocks(history, width: float = BLOCK_S):
    """``history`` in blocks (0, width], (width, 2 width], … labelled by their end (the row at
    t = 0 kept alone): the largest ``energy_error`` and the least ``tension_min`` of each block,
    the mean of every other column."""
    if history.empty:
        return history
    t = history["t"].to_numpy(float)
    k = np.where(t <= 0.0, 0, np.ceil(t / width - 1e-9)).astype(int)
    agg = {c: ("max" if c == "energy_error" else "min" if c == "tension_min" else "mean")
           for c in history.columns if c != "t"}
    out = history.drop(columns="t").groupby(k, sort=True).agg(agg)
    ends = np.minimum(out.index.to_numpy(float) * width, t[-1])
    return out.reset_index(drop=True).assign(t=ends)[list(history.columns)]


def crash_row(job: Job, exc: BaseException) -> dict:
    from reelbench.benchmark.core.engine import crash_reason
    from reelbench.integrators.base import CRASHED

    return {**_run_columns(job), "label": f"{label(job.scene, job.elements, job.method)} [crashed]",
            "status": CRASHED, "reason": crash_reason(exc), "history": None}


def describe(row: dict) -> str:
    """A finished run in the progress log: its label, scene and status."""
    return f"horizon {row['label']}" + (f" on {row['scene']}" if row.get("scene") else "") + f": {row['status']}"


# ------------------------------------------------------------------------------------------
# The study on the one runner
# ------------------------------------------------------------------------------------------
def energy_scenes(scenes, overrides: tuple = (), log: Callable[[str], None] = log_stderr) -> list[str]:
    """The scenes of ``scenes`` (names or paths) the energy study can run on over a long
    horizon: those of fixed length (a reel ends at its limit); says which it leaves out."""
    from reelbench.integrators.base import situation
    from reelbench.models import load_scene

    ov = {k: v for k, v in overrides if k != "elements"}
    kept = [s for s in scenes if situation(load_scene(s, **ov)) == "fixed_length"]
    left = [s for s in scenes if s not in kept]
    if left:
        log(f"horizon: {', '.join(left)} left out of the energy study (a reel ends at its limit, long before a "
            "long horizon)")
    return kept


def jobs_for(t_end: float, scenes=None, overrides: tuple = (), selected=None, variants=("",)) -> list[Job]:
    """The runs of `PLAN` (`runs`) on ``scenes`` (default `DEFAULT_SCENE`), each with its
    ``variants``, to ``t_end``. ``overrides`` of the scenes: elements=N runs that N only."""
    from reelbench.models import load_scene

    ov = dict(overrides)
    sizes = (int(ov.pop("elements")),) if "elements" in ov else None  # --set elements=N: that N only
    ov = tuple(sorted(ov.items()))
    out = []
    for s in list(scenes or [DEFAULT_SCENE]):
        scene = load_scene(s, **dict(ov))
        for v, n, m in runs(selected, sizes, variants):
            job_ov = tuple(sorted({**dict(ov), **dict(variant_overrides(scene, v))}.items()))
            out.append(Job(s, n, m, t_end, job_ov, table_scene(scene.name, v)))
    return out


def key(job: Job) -> str:
    """What determines a run's history: the run, its horizon, overrides and budget
    (`budget.key_settings`: nothing more at the defaults), and the code."""
    other = _budget.key_settings(job.budget)
    return store.key_of(job.tabled_as, job.elements, job.method.name, job.method.settings, float(job.t_end),
                        list(job.overrides), store.code_version(), MAX_STEPS,
                        store.source_hash((), ("benchmark/studies/horizon.py",)), *([other] if other else []))


def expand(row: dict) -> list[dict]:
    """The table rows of a run's row: its history, each saved block with the run's columns; none
    for a run without one (its worker died)."""
    if row.get("history") is None:
        return []
    run = {c: row[c] for c in (*RUN_KEY, "status", "t_end")}
    return row["history"].assign(method=row["label"], **run).to_dict("records")


def to_frame(rows: list[dict]):
    return store.frame(rows, COLUMNS, extra=False)


def read_earlier(df):
    """The study's reading of an earlier energy_horizon.csv. A table from before the study had
    sizes and scenes gets their columns (fixed_length, the scene's own N = 10, the integrator and
    setting from the run's label); the histories of runs the study no longer makes (another
    method or setting) are left out."""
    import pandas as pd

    from reelbench.benchmark.studies.horizon_report import method_of

    for c in ("t", "energy_error"):
        if c in df:
            df[c] = pd.to_numeric(df[c], errors="coerce")
    if "method" in df:
        label = df["method"].astype(str)
        filled = {"integrator": label.map(method_of), "scene": DEFAULT_SCENE, "elements": 10,
                  "setting": label.map(lambda m: m.split(" ", 1)[1] if " " in m else "")}
        for c, value in filled.items():
            if c not in df:
                df[c] = value
    if {"integrator", "setting"} <= set(df.columns):
        made = {(m.name, setting_of(m)) for _, _, m in runs()}
        still = [(i, s) in made for i, s in zip(df["integrator"], df["setting"])]
        df = df[pd.Series(still, index=df.index, dtype=bool)]
    return df


def failure(row: dict) -> str | None:
    """What failed, for a run without a history (its worker died); None for a run with one."""
    if row.get("history") is not None:
        return None
    return (f"{row['integrator']} {row['setting']} N={row['elements']} on {row['scene']} "
            f"({row.get('reason') or row['status']})")


def _cost(job: Job) -> float:
    from reelbench.benchmark.runs import runner
    from reelbench.benchmark.runs.sweep import Task

    m = job.method
    return runner.task_costs([Task(job.scene, m.name, dt=m.settings.get("dt"), rtol=m.settings.get("rtol"),
                                   t_end=job.t_end)])[0]


def with_slack_orders(selected=None, variants=("",)) -> bool:
    """Whether the `energy` command measures the observed orders with and without `slack` too: with
    the slack variant and every method."""
    return (variants is None or "slack" in variants) and selected is None


def measure_slack_orders(out: Path, log: Callable[[str], None]) -> None:
    """The observed orders with and without `slack` (`benchmark.studies.slack_orders`), kept when
    its code did not change: a step of the `energy` command after its runs."""
    from reelbench.benchmark.studies import slack_orders

    if slack_orders.fresh(out):
        log(f"energy: {out}/{slack_orders.TABLE} kept (same code)")
    else:
        log(f"energy: observed orders with and without `slack` -> {out}/{slack_orders.TABLE} ...")
        slack_orders.study(out, log=log)


def study(t_end: float, scenes=None, *, overrides: tuple = (), selected=None, variants=("",),
          workers: int | None = None, text: bool = False, budget=None):
    """The energy study as a study of `benchmark.core.study.run`: the runs of `PLAN` among the
    ``selected`` methods (None: all) on ``scenes`` (default `DEFAULT_SCENE`) and their string
    ``variants`` ("" the scene as it is, "slack" the tension-only string; None: all of
    `VARIANTS`), to ``t_end``, one job per run on ``workers`` (0: this process; None: one per
    run, `engine.default_workers`), each solve within ``budget`` (None: the defaults). Its report
    draws energy_horizon_SCENE.png of each of its scenes from the whole table; ``text`` (the `energy` command): also the energy section
    (`benchmark.studies.horizon_report.write`), after the observed orders with and without `slack`
    (`measure_slack_orders`) when the slack variant and every method run."""
    from reelbench.benchmark.core.engine import default_workers
    from reelbench.benchmark.core.study import Study
    from reelbench.benchmark.studies import horizon_report

    jobs = [j._replace(budget=budget) for j in jobs_for(t_end, scenes, overrides, selected, variants)]
    drawn = tuple(dict.fromkeys(j.tabled_as for j in jobs))
    return Study(name="horizon", table=TABLE, identity=RUN_KEY, jobs=jobs, run_job=run_job,
                 identity_of=Job.identity, frame=to_frame, key=key, expand=expand, read_earlier=read_earlier,
                 reusable=lambda row: True,  # every history in the table is a run's result, whatever its status
                 failure=failure, crash_row=crash_row, describe=describe, cost=_cost, unit="runs",
                 report=lambda out, rows, provenance: horizon_report.write(out, rows, drawn, text=text),
                 after_jobs=measure_slack_orders if text and with_slack_orders(selected, variants) else None,
                 text_columns=("scene", "integrator", "setting"),
                 workers=workers if workers is not None else default_workers(len(jobs)))
