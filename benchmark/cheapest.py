"""The cost of reaching a target accuracy, with its spread, and verdicts that call a tie a tie.

Pure functions of a runs table (the columns of ``results/runs.csv``); nothing here runs a solve.

**Cost at a target.** For each (scene, accuracy metric, target) and each method, the cost is
read off the method's own work–precision curve: its finished (``status == "ok"``) runs of one
sweep (fixed ``dt`` or adaptive ``rtol``), ordered from the coarsest setting to the finest. Where
two neighbouring settings bracket the target (the coarser one's error above it, the finer one's
at or below it) the cost is interpolated log–log between them: the error fixes the weight
``w = log(target / e_coarse) / log(e_fine / e_coarse)`` and ``log cost = (1 − w) log c_coarse
+ w log c_fine``, and the interval ends (``run_time_low``, ``run_time_high``) are interpolated
with the same weight. Nothing is extrapolated:

- when the coarsest finished setting already meets the target, its own cost is the cost
  (``bracket`` says so; coarser settings failed or were not in the sweep, so the method
  cannot be shown to be cheaper there);
- a curve whose errors never reach the target gives ``not reached``;
- a non-monotone curve (the error goes up and comes down through the target again) may
  cross the target more than once: the cheapest crossing counts, i.e. the least the method
  was seen to need;
- a failed run (any status but ``ok``) has no error and is not a point of the curve: the
  neighbours of a failed setting are the finished settings on either side of it. This includes
  a run that finished but is no longer a solution (status ``inaccurate``, an error beyond a
  sanity bound, `benchmark.metrics.INACCURATE`): a cost is read only between two solutions;
- a method with a fixed-step and an adaptive sweep (``tsit5``) is two entries, ranked apart
  like two methods (column ``entry``: ``tsit5 (fixed dt)``, ``tsit5 (adaptive)``): a fixed step
  and an error-controlled step are two ways to use it, not one curve to pick the cheaper from;
- two methods whose runs the table shows to be one trajectory (`identical_methods`: every
  setting both ran agrees bit for bit, e.g. ``lgvi`` and ``lgvi_sym`` at fixed length) are one
  entry (``lgvi = lgvi_sym``); the other's row says ``identical`` and is not ranked, so one
  computation never appears twice in a tie.

**Spread.** A wall-time cost carries the interval of its timing repeats. A work cost (the
column given, else ``flops`` when the table has it, else ``work_evals``) is deterministic;
its interval is zero. Each interval is widened to at least a relative resolution around the
cost, ``[cost / √(1 + r), cost · √(1 + r)]``, so two costs within a factor ``1 + r`` of each
other always overlap: `WORK_RESOLUTION` for work, `WALL_RESOLUTION`
for wall time (from measured timing noise, see there).

**Verdicts.** Among the methods that reached the target, the one of lowest cost is the
``winner`` only when its ``cost_high`` is below every other method's ``cost_low``; otherwise it
and every method whose interval overlaps its interval are a ``tie``. The rest are ``slower``,
``not reached``, or ``not measured`` (the method reached the target but the table has no cost of
that kind for it, e.g. no work count).
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from benchmark.metrics import ACCURACY, INACCURATE
from benchmark.sweep import PRESENTATION_ORDER, SWEEP_WORDS

#: Relative resolution of a work count: two work costs within 10 % of each other are a tie.
#: A count is deterministic on one machine, but adaptive step sequences follow round-off, so the
#: same sweep on another CPU takes a few steps more or fewer; and 10 % is below any difference
#: worth a sentence in a benchmark.
WORK_RESOLUTION = 0.10
#: Relative resolution of a wall time: two run times within a factor 2 of each other are a tie
#: whatever their repeats say. Measured on a shared 2-core machine at 1-minute load 2.1–2.9,
#: 30 interleaved solves each of lgvi (dt 5 ms), tsit5 and dop853 (rtol 1e-6) on fixed_length:
#: single solves spread over 2.2–2.7× (max / min), medians of 5 consecutive solves over
#: 1.5–1.85×, of 10 over 1.2–1.3×. A row timed once has no spread of its own, and the repeats of
#: one row do not see the load change between rows (the same few-ms runs moved by 2× between
#: two sweeps). At load 9–13 the spreads were 2.6–7.7×, and the dop853 / tsit5 ratio of medians
#: moved from 25 to 67: wall-time verdicts need a machine loaded below its core count.
WALL_RESOLUTION = 1.0

#: Wall time: the central cost (the median of the timing repeats) and its interval's ends.
WALL_COLUMNS = ("run_time", "run_time_low", "run_time_high")

COST_KINDS = ("wall", "work")
VERDICTS = ("winner", "tie", "slower", "not reached", "not measured", "identical")

#: Columns of the cheapest table, in order (``entry``: what is ranked, `entry_name`).
COLUMNS = ["scene", "metric", "target", "cost_kind", "integrator", "entry", "sweep", "cost", "cost_low", "cost_high",
           "ratio", "ratio_low", "ratio_high", "verdict", "cost_column", "bracket", "bound", "note"]

#: What fixes a cost (column ``bound``): the target, read off the curve between two settings
#: ("accuracy"), or the coarsest finished setting already meeting it, because coarser fixed steps
#: did not finish ("stability"), coarser tolerances did not finish ("failures"), the next
#: coarser setting finished but is no solution ("cliff": status ``inaccurate``), or nothing
#: coarser was swept ("sweep range"): then the method may be cheaper than the cost says.
BOUNDS = ("accuracy", "stability", "failures", "cliff", "sweep range")

_KEY_COLUMNS = ("scene", "integrator", "setting", "dt", "rtol", "status")
#: The least settings, solutions on both sides, at which two methods' runs must agree bit for
#: bit to be ranked as one (`identical_methods`).
MIN_IDENTICAL_SETTINGS = 2


def work_column(runs: pd.DataFrame) -> str:
    """The work column of a runs table: ``flops`` when it has any value, else ``work_evals``."""
    if "flops" in runs and runs["flops"].notna().any():
        return "flops"
    return "work_evals"


def sweep_of(runs: pd.DataFrame) -> pd.Series:
    """``"dt"`` for a fixed-step run (``dt`` set), ``"rtol"`` for an adaptive one."""
    return pd.Series(np.where(runs["dt"].notna(), "dt", "rtol"), index=runs.index)


def _curves(runs: pd.DataFrame) -> dict[tuple[str, str], dict[str, list[dict]]]:
    """(scene, integrator) -> sweep -> that curve's rows as records, coarsest setting first."""
    out: dict = {}
    for (scene, integ, sweep), g in runs.assign(sweep=sweep_of(runs)).groupby(["scene", "integrator", "sweep"],
                                                                              sort=True):
        g = g.sort_values("dt" if sweep == "dt" else "rtol", ascending=False, kind="stable")
        out.setdefault((scene, integ), {})[sweep] = g.to_dict("records")
    return out


def entry_name(integrator: str, sweep: str, both_sweeps: bool, twins: Sequence[str] = ()) -> str:
    """What one row ranks: the method, with its sweep's words (``tsit5 (fixed dt)``, ``tsit5
    (adaptive)``) when it has runs on both sweeps of the scene, and the methods ranked as it
    (`identical_methods`) after "=" (``lgvi = lgvi_sym``)."""
    name = f"{integrator} ({SWEEP_WORDS[sweep]})" if both_sweeps else integrator
    return " = ".join([name, *twins])


#: How two methods are shown to compute one trajectory on a scene, from the table alone.
IDENTICAL_RULE = (f"every setting both ran has the same status, steps and all {len(ACCURACY)} errors bit for bit, "
                  f"and at least {MIN_IDENTICAL_SETTINGS} of them are solutions")


def _presentation_rank(name: str) -> tuple:
    return (PRESENTATION_ORDER.index(name) if name in PRESENTATION_ORDER else len(PRESENTATION_ORDER), name)


def identical_methods(runs: pd.DataFrame) -> dict[tuple[str, str, str], str]:
    """(scene, integrator, sweep) -> the method it computes the same trajectory as, for every
    curve the table shows to be another's (`IDENTICAL_RULE`: e.g. ``lgvi_sym`` and ``lgvi`` at
    fixed length, where the symmetric scheme's forcing step has nothing to do). Of such a
    group the method first in `benchmark.sweep.PRESENTATION_ORDER` (then by name) is ranked;
    the others map to it. Equal errors at several settings cannot happen by chance: they are
    every metric of the registry (`benchmark.metrics.ACCURACY`; a table without all of them
    shows nothing identical), floats of a chaotic system's run."""
    columns = ["status", "steps", *ACCURACY]
    out: dict = {}
    if any(c not in runs for c in columns):  # less than every error is no evidence of one trajectory
        return out
    for (scene, sweep), g in runs.assign(sweep=sweep_of(runs)).groupby(["scene", "sweep"], sort=True):
        names = sorted(g["integrator"].unique(), key=_presentation_rank)
        by = {n: g[g["integrator"] == n].set_index("setting")[columns].sort_index() for n in names}
        for i, a in enumerate(names):
            if (scene, a, sweep) in out:
                continue
            for b in names[i + 1:]:
                if (scene, b, sweep) in out:
                    continue
                shared = by[a].index.intersection(by[b].index)
                x, y = by[a].loc[shared], by[b].loc[shared]
                if (x["status"] == "ok").sum() >= MIN_IDENTICAL_SETTINGS and x.equals(y):
                    out[(scene, b, sweep)] = a
    return out


def _positive(v) -> bool:
    return v is not None and np.isfinite(v) and v > 0


def _check_table(runs: pd.DataFrame, metrics: Iterable[str], cost_columns: Iterable[str]) -> None:
    missing = [c for c in (*_KEY_COLUMNS, *metrics, *cost_columns) if c not in runs]
    if missing:
        raise ValueError(f"cheapest: the runs table has no column(s) {', '.join(missing)}")
    dup = runs.duplicated(["scene", "integrator", "setting"])
    if dup.any():
        r = runs[dup].iloc[0]
        raise ValueError(f"cheapest: the runs table has two rows for scene {r['scene']!r}, integrator "
                         f"{r['integrator']!r}, setting {r['setting']!r}; pass one sweep")
    if "t_end" in runs:
        horizons = runs.groupby("scene")["t_end"].nunique()
        if (horizons > 1).any():
            raise ValueError(f"cheapest: scene {horizons[horizons > 1].index[0]!r} has runs over several "
                             "horizons (t_end); pass the runs of one horizon")
    if "run_time_low" in runs and "run_time_high" in runs:
        t, lo, hi = (runs[c].to_numpy(float) for c in WALL_COLUMNS)
        with np.errstate(invalid="ignore"):
            bad = (lo > t * (1 + 1e-12)) | (hi < t * (1 - 1e-12))
        if bad.any():
            r = runs[bad].iloc[0]
            raise ValueError(f"cheapest: run_time_low <= run_time <= run_time_high must hold; row "
                             f"{r['scene']}/{r['integrator']}/{r['setting']} has {r['run_time_low']}, "
                             f"{r['run_time']}, {r['run_time_high']}")


def _check_arguments(targets, resolution: dict[str, float], cost_kinds) -> None:
    for kind in cost_kinds:
        if kind not in COST_KINDS:
            raise ValueError(f"cheapest: cost_kinds must be among {COST_KINDS}, got {kind!r}")
    for kind, r in resolution.items():
        if not (np.isfinite(r) and r >= 0):
            raise ValueError(f"cheapest: the {kind} resolution must be a finite number >= 0, got {r!r}")
    for metric, target in targets:
        if not (isinstance(target, (int, float)) and np.isfinite(target) and target > 0):
            raise ValueError(f"cheapest: the target of {metric!r} must be a positive number, got {target!r}")


def cost_on_curve(errors: Sequence[float], costs: Sequence[float], lows: Sequence[float], highs: Sequence[float],
                  target: float) -> tuple[float, float, float, int, int] | None:
    """The cheapest cost at which one curve reaches ``target``, or None if it never does.

    The points are ordered coarse → fine and every error and cost is finite and positive.
    Returns ``(cost, low, high, i, j)``: ``i, j`` the bracketing points (``i == j``: the coarsest
    point already meets the target; its own cost, not interpolated)."""
    e = np.log(np.asarray(errors, float))
    points = [np.asarray(a, float) for a in (costs, lows, highs)]
    lt = math.log(target)
    found = []
    if len(e) and e[0] <= lt:  # a measured point, returned as measured
        found.append(tuple(float(a[0]) for a in points) + (0, 0))
    for i in range(len(e) - 1):
        if e[i] > lt >= e[i + 1]:
            w = (lt - e[i]) / (e[i + 1] - e[i])
            found.append(tuple(float(np.exp((1 - w) * np.log(a[i]) + w * np.log(a[i + 1]))) for a in points) + (i, i + 1))
    return min(found, key=lambda f: f[0]) if found else None


def _widen(cost: float, low: float, high: float, resolution: float) -> tuple[float, float]:
    s = math.sqrt(1.0 + resolution)
    return min(low, cost / s), max(high, cost * s)


def _curve_cost(curve: list[dict], metric: str, target: float, columns: tuple[str, str, str],
                resolution: float) -> dict:
    """One (scene, integrator, sweep) curve (records, coarsest first) at one target: a partial
    row of the cheapest table."""
    cost_col, low_col, high_col = columns
    finished = [r for r in curve if r["status"] == "ok"]
    # an error of exactly 0 is below any target; the log needs it positive
    ok = [dict(r, _e=max(r[metric], np.finfo(float).tiny)) for r in finished if np.isfinite(r[metric]) and r[metric] >= 0]
    if not finished:
        counts = pd.Series([r["status"] for r in curve]).value_counts()
        return {"verdict": "not reached",
                "note": "no finished run (" + ", ".join(f"{n} {s}" for s, n in counts.items()) + ")"}
    if not ok:
        return {"verdict": "not reached", "note": f"no {metric} value"}
    if min(r["_e"] for r in ok) > target:
        least = min(ok, key=lambda r: r["_e"])
        return {"verdict": "not reached", "note": f"least {metric} {least[metric]:.3g} (at {least['setting']})"}
    measured = [r for r in ok if _positive(r[cost_col])]
    if not measured or min(r["_e"] for r in measured) > target:
        return {"verdict": "not measured", "note": f"no {cost_col} for the runs that reached the target"}

    def end(r, col):  # an interval end, or the cost itself where the table has none
        return r[col] if col and _positive(r.get(col)) else r[cost_col]

    cost, lo, hi, i, j = cost_on_curve([r["_e"] for r in measured], [r[cost_col] for r in measured],
                                       [end(r, low_col) for r in measured], [end(r, high_col) for r in measured], target)
    lo, hi = _widen(cost, lo, hi, resolution)
    settings = [r["setting"] for r in measured]
    if i == j:
        coarser = curve[:[r["setting"] for r in curve].index(settings[i])]
        why = ("coarser: " + ", ".join(f"{r['setting']} {r['status']}" for r in coarser) if coarser
               else "the sweep's coarsest setting")
        bracket, note = settings[i], f"reached at the coarsest finished setting ({why}): its own cost"
        failed = [r for r in coarser if r["status"] != "ok"]
        bound = ("sweep range" if not failed else "cliff" if failed[-1]["status"] == INACCURATE else
                 "stability" if str(settings[i]).startswith("dt=") else "failures")
    else:
        bracket, note, bound = f"{settings[i]} .. {settings[j]}", "interpolated", "accuracy"
    return {"cost": cost, "cost_low": lo, "cost_high": hi, "bracket": bracket, "bound": bound, "note": note}


def _verdicts(rows: list[dict]) -> None:
    """Set verdict and ratios in place for the rows of one (scene, metric, target, cost_kind)."""
    reached = sorted((r for r in rows if np.isfinite(r.get("cost", np.nan))), key=lambda r: (r["cost"], r["entry"]))
    if not reached:
        return
    best, others = reached[0], reached[1:]
    alone = all(best["cost_high"] < o["cost_low"] for o in others)
    best["verdict"] = "winner" if alone else "tie"
    best.update(ratio=1.0, ratio_low=1.0, ratio_high=1.0)
    for o in others:
        o["verdict"] = "tie" if (not alone and o["cost_low"] <= best["cost_high"]) else "slower"
        o.update(ratio=o["cost"] / best["cost"], ratio_low=o["cost_low"] / best["cost_high"],
                 ratio_high=o["cost_high"] / best["cost_low"])


def cheapest(runs: pd.DataFrame, targets: Iterable[tuple[str, float]], *, cost_kinds: Sequence[str] = COST_KINDS,
             work_count: str | None = None, work_resolution: float = WORK_RESOLUTION,
             wall_resolution: float = WALL_RESOLUTION) -> pd.DataFrame:
    """The cheapest table: one row per (scene, metric, target, cost kind, integrator); see the
    module's docstring for the definitions.

    ``targets``: (metric column, target value) pairs, e.g. ``[("energy_error", 1e-4)]``.
    ``cost_kinds``: ``"wall"`` needs the columns `WALL_COLUMNS`; ``"work"`` the column
    ``work_count``, or when None the one `work_column` picks (``flops`` when present, else
    ``work_evals``). Every integrator of a scene has a row (``not reached`` when it finished no run)."""
    targets = list(targets)
    resolution = {"work": work_resolution, "wall": wall_resolution}
    _check_arguments(targets, resolution, cost_kinds)
    work = work_count or work_column(runs)
    columns = {"wall": WALL_COLUMNS, "work": (work, "", "")}
    _check_table(runs, [m for m, _ in targets], [c for k in cost_kinds for c in columns[k] if c])
    curves = _curves(runs)
    same_as = identical_methods(runs)
    out = []
    for metric, target in targets:
        for kind in cost_kinds:
            for scene in sorted(runs["scene"].unique()):
                rows = []
                for (s, integ), sweeps in curves.items():
                    if s != scene:
                        continue
                    for sweep, curve in sweeps.items():
                        twins = sorted(b for (sc, b, sw), a in same_as.items() if (sc, a, sw) == (scene, integ, sweep))
                        entry = entry_name(integ, sweep, len(sweeps) > 1, twins)
                        kept = same_as.get((scene, integ, sweep))
                        if kept:  # the same trajectory as another method: ranked once, as that one
                            found = {"verdict": "identical",
                                     "note": f"the same trajectory as `{kept}` on this scene ({IDENTICAL_RULE}): "
                                             f"ranked once, as `{kept}`"}
                        else:
                            found = _curve_cost(curve, metric, target, columns[kind], resolution[kind])
                        rows.append({"scene": scene, "metric": metric, "target": float(target), "cost_kind": kind,
                                     "integrator": integ, "entry": entry, "sweep": sweep,
                                     "cost_column": columns[kind][0], **found})
                _verdicts(rows)
                out += rows
    table = pd.DataFrame(out, columns=COLUMNS)
    order = {v: k for k, v in enumerate(VERDICTS)}
    return (table.assign(_v=table["verdict"].map(order))
            .sort_values(["metric", "target", "cost_kind", "scene", "_v", "cost", "entry"], kind="stable")
            .drop(columns="_v").reset_index(drop=True))


# ------------------------------------------------------------------------------------------
# Summary lines
# ------------------------------------------------------------------------------------------
def _times(x: float) -> str:
    """A ratio as text: two decimals below 10 (so 1.04 never prints as "1×"), else 3 digits."""
    return f"{x:.2f}×" if x < 10 else f"{x:.3g}×"


def _amount(r: dict) -> str:
    unit = " s" if r["cost_kind"] == "wall" else (" flop" if r["cost_column"] == "flops" else " evaluations")
    return f"{r['cost']:.3g}{unit} ({r['cost_low']:.3g}–{r['cost_high']:.3g})"


def _relative(r: dict) -> str:
    return f"{_times(r['ratio'])} ({_times(r['ratio_low'])}–{_times(r['ratio_high'])})"


def _verdict_text(g: pd.DataFrame) -> str:
    rows = g.to_dict("records")
    by = {v: [r for r in rows if r["verdict"] == v] for v in VERDICTS}
    what = "wall time" if rows[0]["cost_kind"] == "wall" else f"work ({rows[0]['cost_column']})"
    parts = []
    if by["winner"]:
        w = by["winner"][0]
        if by["slower"]:
            n = by["slower"][0]
            parts.append(f"by {what}, `{w['entry']}` is cheapest, {_amount(w)}; the next, `{n['entry']}`, "
                         f"costs {_relative(n)} as much")
        else:
            parts.append(f"by {what}, only `{w['entry']}` reached it, {_amount(w)}")
    elif by["tie"]:
        first, rest = by["tie"][0], by["tie"][1:]
        names = f"`{first['entry']}` {_amount(first)}" + "".join(
            f", `{r['entry']}` {_relative(r)}" for r in rest)
        parts.append(f"by {what}, a tie of {len(by['tie'])}: {names}")
        if by["slower"]:
            n = by["slower"][0]
            parts.append(f"the next outside the tie, `{n['entry']}`, costs {_relative(n)} as much")
    else:
        parts.append(f"by {what}, no method reached it")
    bounded = _bounded_text(by["winner"] + by["tie"])
    if bounded:
        parts.append(bounded)
    if by["not measured"]:
        parts.append("no cost for " + ", ".join(f"`{r['entry']}`" for r in by["not measured"]))
    return "; ".join(parts)


_BOUND_WORDS = {"stability": "by the stability limit (coarser steps did not finish)",
                "failures": "by failures (coarser tolerances did not finish)",
                "cliff": "by a cliff (the next coarser setting is no longer a solution)",
                "sweep range": "by the sweep's range (its coarsest setting already meets the target)"}


def _bounded_text(rows: list[dict]) -> str:
    """Which of the ranked methods' costs are bounded by something other than accuracy (they may
    be cheaper than stated), e.g. "cost of `lgvi` bounded by the sweep's range"."""
    by_bound: dict[str, list[str]] = {}
    for r in rows:
        b = r.get("bound")
        if isinstance(b, str) and b in _BOUND_WORDS:
            by_bound.setdefault(b, []).append(f"`{r['entry']}`")
    return "; ".join(f"cost of {', '.join(names)} bounded {_BOUND_WORDS[b]}, not by the target"
                     for b, names in by_bound.items())


def summary_lines(table: pd.DataFrame, labels: dict[str, str] | None = None) -> list[str]:
    """One Markdown bullet per (scene, metric, target) of a `cheapest` table, every cost kind in
    it: the winner and the next method's cost ratio with its range, or the tie and its members'
    ratios to the cheapest; the methods that did not reach the target are counted.
    ``labels`` maps a metric to its words (default: the column name)."""
    labels = labels or {}
    lines = []
    for (metric, target, scene), g in table.groupby(["metric", "target", "scene"], sort=False):
        texts = [_verdict_text(k) for _, k in g.groupby("cost_kind", sort=False)]
        missed = sorted(set(g.loc[g["verdict"] == "not reached", "entry"]))
        if missed:
            texts.append(f"not reached by {', '.join(f'`{m}`' for m in missed)}")
        lines.append(f"- **{scene}**, {labels.get(metric, metric)} ≤ {target:g}: "
                     + ". ".join(t[0].upper() + t[1:] for t in texts) + ".")
    return lines


# ------------------------------------------------------------------------------------------
# Runs that did not finish, and why that was expected (or not)
# ------------------------------------------------------------------------------------------
#: Statuses that end a run by its budget, not by a failure of the method.
BUDGET_STATUSES = ("max_steps", "time_limit")

#: Why a run did not finish: the key, and the words that follow a count ("19 ...").
CAUSES = {
    "beyond the stability map's limit": "at a step larger than the method's largest stable step in the stability map",
    "beyond its largest finishing step": "at a step larger than every step at which the same method finished the scene",
    "budget": "stopped by their step or time budget",
    "no finished run": "of a method that finished no fixed-step run of the scene",
    "within its finishing range": "failed although the same method finished the scene with a larger step",
    "inaccurate": "finished with an error beyond a sanity bound (no longer a solution)",
    "adaptive": "adaptive runs that did not finish",
    "error": "raised an exception (a bug)",
}
#: An inaccurate run is expected: a method's coarsest settings may be too coarse to solve the
#: scene (the sweep reaches beyond the accuracy range on purpose, to find where it ends).
EXPECTED_CAUSES = ("beyond the stability map's limit", "beyond its largest finishing step", "budget", "inaccurate")


def failure_causes(runs: pd.DataFrame, stability: pd.DataFrame | None = None) -> pd.DataFrame:
    """Every run whose status is not ``ok``, with its cause (a key of `CAUSES`).

    A fixed-step failure is *beyond the stability map's limit* when ``stability`` (the stability
    map's table: scene, integrator, largest_stable_dt) has the same scene and method with a
    smaller largest stable step; else *beyond its largest finishing step* when the same method
    finished the same scene at a smaller step but at no step as large (the sweep's own evidence
    of its stability limit, to the sweep's resolution)."""
    missing = [c for c in _KEY_COLUMNS if c not in runs]
    if missing:
        raise ValueError(f"failure_causes: the runs table has no column(s) {', '.join(missing)}")
    limits = {}
    if stability is not None:
        miss = [c for c in ("scene", "integrator", "largest_stable_dt") if c not in stability]
        if miss:
            raise ValueError(f"failure_causes: the stability table has no column(s) {', '.join(miss)}")
        limits = {(r.scene, r.integrator): r.largest_stable_dt for r in stability.itertuples()
                  if np.isfinite(r.largest_stable_dt)}
    finished = runs[(runs["status"] == "ok") & runs["dt"].notna()].groupby(["scene", "integrator"])["dt"]
    largest_ok = finished.max().to_dict()
    out = []
    for r in runs[runs["status"] != "ok"].itertuples():
        key = (r.scene, r.integrator)
        if r.status in BUDGET_STATUSES:
            cause = "budget"
        elif r.status == INACCURATE:
            cause = "inaccurate"
        elif r.status == "error":
            cause = "error"
        elif pd.isna(r.dt):
            cause = "adaptive"
        elif key in limits and r.dt > limits[key]:
            cause = "beyond the stability map's limit"
        elif key not in largest_ok:
            cause = "no finished run"
        elif r.dt > largest_ok[key]:
            cause = "beyond its largest finishing step"
        else:
            cause = "within its finishing range"
        out.append({"scene": r.scene, "integrator": r.integrator, "setting": r.setting, "status": r.status,
                    "cause": cause, "largest_finished_dt": largest_ok.get(key, np.nan),
                    "stable_dt_in_map": limits.get(key, np.nan)})
    return pd.DataFrame(out, columns=["scene", "integrator", "setting", "status", "cause", "largest_finished_dt",
                                      "stable_dt_in_map"])


def failure_summary(runs: pd.DataFrame, stability: pd.DataFrame | None = None) -> str:
    """One sentence on the runs that did not finish: how many, and whether all were expected
    (e.g. "19 of 147 runs not ok, all expected: 19 at a step larger than every step at which the
    method finished the scene (diverged 17, length_limit 1, newton_failed 1)."), naming the
    unexpected ones."""
    causes = failure_causes(runs, stability)
    if causes.empty:
        return f"All {len(runs)} runs ok."
    expected = causes[causes["cause"].isin(EXPECTED_CAUSES)]
    other = causes[~causes["cause"].isin(EXPECTED_CAUSES)]
    parts = []
    for cause, g in expected.groupby("cause", sort=True):
        counts = g["status"].value_counts().sort_index()
        parts.append(f"{len(g)} {CAUSES[cause]} ({', '.join(f'{s} {n}' for s, n in counts.items())})")
    head = f"{len(causes)} of {len(runs)} runs not ok, "
    if other.empty:
        return head + "all expected: " + "; ".join(parts) + "."
    named = ", ".join(f"`{r.integrator}` {r.setting} on {r.scene} ({r.status}, {r.cause})" for r in other.itertuples())
    return head + (f"{len(expected)} expected: " + "; ".join(parts) + "; " if parts else "") + \
        f"{len(other)} not explained by a stability limit or a budget: {named}."
