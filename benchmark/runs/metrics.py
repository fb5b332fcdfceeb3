"""One tidy row of metrics per run: conservation, accuracy against a reference, cost."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import pandas as pd

from reelbench.benchmark.core.order import successive_orders
from reelbench.models._lazy import lazy_function
from reelbench.integrators.base import FINISHED_STATUSES
from reelbench.integrators.base import INACCURATE as _INACCURATE

# JAX-backed: imported on first use, so that the command line can list the metrics without JAX
build_model = lazy_function("reelbench.models.model", "build_model")
energy_deviation = lazy_function("reelbench.models.diagnostics", "energy_deviation")
evaluate = lazy_function("reelbench.models.diagnostics", "evaluate")
quat_to_rot_many = lazy_function("reelbench.models.model", "quat_to_rot_many")

#: The sum of a run's counts (column ``work_evals``; rankings and figures use ``flops``, see
#: `FLOPS_DEFINITION`, and this sum is kept to compare with tables from before it), in
#: right-hand-side-equivalent evaluations:
#: ``rhs_evals + newton_iterations + ny × jac_evals``. For the ODE baselines the Newton
#: iterations are already right-hand-side evaluations (counted in ``rhs_evals``); a Jacobian
#: counts as the ny evaluations a finite-difference Jacobian costs (the classical convention;
#: ny = size of the ODE state), LU factorisations are not counted (reported apart in
#: ``lu_decompositions``). For the LGVI it is its Newton iterations (two or three per step),
#: each counted as one evaluation although it costs less than one (hence ``flops``).
#: NaN when the integrator reports no count (diffrax Kvaerno5: diffrax does not expose its
#: Newton iterations).
WORK_DEFINITION = ("work = RHS evaluations + Newton iterations + ny × Jacobian evaluations "
                   "(LU factorisations not counted)")

#: The work in one unit that ranks methods (column ``flops``, the bottom row of the work-precision
#: figures): the sum above adds unlike units (an LGVI Newton iteration is not an evaluation).
FLOPS_DEFINITION = ("work = floating-point operations (flops): XLA's cost model of each method's whole compiled step (loops at their trip "
                    "counts) × its attempted steps (`benchmark.work.flops`)")


def work_evals(stats: dict, ny: int | None = None) -> float:
    """Work of a run's stats in RHS-equivalent evaluations (see `WORK_DEFINITION`; ``ny`` is the
    ODE state size, needed when the run evaluated Jacobians); NaN if no count is known."""
    def count(key):
        v = stats.get(key)
        return float(v) if v is not None and np.isfinite(v) else None

    rhs, newton, jac = count("rhs_evals"), count("newton_iterations"), count("jac_evals")
    if rhs is None and newton is None:
        return np.nan
    if jac and ny is None:
        raise ValueError("work_evals: ny (the ODE state size) is required for a run with Jacobian evaluations")
    return (rhs or 0.0) + (newton or 0.0) + (jac or 0.0) * (ny or 0)


# ------------------------------------------------------------------------------------------
# The metric registry: one entry per accuracy metric, read by runs.csv (`COLUMNS`, `run_metrics`),
# `benchmark check` (floors and directions) and the stability map (the reference-free ones).
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Evidence:
    """What the metrics of one finished run are computed from, computed once: the run's
    diagnostics (`models.diagnostics.evaluate`), whether the scene has work terms, and, when a
    reference was given and shares saved times with the run, the body-position distances
    ``dpos`` (m) and attitude distances ``datt`` (Frobenius; None without a rigid body)."""

    df: pd.DataFrame
    has_work: bool
    dpos: np.ndarray | None = None
    datt: np.ndarray | None = None
    conserves_pi3: bool = True


def pi3_deviation(df: pd.DataFrame) -> pd.Series:
    """|π3 − π3(0)| / |π3(0)| at every saved time of a run's diagnostics (absolute if π3(0) = 0),
    the π3 drift of the paper's panel (d) and of the metric ``pi3_error``."""
    pi0 = float(df["pi3"].iloc[0])
    dpi = np.abs(df["pi3"] - pi0)
    return dpi / abs(pi0) if abs(pi0) > 1e-12 else dpi


def _pi3_error(ev: Evidence) -> float:
    """NaN where the scene's forces do not conserve π3 (`models.layout.StateLayout.conserves_pi3`)."""
    return float(np.max(pi3_deviation(ev.df))) if ev.conserves_pi3 else np.nan


def _of(arr: str, how: str) -> Callable[[Evidence], float]:
    def f(ev: Evidence) -> float:
        a = getattr(ev, arr)
        return np.nan if a is None else float(a[-1] if how == "final" else a.max())
    return f


@dataclass(frozen=True)
class Metric:
    """One accuracy metric: its ``function`` of the run's `Evidence`; ``floor``: below it a value
    is round-off or the reference's own error (`benchmark check` never fails a value under it);
    ``direction``: "lower" when smaller is better (all of them today); ``reference``: whether
    it needs the reference solution (the stability map reports only those that do not);
    ``sanity``: see `INACCURATE`."""

    name: str
    function: Callable[[Evidence], float]
    floor: float = 1e-10
    direction: str = "lower"
    reference: bool = False
    description: str = ""
    #: the sanity bound: a function of the scene giving the value above which a run is no longer
    #: a solution of it (status `INACCURATE`), or None when the metric sets no such bound
    sanity: Callable[[object], float] | None = None


#: Status of a run that finished (the integrator said "ok") with an error beyond a metric's
#: sanity bound (`Metric.sanity`): its numbers are no longer a solution of the scene, so it is
#: no point of a work–precision curve and no cost is read from it (a search, `benchmark.answer.search`,
#: meets a target only with runs whose status is "ok"); its accuracy values are not reported, its
#: ``reason`` names the values and bounds it broke. The bounds, each far beyond any error a
#: benchmark target asks for (targets go down from 1e-2):
#:
#: * energy error above `ENERGY_SANITY_BOUND` = 0.1: the energy balance is off by a tenth of
#:   the largest kinetic energy (a run that far off conserves nothing; an integrator's own
#:   guard stops a run at 1× the energy scale, `integrators.base.energy_bound`);
#: * body position error (max over the saved times) above `POSITION_SANITY_FRACTION` = 1/100 of
#:   the initially deployed string length (0.1 m on the 10 m fixed_length scene): the body is no
#:   longer where the scene puts it (needs the reference; without one only the energy bound applies).
#:
#: In results/runs.csv before this status, 7 of the 197 "ok" runs broke a bound, all at the
#: two coarsest fixed steps (10 and 20 ms), e.g. dopri5 at 10 ms on fixed_length (energy error
#: 1.18, position error 13.9 m) and dopri8 at 20 ms (energy error 0.15); every one that broke
#: the position bound broke the energy bound too.
INACCURATE = _INACCURATE  # the status, named with the others in `integrators.base`
ENERGY_SANITY_BOUND = 0.1
POSITION_SANITY_FRACTION = 0.01


def _position_sanity(scene) -> float:
    return POSITION_SANITY_FRACTION * float(scene.initial.deployed_length)


METRICS: tuple[Metric, ...] = (
    Metric("energy_error", lambda ev: float(energy_deviation(ev.df, has_work=ev.has_work).max()),
           description="max |E − E0| / max T (E − W with non-conservative forces)",
           sanity=lambda scene: ENERGY_SANITY_BOUND),
    Metric("pi3_error", _pi3_error, description="max |π3 − π3(0)| / |π3(0)| (absolute if π3(0) = 0; empty where "
           "external forces do not conserve π3)"),
    Metric("orthogonality_error", lambda ev: float(ev.df["orthogonality_error"].max()), description="max ‖I − RᵀR‖"),
    Metric("position_error_final", _of("dpos", "final"), reference=True, description="body position error at t_end (m)"),
    Metric("position_error_max", _of("dpos", "max"), reference=True,
           description="body position error, max over saved times (m)", sanity=_position_sanity),
    Metric("attitude_error_final", _of("datt", "final"), reference=True, description="attitude error at t_end"),
    Metric("attitude_error_max", _of("datt", "max"), reference=True, description="attitude error, max over saved times"),
)
#: Accuracy metrics: reported only for runs that finished ("ok"); NaN otherwise.
ACCURACY = [m.name for m in METRICS]
#: The metrics a run gives without a reference (conservation): the stability map's.
CONSERVATION = [m.name for m in METRICS if not m.reference]
#: name -> floor, name -> direction (`benchmark check`)
FLOORS = {m.name: m.floor for m in METRICS}
DIRECTIONS = {m.name: m.direction for m in METRICS}

#: Columns of the runs table, in order (the metrics' come from the registry, so a new metric is
#: one `Metric` entry above).
COLUMNS = [
    "scene", "integrator", "setting", "dt", "rtol", "atol", "t_end", "status", "reason",
    "rhs", "steps", "rhs_evals", "jac_evals", "lu_decompositions", "newton_iterations", "work_evals",
    "run_time", "compile_time",
    *ACCURACY,
    "t_reached",
]


def sanity_bounds(scene) -> dict[str, float]:
    """metric -> its sanity bound on ``scene`` (see `INACCURATE`)."""
    return {m.name: float(m.sanity(scene)) for m in METRICS if m.sanity is not None}


def inaccurate_reason(values: dict, scene) -> str:
    """Why a finished run with these metric ``values`` is no solution of ``scene`` (the bounds
    it broke, with the values), or "" when it is within every sanity bound (a NaN is no
    evidence either way: a metric without its reference breaks no bound)."""
    broken = [f"{name} {values[name]:.3g} > {bound:.3g}" for name, bound in sanity_bounds(scene).items()
              if np.isfinite(values.get(name, np.nan)) and values[name] > bound]
    if not broken:
        return ""
    return "no longer a solution: " + ", ".join(broken) + " (sanity bound)"


def attitude_matrices(traj) -> np.ndarray | None:
    """(n, 3, 3) attitude as the integrator has it (quaternions mapped without renormalising)."""
    if traj.attitude is None:
        return None
    if traj.attitude_kind == "quaternion":
        return quat_to_rot_many(np.reshape(traj.attitude, (-1, 4)))
    return np.asarray(traj.attitude)


def body_positions(model, traj) -> np.ndarray:
    """Attachment point r_p + q_{N+1} at every saved time, (n, 3)."""
    return model.r_p + np.asarray(traj.x)[:, -3:]


def _distances(scene, traj, ref, save_every: float):
    """(dpos, datt) at every saved time of ``traj``, the reference read there by its dense output
    (`benchmark.core.reference.reference_at`); a reference without one is compared at the saved times
    both share; (None, None) if none."""
    from reelbench.benchmark.core.reference import reference_at

    model = build_model(scene)
    if ref.dense is not None:
        ref = reference_at(scene, ref, traj.t)
        common = i = j = np.arange(len(traj.t))
    else:
        k_traj = np.round(np.asarray(traj.t) / save_every).astype(int)
        k_ref = np.round(np.asarray(ref.t) / save_every).astype(int)
        common, i, j = np.intersect1d(k_traj, k_ref, return_indices=True)
    if len(common) == 0:
        return None, None
    dpos = np.linalg.norm(body_positions(model, traj)[i] - body_positions(model, ref)[j], axis=1)
    Ra, Rb = attitude_matrices(traj), attitude_matrices(ref)
    datt = np.linalg.norm(Ra[i] - Rb[j], axis=(1, 2)) if Ra is not None and Rb is not None else None
    return dpos, datt


def run_metrics(scene, traj, ref, save_every: float, finished=FINISHED_STATUSES) -> dict:
    """All accuracy metrics of one run (`METRICS`; NaN if the run did not finish, i.e. its status
    is not in ``finished``; the reference metrics are NaN without a reference ``ref``)."""
    if traj.status not in finished or len(traj.t) == 0:
        return {k: np.nan for k in ACCURACY}
    dpos, datt = _distances(scene, traj, ref, save_every) if ref is not None else (None, None)
    layout = build_model(scene).layout
    ev = Evidence(df=evaluate(scene, traj), has_work=layout.has_work, dpos=dpos, datt=datt,
                  conserves_pi3=layout.conserves_pi3)
    return {m.name: m.function(ev) for m in METRICS}


def energy_history(scene, traj) -> pd.DataFrame:
    """t and the energy error relative to max T (E - W with non-conservative forces)."""
    df = evaluate(scene, traj)
    dev = energy_deviation(df, has_work=build_model(scene).layout.has_work)
    return pd.DataFrame({"t": df["t"], "energy_error": dev})


def observed_orders(runs: pd.DataFrame, error: str = "position_error_final") -> pd.DataFrame:
    """Observed order per scene and integrator: slope p of error ∝ steps^(-p).

    For fixed-step runs this is the classical order in dt (the mean of
    `benchmark.core.order.successive_orders` over the sweep, with h = 1 / steps); adaptive
    runs use the same definition along their tolerance sweep. Only finished runs above round-off (error > 1e-12) count.
    ``finest_pair_order`` uses only the two runs with the most steps, the ones most likely
    in the asymptotic range (coarse steps near a stability limit, or a long horizon of this
    chaotic system, can make the mean meaningless).
    """
    rows = []
    for (scene, integ, axis), g in runs.assign(axis=np.where(runs["dt"].notna(), "dt", "rtol")).groupby(
        ["scene", "integrator", "axis"]
    ):
        g = g[g["status"].isin(FINISHED_STATUSES) & (g[error] > 1e-12) & (g["steps"] > 0)].sort_values("steps")
        slopes = successive_orders(1.0 / g["steps"].to_numpy(float), g[error].to_numpy(float))
        rows.append({"scene": scene, "integrator": integ, "sweep": axis, "points": len(g),
                     "observed_order": float(np.mean(slopes)) if len(slopes) else np.nan,
                     "finest_pair_order": float(slopes[-1]) if len(slopes) else np.nan})
    return pd.DataFrame(rows)


def fastest_at(runs: pd.DataFrame, error: str, target: float, cost: str = "run_time") -> pd.DataFrame:
    """Per scene: the cheapest finished run of each integrator whose ``error`` <= target,
    ranked by ``cost`` (``run_time``, or ``work_evals``: see `WORK_DEFINITION`), with the factor
    to the cheapest. Runs without that cost (NaN) are left out."""
    ok = runs[runs["status"].isin(FINISHED_STATUSES) & (runs[error] <= target) & runs[cost].notna()]
    out = []
    for scene, g in ok.groupby("scene"):
        best = g.loc[g.groupby("integrator")[cost].idxmin()].sort_values(cost)
        t0 = best[cost].iloc[0]
        for _, r in best.iterrows():
            out.append({"scene": scene, "integrator": r["integrator"], "setting": r["setting"],
                        cost: r[cost], error: r[error], "factor": r[cost] / t0})
    return pd.DataFrame(out)
