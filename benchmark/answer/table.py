"""The answer table, ``cheapest.csv``: one row per scene × N × metric × target × cost kind ×
method, from the searches' rows (``search.csv``: the work rows, ranked by flops) and the paired
timings' rows (``timing.csv``: the wall rows, ranked by paired wall time).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from typing import TYPE_CHECKING

import numpy as np

from reelbench.benchmark.answer import paired as _paired
from reelbench.benchmark.answer.jobs import TWIN_COLUMNS, setting_text, twins
from reelbench.benchmark.core.policy import BEST_VERDICTS, IDENTICAL, LOWER_BOUND, NO_FLOPS_COUNT, NOT_REACHED, SLOWER
from reelbench.benchmark.core.store import frame

if TYPE_CHECKING:
    import pandas as pd

#: Columns of cheapest.csv.
COLUMNS = ["scene", "elements", "metric", "target", "cost_kind", "integrator", "entry", "sweep", "setting", "setting_low",
           "setting_high", "bound", "cost", "cost_low", "cost_high", "ratio", "ratio_low", "ratio_high", "pairs",
           "verdict", "cost_column", "error", "runs", "note"]

#: The note of a work cost that is only a lower bound (`benchmark.work.flops.counting_rule`
#: "evaluations"): one below the winner's has the verdict `LOWER_BOUND` (it cannot be ranked).
LOWER_BOUND_NOTE = ("its flops count right-hand sides, Jacobians and LU factorisations only (its Newton solves "
                    "and stage arithmetic left out): a lower bound of its work, ranked only where it is above "
                    "the winner's")


def answer_table(searched: pd.DataFrame, timed: pd.DataFrame) -> pd.DataFrame:
    """cheapest.csv: per scene × N × metric × target, the work rows (every entry, a method on
    one axis, that reached the target, by its searched cost in flops: winner when its cost, with
    the bracket's 10 % below it, stays below every other's, else tie) and the wall rows (the
    paired timing's ratios, intervals, pairs and verdicts)."""
    rows = []
    for (scene, n, metric, target), g in searched.groupby(["scene", "elements", "metric", "target"], sort=True):
        place = dict(scene=scene, elements=int(n), metric=metric, target=target)
        identical, work = _work_rows(g, place)
        rows += identical + work
        t = timed[(timed["scene"] == scene) & (timed["elements"] == n) & (timed["metric"] == metric)
                  & (timed["target"] == target)] if len(timed) else timed
        if len(t):
            rows += _wall_rows(t.iloc[0], work, place)
    return frame(rows, COLUMNS, extra=False)


def _work_rows(g: pd.DataFrame, place: dict) -> tuple[list[dict], list[dict]]:
    """(the rows of the searches bit-identical to another's, every other entry's work row with
    its verdict) of one scene × N × metric × target's searches ``g``, in the order they are written."""
    from reelbench.benchmark.runs.ranking import entry_name, presentation_rank, work_verdicts

    rows, work, same = [], [], twins(g)
    axes = g.groupby("integrator")["sweep"].nunique().to_dict()
    for (integ, sweep), h in g.groupby(["integrator", "sweep"], sort=True):
        r = h.iloc[0]
        if (integ, sweep) in same:
            rows.append(dict(**place, cost_kind="work", integrator=integ,
                             entry=entry_name(integ, sweep, axes[integ] > 1), sweep=sweep,
                             setting=setting_text(sweep, r["setting"]), verdict=IDENTICAL, cost_column=r["cost_column"],
                             error=r["error"], runs=r["runs"],
                             note=f"its search is bit-identical to {same[(integ, sweep)]}'s "
                                  f"({', '.join(TWIN_COLUMNS)}): ranked as one entry"))
            continue
        mates = sorted((i for (i, sw), m in same.items() if m == integ and sw == sweep), key=presentation_rank)
        base = dict(**place, cost_kind="work", integrator=integ, entry=entry_name(integ, sweep, axes[integ] > 1, mates),
                    sweep=sweep, setting=setting_text(sweep, r["setting"]), setting_low=r["setting_low"],
                    setting_high=r["setting_high"], bound=r["bound"], cost_column=r["cost_column"], error=r["error"],
                    runs=r["runs"], note=r.get("note", ""))
        base.update(_work_cost(integ, r))
        work.append(base)
    work_verdicts([w for w in work if w.get("verdict") != LOWER_BOUND])
    _rank_lower_bounds(work)
    return rows, work


def _work_cost(integ: str, r) -> dict:
    """The cost columns (and verdict, where the cost decides it) of one search's work row."""
    spread = r["spread"] if np.isfinite(r.get("spread", np.nan)) else 0.0
    if np.isfinite(r["setting"]) and r["cost_column"] != "flops":
        # a cost in another unit (steps: a method XLA's cost model cannot count) is no
        # point on the flops axis: it reached the target, but is not ranked by work
        return dict(cost=np.nan, verdict=NO_FLOPS_COUNT,
                    note=f"its cost at the target is {r['cost']:.4g} {r['cost_column']}, not flops: not ranked by work")
    if np.isfinite(r["setting"]) and _counts_whole_step(integ):
        # the cost at the target lies between the bracket's coarser end and its answer
        return dict(cost=r["cost"], cost_low=r["cost"] / (1.0 + max(spread, 0.0)), cost_high=r["cost"])
    if np.isfinite(r["setting"]):
        # counted by its evaluations alone (Radau: its Newton solves left out): the work is
        # at least this, so it can show a method slower, never make one the winner
        return dict(cost=r["cost"], cost_low=r["cost"] / (1.0 + max(spread, 0.0)), cost_high=np.inf,
                    verdict=LOWER_BOUND, note=LOWER_BOUND_NOTE)
    return dict(cost=np.nan, verdict=NOT_REACHED)


def _wall_rows(timing, work: list[dict], place: dict) -> list[dict]:
    """The wall rows of one paired timing (a row of timing.csv), each method named as its work row."""
    # the timing names each method as `run_timing` does, without its twins
    by_entry = {**{r["entry"].split(" = ")[0]: r for r in work}, **{r["integrator"]: r for r in work}}
    # the verdicts of today's rule (`benchmark.answer.paired.verdicts`), not those stored with the timing
    stored = [_paired.Ratio(**r) for r in json.loads(timing["ratios"] or "[]")]
    rows = []
    for ratio in [asdict(r) for r in (_paired.verdicts(stored) if stored else [])]:
        w = by_entry.get(ratio["method"], {})
        rows.append(dict(**place, cost_kind="wall", integrator=w.get("integrator", ratio["method"]),
                         entry=w.get("entry", ratio["method"]), sweep=w.get("sweep", ""), setting=w.get("setting", ""),
                         cost=ratio["time"], ratio=ratio["ratio"], ratio_low=ratio["low"], ratio_high=ratio["high"],
                         pairs=ratio["pairs"], verdict=ratio["verdict"], cost_column="run_time (paired)",
                         note=timing.get("note", "")))
    return rows


def _counts_whole_step(integrator: str) -> bool:
    from reelbench.benchmark.work.flops import WHOLE_STEP_RULES, counting_rule

    try:
        return counting_rule(integrator) in WHOLE_STEP_RULES
    except ValueError:  # an integrator no longer registered: its count cannot be vouched for
        return False


def _rank_lower_bounds(work: list[dict]) -> None:
    """A lower-bound cost above the winner's (or the tie's best) cost interval is `slower`
    (its ratio interval open above); one below it stays a `LOWER_BOUND`, unranked."""
    ranked = [w for w in work if w.get("verdict") in BEST_VERDICTS]
    best = min(ranked, key=lambda w: (w["cost"], w["entry"])) if ranked else None
    for w in work:
        if w.get("verdict") == LOWER_BOUND and best is not None and w["cost_low"] > best["cost_high"]:
            w.update(verdict=SLOWER, ratio=w["cost"] / best["cost"], ratio_low=w["cost_low"] / best["cost_high"],
                     ratio_high=np.inf)
