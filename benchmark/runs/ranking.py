"""What is ranked and how: the entries a verdict ranks, the work verdicts that call a tie a tie,
and why runs failed. Pure functions of table rows; nothing here runs a solve.

**Entries.** A method with a fixed-step and an adaptive axis on one scene is two entries, ranked
apart like two methods (`entry_name`: ``tsit5 (fixed dt)``, ``tsit5 (adaptive)``): a fixed step
and an error-controlled step are two ways to use it. Methods shown to compute one trajectory are
one entry (``lgvi = lgvi_sym``), the method first in `benchmark.runs.sweep.PRESENTATION_ORDER`
(`presentation_rank`) named first.

**Work verdicts** (`work_verdicts`). Among the entries with a cost and an interval
(``cost_low`` .. ``cost_high``), the one of lowest cost is the ``winner`` only when its
``cost_high`` is below every other entry's ``cost_low``; otherwise it and every entry whose
interval overlaps its interval are a ``tie``. The rest are ``slower``.

**Failures** (`failure_causes`, `failure_summary`). Every run that did not finish, with its
cause, and whether a stability limit or a budget explains it.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

from reelbench.benchmark.core.policy import ROW_IDENTITY, SLOWER, TIE, WINNER
from reelbench.benchmark.runs.sweep import PRESENTATION_ORDER, SWEEP_WORDS
from reelbench.integrators.base import BUDGET_STATUSES, ERROR, FINISHED_STATUSES, INACCURATE  # a budget ends a run, not a failure of the method

#: The columns `failure_causes` reads from a runs table.
_KEY_COLUMNS = (*ROW_IDENTITY, "dt", "rtol", "status")


def entry_name(integrator: str, sweep: str, both_sweeps: bool, twins: Sequence[str] = ()) -> str:
    """What one row ranks: the method, with its sweep's words (``tsit5 (fixed dt)``, ``tsit5
    (adaptive)``) when it has settings on both axes of the scene, and the methods ranked as it
    (one trajectory) after "=" (``lgvi = lgvi_sym``)."""
    name = f"{integrator} ({SWEEP_WORDS[sweep]})" if both_sweeps else integrator
    return " = ".join([name, *twins])


def presentation_rank(name: str) -> tuple:
    """The sort key of a method's name: its place in `benchmark.runs.sweep.PRESENTATION_ORDER`, then
    the name (a method outside the order comes after every method in it)."""
    return (PRESENTATION_ORDER.index(name) if name in PRESENTATION_ORDER else len(PRESENTATION_ORDER), name)


def work_verdicts(rows: list[dict]) -> None:
    """Set ``verdict`` and the ratios to the cheapest (``ratio``, ``ratio_low``, ``ratio_high``)
    in place for the rows of one (scene, metric, target, cost kind): the rows with a finite
    ``cost`` are ranked (`winner`, `tie`, `slower`, see the module's docstring), the others are
    left as they are."""
    reached = sorted((r for r in rows if np.isfinite(r.get("cost", np.nan))), key=lambda r: (r["cost"], r["entry"]))
    if not reached:
        return
    best, others = reached[0], reached[1:]
    alone = all(best["cost_high"] < o["cost_low"] for o in others)
    best["verdict"] = WINNER if alone else TIE
    best.update(ratio=1.0, ratio_low=1.0, ratio_high=1.0)
    for o in others:
        o["verdict"] = TIE if (not alone and o["cost_low"] <= best["cost_high"]) else SLOWER
        o.update(ratio=o["cost"] / best["cost"], ratio_low=o["cost_low"] / best["cost_high"],
                 ratio_high=o["cost_high"] / best["cost_low"])


# ------------------------------------------------------------------------------------------
# Runs that did not finish, and why that was expected (or not)
# ------------------------------------------------------------------------------------------

#: Why a run did not finish: the key, and the words that follow a count ("19 ...").
CAUSES = {
    "beyond the stability map's limit": "at a step larger than the method's largest stable step in the stability map",
    "beyond its largest finishing step": "at a step larger than every step at which the same method finished the scene",
    "budget": "stopped by their step or time budget",
    "no finished run": "of a method that finished no fixed-step run of the scene",
    "within its finishing range": "failed although the same method finished the scene with a larger step",
    INACCURATE: "finished with an error beyond a sanity bound (no longer a solution)",
    "adaptive": "adaptive runs that did not finish",
    ERROR: "raised an exception (a bug)",
}
#: An inaccurate run is expected: a method's coarsest settings may be too coarse to solve the
#: scene (the sweep reaches beyond the accuracy range on purpose, to find where it ends).
EXPECTED_CAUSES = ("beyond the stability map's limit", "beyond its largest finishing step", "budget", INACCURATE)


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
    finished = runs[(runs["status"].isin(FINISHED_STATUSES)) & runs["dt"].notna()].groupby(["scene", "integrator"])["dt"]
    largest_ok = finished.max().to_dict()
    out = []
    for r in runs[~runs["status"].isin(FINISHED_STATUSES)].itertuples():
        key = (r.scene, r.integrator)
        if r.status in BUDGET_STATUSES:
            cause = "budget"
        elif r.status == INACCURATE:
            cause = INACCURATE
        elif r.status == ERROR:
            cause = ERROR
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
