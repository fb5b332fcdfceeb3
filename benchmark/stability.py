"""Stability map (issue #7): how large a step each integrator can take on each hard scene.

    python -m benchmark stability [--scenes ...] [--integrators ...] [--jobs N] [--out DIR]

* Fixed-step methods (the LGVI, diffrax Tsit5 at a constant step) walk a **ladder** of step
  sizes dt = DT_MAX / 2^k, largest first, and stop at the first rung whose run stays bounded
  over the horizon: its status is "ok" (or "length_limit" on the scenes that are meant to end
  at a length limit). That rung is the *largest stable dt* of the map (resolution: a factor 2;
  the rung above it is reported with the status that ended it). This assumes stability is
  monotone in dt, which holds for every ladder here (each rung above the stable one failed).
* Adaptive methods run once at ``ADAPTIVE_RTOL`` / ``ADAPTIVE_ATOL`` and report their step
  statistics: accepted and rejected steps, min / median / mean step, status, cost.

Every run is a `benchmark.sweep.Task` executed by `benchmark.runner.run_task` (no reference
solution: the map is about staying bounded, the conservation metrics come from the run itself),
so a failing run is a row with its status and reason, and an exception is a row with status
"error". One (scene, integrator, kind) row is one job on the runner's engine (`runner.run_jobs`:
the jobs of one (scene, integrator) in one worker, so it compiles once; longest groups first by
`_cost_hint`; a dead worker's job is a "crashed" row; Ctrl-C / SIGTERM stop it and keep the rows
done). Rows are written atomically after each job (``stability.csv``), then ``stability.md``,
``stability.png`` and a generated ``README.md`` with a written reading of the table.
"""

from __future__ import annotations

import datetime
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from benchmark import report, runner
from benchmark.metrics import CONSERVATION
from benchmark.sweep import Task
from models.io import atomic_write_text

#: Largest step of the fixed-step ladder (s) and the number of halvings tried below it.
DT_MAX = 0.04
LADDER_RUNGS = 12  # down to 0.04 / 2^11 ≈ 2e-5 s
ADAPTIVE_RTOL = 1e-6
ADAPTIVE_ATOL = 1e-8
SAVED_POINTS = 100  # per run: the energy guard is checked at these (LGVI, scipy)



def implicit_baseline(integ) -> bool:
    """An implicit *baseline* (declares IMPLICIT, not VARIATIONAL): its Jacobian or Newton compiles
    through the ODE model per scene. The LGVIs are implicit too, but structured."""
    from integrators import Capability

    return integ.has(Capability.IMPLICIT) and not integ.has(Capability.VARIATIONAL)


def default_integrators() -> list[str]:
    """The map's default methods: those of the default sweep (`benchmark.sweep.default_names`:
    every registered method and plugin), implicit baselines last (their jobs are the longest)."""
    from benchmark.sweep import default_names
    from integrators import get_integrator

    return sorted(default_names(), key=lambda n: implicit_baseline(get_integrator(n)))


def adaptive_only(integ) -> bool:
    """An adaptive method that cannot take a constant step (declares ADAPTIVE, not FIXED_STEP)."""
    from integrators import Capability

    return integ.has(Capability.ADAPTIVE) and not integ.has(Capability.FIXED_STEP)


def also_fixed_step(integ) -> bool:
    """An adaptive method that also takes a constant step (Tsit5): the map runs it both ways."""
    from integrators import Capability

    return integ.has(Capability.ADAPTIVE) and integ.has(Capability.FIXED_STEP)


def kinds(name: str) -> list[str]:
    """The map's kinds of ``name`` from its declared capabilities: "fixed" (a dt ladder) for
    FIXED_STEP, "adaptive" (one tolerance) for ADAPTIVE; Tsit5 has both."""
    from integrators import Capability, get_integrator

    integ = get_integrator(name)
    return [k for k, cap in (("fixed", Capability.FIXED_STEP), ("adaptive", Capability.ADAPTIVE)) if integ.has(cap)]


@dataclass(frozen=True)
class Case:
    """One hard scene in the map: horizon, overrides that keep it short, what counts as bounded."""

    scene: str
    horizon: float
    bounded: tuple[str, ...] = ("ok",)
    overrides: tuple = ()
    #: shorter horizons for some methods: selector -> (s, reason), or (selector, kind) for one
    #: kind only; a selector is a function of the integrator (declared capabilities, never a
    #: name), true when it applies. The first that applies wins.
    short: dict = field(default_factory=dict)
    #: integrators left out of this scene: selectors, functions of the integrator returning the
    #: reason written into the table (or None), see `skip_reason`
    skip: tuple = ()
    #: left out of the default run only (``--integrators`` naming them runs them), same form
    default_skip: tuple = ()
    note: str = ""


_STEPS_500 = "adaptive-only baseline: 500 s at rtol 1e-6 is ~1e5 steps, minutes per run"
#: Since the baselines run on the O(N) closed form (issue #11), the implicit ones compile in
#: seconds and run on the hard scenes; on the 1,927-dimensional many_elements state each of
#: their steps still factorises a dense Jacobian (O(n^3)), so implicit baselines get a shorter
#: horizon there, and a method declaring itself `expensive` (kvaerno5) stays out of the two
#: stiff, large scenes.
_DENSE_LU = "implicit baseline: a dense LU of the 1,927 x 1,927 Jacobian per step (O(n^3))"


def _expensive(integ) -> str | None:
    """Default run: leave out a method whose declared cost (`Integrator.expensive`, measured) is
    prohibitive on this scene."""
    return f"default run: {integ.name} {integ.expensive}; run it with --integrators {integ.name}" if integ.expensive else None


CASES = (
    Case("stiff_string", 0.2, note="EA = 20 kN, N = 40",
         short={implicit_baseline: (0.05, "implicit baseline: a Newton solve with LU per step on a stiff string")},
         default_skip=(_expensive,)),
    Case("many_elements", 1.0, note="N = 320", short={implicit_baseline: (0.05, _DENSE_LU)},
         default_skip=(_expensive,)),
    Case("fast_spin", 2.0, note="|Omega0| = 30 rad/s"),
    Case("retrieval_to_limit", 10.0, bounded=("length_limit",), overrides=(("deployed_length", 3.0),),
         note="started at 3 m (scene: 15 m) to reach the 2 m limit sooner; bounded = ends with length_limit"),
    Case("deployment_to_end", 10.0, bounded=("length_limit",), overrides=(("deployed_length", 36.0),),
         note="started at 36 m (scene: 3 m) to reach the 39 m limit sooner; bounded = ends with length_limit"),
    Case("long_horizon", 500.0, note="the scene's full 500 s for the fixed-step methods",
         short={implicit_baseline: (20.0, "implicit baseline: 500 s is ~1e5 steps with a Newton solve each"),
                adaptive_only: (20.0, _STEPS_500),
                (also_fixed_step, "adaptive"): (100.0, "adaptive at rtol 1e-6 it needs > 1e5 steps (its default "
                                                       "step budget) for 500 s")}),
    Case("near_slack", 2.0, note="string compressed by 5 % at t = 0"),
)


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _horizon(case: Case, integrator: str, kind: str = "adaptive") -> tuple[float, str]:
    """(horizon, why it is shorter than the case's): the first `Case.short` selector (or
    (selector, kind)) that applies to the integrator's declared capabilities."""
    if case.short:
        from integrators import get_integrator

        integ = get_integrator(integrator)
        for key, value in case.short.items():
            select, only = key if isinstance(key, tuple) else (key, kind)
            if only == kind and select(integ):
                return value
    return case.horizon, ""


def skip_reason(case: Case, integrator: str, default_run: bool = True) -> str | None:
    """Why ``integrator`` is left out of ``case`` (`Case.skip`, and `Case.default_skip` in the
    default run), or None when it runs."""
    selectors = case.skip + (case.default_skip if default_run else ())
    if not selectors:
        return None
    from integrators import get_integrator

    integ = get_integrator(integrator)
    return next((r for r in (sel(integ) for sel in selectors) if r), None)


def ladder(case: Case, integrator: str) -> list[Task]:
    """The fixed-step ladder of one (scene, integrator), largest dt first."""
    horizon, _ = _horizon(case, integrator, "fixed")
    save_every = horizon / SAVED_POINTS
    dts = [DT_MAX / 2 ** k for k in range(LADDER_RUNGS)]
    dts = [dt for dt in dts if dt <= horizon / 10] or dts[-1:]  # at least 10 steps per run
    return [Task(case.scene, integrator, dt=dt, t_end=horizon, save_every=save_every, overrides=case.overrides)
            for dt in dts]


def adaptive_task(case: Case, integrator: str) -> Task:
    horizon, _ = _horizon(case, integrator)
    return Task(case.scene, integrator, rtol=ADAPTIVE_RTOL, atol=ADAPTIVE_ATOL, t_end=horizon,
                save_every=horizon / SAVED_POINTS, overrides=case.overrides)


def _base_row(case: Case, integrator: str, kind: str) -> dict:
    horizon, why = _horizon(case, integrator, kind)
    return {"scene": case.scene, "integrator": integrator, "kind": kind, "horizon": horizon,
            "horizon_note": why, "overrides": ", ".join(f"{k}={v}" for k, v in case.overrides)}


def run_job(case: Case, integrator: str, kind: str, default_run: bool = True) -> dict:
    """One row of the map: a whole ladder (kind "fixed") or one adaptive run. Never raises."""
    t0 = time.perf_counter()
    row = _base_row(case, integrator, kind)
    why = skip_reason(case, integrator, default_run)
    if why:
        row.update(status="skipped", reason=why, bounded=False)
        return row
    try:
        if kind == "fixed":
            tried, stable, above = 0, None, None
            for task in ladder(case, integrator):
                r = runner.run_task(task, repeats=0, reference=False, finished=case.bounded)
                tried += 1
                if r["status"] in case.bounded:
                    stable = r
                    break
                above = r
            row.update(rungs_tried=tried)
            if above is not None:
                row.update(first_unstable_dt=above["dt"], unstable_status=above["status"],
                           unstable_reason=above["reason"])
            r = stable if stable is not None else above
            row.update(largest_stable_dt=stable["dt"] if stable is not None else np.nan)
        else:
            r = runner.run_task(adaptive_task(case, integrator), repeats=0, reference=False, finished=case.bounded)
        row.update({k: r.get(k, np.nan) for k in (
            "setting", "status", "reason", "steps", "rejected_steps", "min_step", "median_step", "newton_iterations",
            "run_time", "compile_time", *CONSERVATION, "t_reached")})
        row["bounded"] = r["status"] in case.bounded
        steps = row.get("steps")
        if steps is not None and np.isfinite(steps) and steps > 0:
            row["mean_step"] = row["t_reached"] / steps
    except Exception as exc:  # one bad job must not lose the other rows
        row.update(status="error", reason=f"{type(exc).__name__}: {exc}".splitlines()[0][:300], bounded=False)
    row["job_time"] = time.perf_counter() - t0
    return row


#: the map's table; its metrics are the registry's that need no reference (`metrics.CONSERVATION`)
COLUMNS = ["scene", "integrator", "kind", "horizon", "bounded", "largest_stable_dt", "first_unstable_dt",
           "unstable_status", "setting", "status", "steps", "rejected_steps", "min_step", "median_step", "mean_step",
           "newton_iterations", *CONSERVATION, "run_time", "compile_time", "job_time",
           "rungs_tried", "t_reached", "overrides", "horizon_note", "reason", "unstable_reason"]


def to_frame(rows: list[dict]) -> pd.DataFrame:
    return runner.to_frame(rows, COLUMNS, extra=False)


def jobs_for(scenes=None, integrators=None) -> list[tuple[Case, str, str, bool]]:
    from integrators import get_integrator

    names = list(integrators) if integrators else default_integrators()
    for n in names:
        get_integrator(n)  # unknown names raise before any work
    cases = [c for c in CASES if scenes is None or c.scene in scenes]
    if scenes is not None:
        unknown = set(scenes) - {c.scene for c in CASES}
        if unknown:
            raise ValueError(f"no stability case for scene(s) {', '.join(sorted(unknown))} "
                             f"(allowed: {', '.join(c.scene for c in CASES)})")
    out = []
    for case in cases:
        for n in names:
            out += [(case, n, kind, not integrators) for kind in kinds(n)]
    return out


def describe(row: dict) -> str:
    """A finished job in the progress log."""
    what = (f"largest stable dt {row.get('largest_stable_dt'):.3g} s" if row.get("kind") == "fixed"
            and np.isfinite(row.get("largest_stable_dt", np.nan)) else f"{row.get('status')}")
    return (f"{row['scene']} {row['integrator']} ({row['kind']}): {what}, "
            f"{row.get('steps', float('nan')):.0f} steps, job {row.get('job_time', float('nan')):.0f} s")


def execute(jobs: list[tuple[Case, str, str, bool]], *, workers: int = 2, on_rows: Callable | None = None,
            log: Callable[[str], None] = _log) -> pd.DataFrame:
    """Run the jobs on the runner's engine (`runner.run_jobs`; ``workers`` = 0: in this process);
    rows in job order. The jobs of one (scene, integrator) run in one worker, so it compiles that
    method on that scene once (Tsit5's ladder and adaptive run share it); the longest groups
    start first (`_cost_hint`)."""

    def crashed(i: int, exc: BaseException) -> dict:
        case, integ, kind, _ = jobs[i]
        return {**_base_row(case, integ, kind), "status": "crashed", "reason": runner.crash_reason(exc), "bounded": False}

    rows = runner.run_jobs(run_job, jobs, workers=workers, crash_row=crashed,
                           group=lambda i: (jobs[i][0].scene, jobs[i][1]), cost=lambda i: _cost_hint(*jobs[i]),
                           describe=describe, on_row=on_rows, log=log)
    return to_frame(rows)


def _cost_hint(case: Case, integrator: str, kind: str, default_run: bool = True) -> float:
    """Rough job cost, to start the longest jobs first (compilation dominates the short ones)."""
    from integrators import get_integrator

    if skip_reason(case, integrator, default_run):
        return 0.0
    compile_s, per_step = get_integrator(integrator).cost_hint  # declared by each method
    horizon, _ = _horizon(case, integrator, kind)
    per_s = {"stiff_string": 200, "many_elements": 400}.get(case.scene, 1)
    return compile_s + horizon * per_s * per_step


# ------------------------------------------------------------------------------------------
# Outputs
# ------------------------------------------------------------------------------------------
def plot(df: pd.DataFrame, out_dir: Path) -> Path:
    from benchmark.plots import _save, plt

    scenes = list(dict.fromkeys(df["scene"]))
    x = np.arange(len(scenes))
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 4.8))
    fixed = df[df["kind"] == "fixed"]
    for k, (integ, g) in enumerate(fixed.groupby("integrator", sort=False)):
        g = g.set_index("scene").reindex(scenes)
        xs = x + (k - 0.5) * 0.3
        a1.bar(xs, g["largest_stable_dt"].fillna(0.0), width=0.3, label=f"{integ} (fixed dt)")
        for xi, v in zip(xs, g["largest_stable_dt"]):
            if not np.isfinite(v):
                a1.text(xi, DT_MAX / 2 ** LADDER_RUNGS, "none", rotation=90, ha="center", va="bottom", fontsize=7)
    a1.set_yscale("log")
    a1.set_ylim(DT_MAX / 2 ** LADDER_RUNGS, DT_MAX * 1.5)
    a1.set_ylabel("largest stable step dt (s)")
    a1.set_title("fixed-step methods: largest dt that stays bounded")
    a2.set_title(f"adaptive methods at rtol {ADAPTIVE_RTOL:g}: steps per second of horizon")
    adaptive = df[df["kind"] == "adaptive"]
    for k, (integ, g) in enumerate(adaptive.groupby("integrator", sort=False)):
        g = g.set_index("scene").reindex(scenes)
        rate = g["steps"] / g["t_reached"].where(g["t_reached"] > 0)
        xs = x + (k - 2) * 0.12
        a2.scatter(xs[g["bounded"] == True], rate[g["bounded"] == True], marker="o", label=f"{integ}")  # noqa: E712
        bad = (g["bounded"] != True) & g["status"].notna()  # noqa: E712
        a2.scatter(xs[bad.to_numpy()], np.where(np.isfinite(rate[bad]), rate[bad], 1.0), marker="x", color="k")
    a2.scatter([], [], marker="x", color="k", label="not bounded / skipped (see table)")
    a2.set_yscale("log")
    a2.set_ylabel("accepted steps per simulated second")
    for ax in (a1, a2):
        ax.set_xticks(x)
        ax.set_xticklabels(scenes, rotation=25, ha="right", fontsize=8)
        ax.grid(True, which="both", axis="y", alpha=0.3)
        ax.legend(fontsize=7)
    return _save(fig, Path(out_dir) / "stability.png")


def _fmt(v, f=".3g") -> str:
    return "–" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, f)


def _per_second(r) -> float:
    """Run time per simulated second (horizons differ between methods)."""
    return r["run_time"] / r["t_reached"] if r["t_reached"] and np.isfinite(r["t_reached"]) and r["t_reached"] > 0 else np.nan


def _variational(name: str) -> bool:
    """Whether ``name`` declares VARIATIONAL (False for a name no longer registered)."""
    from integrators import Capability, get_integrator

    try:
        return get_integrator(name).has(Capability.VARIATIONAL)
    except ValueError:
        return False


def _best_pair(fx: pd.DataFrame):
    """(variational row, other row) with the largest stable dt of each group among the fixed-step
    rows ``fx`` (indexed by integrator), or None when a group has no stable rung."""
    fx = fx[np.isfinite(fx["largest_stable_dt"].astype(float))]
    var = fx[[_variational(n) for n in fx.index]]
    other = fx[[not _variational(n) for n in fx.index]]
    if not len(var) or not len(other):
        return None
    return var.loc[var["largest_stable_dt"].idxmax()], other.loc[other["largest_stable_dt"].idxmax()]


#: The scenes whose largest stable steps the summary compares with the adaptive methods' steps.
STIFF_SCENES = ("stiff_string", "many_elements")


def _nonfinite(df: pd.DataFrame) -> int:
    """Bounded runs whose energy error is not finite (a run that went NaN without a status)."""
    ok = df[df["bounded"] == True]  # noqa: E712
    return int((~np.isfinite(ok["energy_error"].astype(float))).sum())


def reading(df: pd.DataFrame) -> str:
    """A short written reading of the map, generated from the rows: numbers and the names in
    the rows; which methods are compared follows from their declared capabilities (VARIATIONAL
    or not), never from names in this code."""
    lines = []
    for scene, g in df.groupby("scene", sort=False):
        parts = []
        fx = g[g["kind"] == "fixed"].set_index("integrator")
        for name, l in fx.iterrows():
            if np.isfinite(l["largest_stable_dt"]):
                top = " (the ladder's top rung for this horizon: its limit is at least that)" if l["rungs_tried"] == 1 else ""
                parts.append(f"`{name}` stays bounded up to dt = {_fmt(l['largest_stable_dt'])} s{top} "
                             f"({_fmt(_per_second(l))} s of run time per simulated second, energy error {_fmt(l['energy_error'])})")
            else:
                parts.append(f"`{name}` found no stable rung down to {DT_MAX / 2 ** (LADDER_RUNGS - 1):.2g} s "
                             f"({l['status']})")
            if isinstance(l.get("unstable_status"), str):
                parts[-1] += f"; at 2x that it ends `{l['unstable_status']}`"
        pair = _best_pair(fx)
        if pair is not None:
            v, o = pair
            parts.append(f"variational/other fixed-step stable step ratio {_fmt(v['largest_stable_dt'] / o['largest_stable_dt'], '.2g')} "
                         f"(`{v.name}` vs `{o.name}`, the largest stable step of each), `{o.name}` costs "
                         f"{_fmt(_per_second(o) / _per_second(v), '.2g')}x `{v.name}`'s run time per simulated second "
                         "at its own largest stable step")
        ad = g[g["kind"] == "adaptive"]
        ran = ad[ad["status"] != "skipped"]
        ok = ran[ran["bounded"] == True]  # noqa: E712
        if len(ran):
            text = f"at rtol {ADAPTIVE_RTOL:g}, {len(ok)} of {len(ran)} adaptive runs stay bounded"
            if len(ok):
                ok = ok.assign(per_s=[_per_second(r) for _, r in ok.iterrows()]).sort_values("per_s")
                best, slow = ok.iloc[0], ok.iloc[-1]
                step = best["median_step"] if np.isfinite(best["median_step"]) else best["mean_step"]
                text += (f"; the cheapest per simulated second is `{best['integrator']}` ({_fmt(best['per_s'])} s/s, "
                         f"{_fmt(best['steps'], '.0f')} steps over {best['t_reached']:.3g} s, typical step {_fmt(step)} s)")
                if slow["integrator"] != best["integrator"]:
                    text += f", the dearest `{slow['integrator']}` ({_fmt(slow['per_s'])} s/s)"
            parts.append(text)
        bad = ran[ran["bounded"] != True]  # noqa: E712
        if len(bad):
            parts.append("not bounded: " + ", ".join(f"`{r['integrator']}` ({r['status']})" for _, r in bad.iterrows()))
        skipped = ad[ad["status"] == "skipped"]
        if len(skipped):
            parts.append("left out: " + ", ".join(f"`{r['integrator']}`" for _, r in skipped.iterrows()))
        horizons = sorted(set(float(h) for h in g.loc[g["status"] != "skipped", "horizon"] if np.isfinite(h)))
        hz = " / ".join(f"{h:g}" for h in horizons)
        lines.append(f"- **{scene}** (horizon {hz} s): " + "; ".join(parts) + ".")
    # overall
    ratios, costs = [], []
    for scene, g in df[df["kind"] == "fixed"].groupby("scene", sort=False):
        pair = _best_pair(g.set_index("integrator"))
        if pair is not None:
            v, o = pair
            ratios.append(v["largest_stable_dt"] / o["largest_stable_dt"])
            costs.append(_per_second(o) / _per_second(v))
    summary = []
    stiff_scenes = [c.scene for c in CASES if c.scene in STIFF_SCENES and c.scene in set(df["scene"])]
    stiff = df[df["scene"].isin(stiff_scenes)]
    stable = stiff["largest_stable_dt"].astype(float)
    stiff_dt = (float(np.nanmin(stable)), float(np.nanmax(stable))) if stable.notna().any() else None
    ad_stiff = stiff[(stiff["kind"] == "adaptive") & (stiff["status"] != "skipped")]
    typical = [r["median_step"] if np.isfinite(r["median_step"]) else r["mean_step"] for _, r in ad_stiff.iterrows()]
    stiff_names = " and ".join(f"`{s}`" for s in stiff_scenes)
    fixed = df[df["kind"] == "fixed"]
    ended = fixed["unstable_status"].dropna()
    ended = ended[ended.astype(str) != ""]
    if ratios:
        text = (f"**Robustness.** On each scene, the largest stable step of the best variational method is "
                f"{_fmt(min(ratios), '.2g')}–{_fmt(max(ratios), '.2g')}x that of the best other fixed-step method "
                "(ladder resolution: a factor 2)")
        if stiff_dt:
            text += (f"; on {stiff_names} the fixed-step methods' largest stable steps are "
                     f"{_fmt(stiff_dt[0])}–{_fmt(stiff_dt[1])} s")
        text += (f". **Cost.** At its largest stable step the other method needs "
                 f"{_fmt(min(costs), '.2g')}–{_fmt(max(costs), '.2g')}x the variational one's run time per simulated second.")
        summary.append(text)
    if len(ended):
        counts = ended.value_counts()
        summary.append(f"**Past the limit.** On the rung above the largest stable step, {len(ended)} ladder(s) ended "
                       "with a status not counted as bounded on their scene: " + ", ".join(f"`{k}` {v}x" for k, v in counts.items())
                       + f" ({_nonfinite(df)} bounded run(s) report a non-finite energy error).")
    longh = df[(df["scene"] == "long_horizon") & (df["kind"] == "fixed")].set_index("integrator")
    pair = _best_pair(longh) if len(longh) else None
    if pair is not None:
        v, o = pair
        summary.append(f"**Long horizon.** Over {_fmt(float(v['horizon']), 'g')} s, `{v.name}` at dt = "
                       f"{_fmt(v['largest_stable_dt'])} s keeps its energy error at {_fmt(v['energy_error'])} of max T, "
                       f"while `{o.name}` at dt = {_fmt(o['largest_stable_dt'])} s ends at {_fmt(o['energy_error'])} "
                       f"({_fmt(o['energy_error'] / v['energy_error'], '.2g')}x), both bounded.")
    ad = df[df["kind"] == "adaptive"]
    ran = ad[ad["status"] != "skipped"]
    unbounded = ran[ran["bounded"] != True]  # noqa: E712
    summary.append(f"**Adaptive methods.** {len(ran) - len(unbounded)} of {len(ran)} adaptive runs stayed bounded"
                   + (" (not bounded: " + ", ".join(f"{r['integrator']} on {r['scene']} ({r['status']})"
                                                    for _, r in unbounded.iterrows()) + ")" if len(unbounded) else "")
                   + f"; {len(ad) - len(ran)} were left out (reasons in the table)."
                   + (f" On {stiff_names} their typical (median or mean) steps are "
                      f"{_fmt(min(typical))}–{_fmt(max(typical))} s, against {_fmt(stiff_dt[0])}–{_fmt(stiff_dt[1])} s "
                      "for the fixed-step methods." if typical and stiff_dt else ""))
    limits = [c.scene for c in CASES if "length_limit" in c.bounded and c.scene in set(df["scene"])]
    at_limit = df[df["scene"].isin(limits) & (df["status"] != "skipped")]
    if len(at_limit):
        summary[-1] += (f" On the length-limit scenes ({', '.join(f'`{s}`' for s in limits)}) "
                        f"{int((at_limit['status'] == 'length_limit').sum())} of {len(at_limit)} runs end with `length_limit`.")
    return "\n".join(lines) + "\n\n" + "\n\n".join(summary) + "\n"


def write_readme(out_dir: Path, df: pd.DataFrame, *, command: str, wall_time: float) -> Path:
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    cases = "\n".join(f"| `{c.scene}` | {c.horizon:g} s | {', '.join(c.bounded)} | "
                      f"{', '.join(f'{k}={v}' for k, v in c.overrides) or '–'} | {c.note} |" for c in CASES
                      if c.scene in set(df["scene"]))
    show = df[["scene", "integrator", "kind", "horizon", "bounded", "largest_stable_dt", "first_unstable_dt",
               "unstable_status", "status", "steps", "rejected_steps", "min_step", "median_step", "mean_step",
               "energy_error", "run_time"]]
    reasons = df[df["status"].ne("ok") | df["unstable_reason"].notna()][["scene", "integrator", "kind", "status", "reason",
                                                                         "unstable_status", "unstable_reason", "horizon_note"]]
    fixed_names = ", ".join(f"`{n}`" for n in dict.fromkeys(df.loc[df["kind"] == "fixed", "integrator"])) or "none here"
    text = f"""# Stability map of the hard scenes

Generated by `{command}` on {now} in {wall_time:.0f} s wall time, with {WORKERS_NOTE[0]}
worker process(es); 1-minute load average {LOAD[0]:.1f} at the start and {os.getloadavg()[0]:.1f} at the end
(the machine is shared: timings are inflated when the load exceeds the core count).
{report.environment()}

Do not edit: rerun the command to regenerate. `stability.csv` has one row per scene ×
integrator × kind with every column; `stability.md` is the table below; `stability.png` the plot.

**How to read it.** Fixed-step methods (kind `fixed`: {fixed_names})
walk the ladder dt = {DT_MAX:g} s / 2^k, largest first, and stop at the first rung whose run
stays *bounded* over the horizon; `largest_stable_dt` is that rung (resolution: a factor 2),
`first_unstable_dt` the rung above it with the status that ended it. Adaptive methods (kind
`adaptive`) run once at rtol {ADAPTIVE_RTOL:g}, atol {ADAPTIVE_ATOL:g}; `steps` are accepted steps,
`rejected_steps` rejected ones (not reported by scipy's Radau), `min_step`/`median_step` from
scipy's step history (diffrax reports counts only: `mean_step` = horizon reached / steps).
*Bounded* means status `ok` — no divergence guard tripped: state finite, energy balance error
within `integrators.base.energy_bound`, Newton converged, Cayley parameter |c| ≤ 1 — or, on
the two limit scenes, status `length_limit`. `energy_error` is max|Δ(E − W)| / max T of the
run shown. `run_time` excludes compilation; it is one solve on a shared 2-core machine (no
repeats), so treat ratios below ~2 as noise.

| scene | horizon | bounded = | overrides | note |
|---|---|---|---|---|
{cases}

## Reading

{reading(df)}
## Table

{report.markdown_table(show)}
## Statuses and reasons of the runs that stopped

{report.markdown_table(reasons)}
![stability map](stability.png)
"""
    path = Path(out_dir) / "README.md"
    atomic_write_text(path, text)
    return path


LOAD = [0.0]
WORKERS_NOTE = [2]


def main(scenes=None, integrators=None, *, workers: int = 2, out: str = "results/stability", command: str = "") -> int:
    out_dir = Path(out)
    LOAD[0], WORKERS_NOTE[0] = os.getloadavg()[0], workers or 1
    jobs = jobs_for(scenes, integrators)  # validates names before any work
    _log(f"stability map: {len(jobs)} jobs ({len({j[0].scene for j in jobs})} scenes) on {workers or 1} worker(s) -> {out_dir}/")
    t0 = time.perf_counter()

    def write(rows) -> None:
        atomic_write_text(out_dir / "stability.csv", to_frame(rows).to_csv(index=False))

    df = execute(jobs, workers=workers, on_rows=write)
    write(df.to_dict("records"))
    atomic_write_text(out_dir / "stability.md", report.markdown_table(df))
    plot(df, out_dir)
    wall = time.perf_counter() - t0
    write_readme(out_dir, df, command=command or "python -m benchmark stability", wall_time=wall)
    _log(f"done in {wall:.0f} s; see {out_dir}/README.md")
    return 0
