"""The grid sweep's words: results/grid/README.md from its runs table.

The grid sweep (`python -m benchmark run`) measures every method on a fixed step and tolerance
grid; its README describes the table, the time per evaluation, the failures and why they were
expected, the reproducibility statement against an earlier table, the observed orders and the
statuses. It gives no verdict: which method to use and what it costs is the answer's
(`benchmark.answer.answer`, ``python -m benchmark answer`` -> results/README.md), by search and paired
timing. Generated from the data, never edited by hand.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from reelbench.benchmark.runs.metrics import ACCURACY, WORK_DEFINITION
from reelbench.benchmark.core.policy import ROW_IDENTITY
from reelbench.benchmark.runs.ranking import failure_summary
from reelbench.benchmark.core.reference import REFERENCE_METHOD
from reelbench.benchmark.runs.sweep import MAX_REPEATS, MIN_REPEATS, TIMING_BUDGET
from reelbench.benchmark.core.report import Provenance, code_list, markdown_table
from reelbench.models.io import atomic_write_text
from reelbench.integrators.base import FINISHED_STATUSES

def horizons_text(horizons: dict | None) -> str:
    """One sentence on the horizons a result covers, e.g. {"sweep": 1.0, "energy study": 10.0};
    None for a horizon means each scene's own t_end, 0 means not run."""
    if not horizons:
        return ""
    parts = []
    for what, h in horizons.items():
        if h is None:
            parts.append(f"{what}: each scene's own t_end")
        elif h == 0:
            parts.append(f"{what}: not run")
        else:
            parts.append(f"{what}: {h:g} s")
    return "Horizons — " + "; ".join(parts) + "."


# ------------------------------------------------------------------------------------------
# Time per evaluation
# ------------------------------------------------------------------------------------------
def implementations(runs: pd.DataFrame) -> pd.Series:
    """Each row's declared implementation ("" where the table or the method has none)."""
    if "implementation" not in runs:
        return pd.Series("", index=runs.index)
    impl = runs["implementation"]
    return impl.astype(object).where(impl.notna(), "").astype(str)


def evaluation_costs(runs: pd.DataFrame) -> pd.DataFrame:
    """µs of run time per right-hand-side evaluation of each method over its finished runs
    (median and range), by implementation; a method without an evaluation count says so."""
    ok = runs[runs["status"].isin(FINISHED_STATUSES)].assign(implementation=implementations(runs))
    rows = []
    for (impl, name), g in ok.groupby(["implementation", "integrator"], sort=True):
        v = pd.to_numeric(g["us_per_eval"], errors="coerce") if "us_per_eval" in g else pd.Series(dtype=float)
        v = v[np.isfinite(v)]
        rows.append({"implementation": impl or "(not declared)", "integrator": name, "runs": len(g),
                     "us_per_eval_median": float(v.median()) if len(v) else np.nan,
                     "us_per_eval_min": float(v.min()) if len(v) else np.nan,
                     "us_per_eval_max": float(v.max()) if len(v) else np.nan,
                     "note": "" if len(v) else "no right-hand-side evaluations counted (its own discrete equations, or no count): see flops"})
    return pd.DataFrame(rows, columns=["implementation", "integrator", "runs", "us_per_eval_median", "us_per_eval_min",
                                       "us_per_eval_max", "note"])


def timing_text(runs: pd.DataFrame) -> str:
    """How the run times were measured, from the rows: repeats, load, and the wall resolution."""
    ok = runs[runs["status"].isin(FINISHED_STATUSES)]
    reps = pd.to_numeric(ok.get("timing_repeats", pd.Series(dtype=float)), errors="coerce").dropna()
    load = pd.to_numeric(ok.get("load_avg", pd.Series(dtype=float)), errors="coerce").dropna()
    parts = []
    if len(reps):
        spread = f"{reps.min():.0f}" if reps.min() == reps.max() else f"{reps.min():.0f}–{reps.max():.0f}"
        parts.append(f"each finished run was timed {spread} times (median {reps.median():.0f})")
    if len(load):
        parts.append(f"the 1-minute load when the rows ran was {load.min():.1f}–{load.max():.1f}")
    missing = len(ok) - len(reps)
    if missing:
        parts.append(f"{missing} finished row(s) come from an older table without a timing spread (their interval is "
                     "the resolution alone)")
    return ("Timing: " + "; ".join(parts) + ". " if parts else "") + (
        "Run times of a few ms move by up to 2× between sweeps on a shared machine, so the sweep's single solves "
        "rank nothing; paired timing does (`python -m benchmark answer`).")


# ------------------------------------------------------------------------------------------
# Against an earlier table
# ------------------------------------------------------------------------------------------
def reproducibility(before: pd.DataFrame, runs: pd.DataFrame, label: str) -> str:
    """The reproducibility statement (`benchmark.runs.reproducibility.statement`) over the runs both
    tables have; the rows only one has are counted, not compared."""
    from reelbench.benchmark.runs import reproducibility as repro

    missing = [c for c in ("scene", "integrator", "setting", "dt", "rtol", "status", "steps") if c not in before]
    if missing:
        return f"{label} has no column(s) {', '.join(missing)}: no reproducibility statement.\n\n"
    key = repro.KEY
    common = before[key].merge(runs[key], on=key)
    if common.empty:
        return f"{label} has no run in common with this table (same scene, integrator and setting): nothing compared.\n\n"
    a = before.merge(common, on=key)
    b = runs.merge(common, on=key)
    only = len(before) + len(runs) - 2 * len(common)
    text = repro.statement(repro.compare_runs(a, b))
    tail = f" ({only} row(s) in only one of the two tables were not compared.)" if only else ""
    return f"Against {label}: {text}{tail}\n\n"


def changes_since(before: pd.DataFrame, runs: pd.DataFrame, label: str) -> str:
    """What changed against an earlier run's table ``before``: the reproducibility statement and
    each method's median speed-up on the runs both tables finished."""
    # an earlier table is the user's file: a number column holding text is not a number
    numeric = [c for c in ("run_time", "run_time_low", "run_time_high", "flops", "work_evals", "steps", "dt", "rtol",
                           "t_end", *ACCURACY) if c in before]
    before = before.assign(**{c: pd.to_numeric(before[c], errors="coerce") for c in numeric})
    out = [f"## Compared with {label}\n\n", reproducibility(before, runs, label)]
    key = list(ROW_IDENTITY)
    both = before[before["status"].isin(FINISHED_STATUSES)].merge(runs[runs["status"].isin(FINISHED_STATUSES)], on=key, suffixes=("_then", "_now"))
    if not both.empty and "run_time_then" in both:
        speed = (both["run_time_then"] / both["run_time_now"]).groupby(both["integrator"]).median()
        counts = both.groupby("integrator").size()
        out.append("Median speed-up of each method (run time then / now, over the "
                   f"{len(both)} runs both tables finished; each table's `run_time` as it defines it: tables "
                   "before the timing spread hold the fastest of the repeats, later ones the median):\n\n"
                   "| integrator | runs | speed-up |\n|---|---|---|\n")
        for name, v in speed.sort_values(ascending=False).items():
            out.append(f"| {name} | {counts[name]} | {v:.3g}× |\n")
        out.append("\n")
    new = sorted(set(runs["integrator"]) - set(before["integrator"]))
    if new:
        out.append(f"New in this run: {code_list(new)}.\n\n")
    return "".join(out)


# ------------------------------------------------------------------------------------------
# results/README.md
# ------------------------------------------------------------------------------------------
TRUST = """## What is checked before it is trusted

A run that resumes keeps a row of `runs.csv` only when it passes its checks: its status is one
of the table's statuses, its numbers are numbers in their ranges (counts, errors and costs
finite and non-negative, `run_time_low` ≤ `run_time` ≤ `run_time_high`, errors only for
finished runs), and every column (settings, status, counts, errors, timings, flops, keys) still
matches the digest (`row_digest`) written with it; a row without a digest in a table whose
other rows have one is not trusted, and rows from before digests are kept only with an explicit
`--accept-legacy`. A row that fails is named in a warning and recomputed (a row outside the run
is set aside in `runs.rejected.csv`). A table that cannot be read whole (a stray byte, binary,
a repeated row) is copied intact to `runs.unreadable-TIME.csv` and its readable rows salvaged. Cached reference
solutions (`cache/`) carry their identity and a SHA-256 checksum of their arrays, and one that
does not match is recomputed. Both protect against accidents — a hand edit, a damaged or
truncated file, a file from another problem or other code — not against a deliberate edit that
recomputes the digest or the checksum: that takes recomputing the results (`--fresh`, or
deleting `cache/`) or comparing them with another machine's (`--compare-with`).
"""


def _figure_lines(figures: list[tuple[str, str]]) -> str:
    return "\n".join(f"- [{name}]({name})" + (f" — {note}" if note else "") for name, note in figures)


def write_readme(out_dir: Path, runs: pd.DataFrame, orders: pd.DataFrame | None, *, provenance: Provenance,
                 figures: list, horizons: dict | None = None, compared: str = "", failures: str | None = None,
                 merged: str = "", energy_csv: Path | None = None) -> Path:
    """README.md of the grid sweep's (merged) runs table. ``figures``: file names, or (name, note)
    pairs; ``failures``: the failure sentence (`benchmark.runs.ranking.failure_summary`, computed when
    not given); ``merged``: what this run added to the table; ``energy_csv``: the energy study's
    table (default: ``out_dir``/energy_horizon.csv)."""
    failures = failure_summary(runs) if failures is None else failures
    figures = [(f, "") if isinstance(f, str) else tuple(f) for f in figures]
    status = runs.groupby(["integrator", "status"]).size().unstack(fill_value=0).reset_index()
    ref = REFERENCE_METHOD
    per_eval = evaluation_costs(runs)
    from reelbench.benchmark.studies.orders import section as orders_section
    from reelbench.benchmark.studies.properties import properties_text

    text = f"""# Grid sweep results

{provenance.header()}
{horizons_text(horizons)}
{merged}

Which method to use and what it costs is the main job's answer (`python -m benchmark answer` ->
`results/README.md`: each method's cheapest setting at each target by search, wall times by paired
timing); this sweep measures every method on a fixed grid of steps and tolerances and ranks nothing.

`runs.csv` has one row per run (scene × integrator × setting) with status, cost and accuracy;
`runs.md` is the same as a table. Run time is the whole `solve()` call (output conversion included, e.g.
the LGVI's velocity recovery) minus its compilation, timed in a separate pass from the error
computation: `run_time` is the median of `timing_repeats` solves (as many as fit in a {TIMING_BUDGET:g} s budget,
{MIN_REPEATS} to {MAX_REPEATS}; one when a single solve takes longer), `run_time_low` the fastest, `run_time_high` the
90th percentile (10 or more solves) or the slowest, `load_avg` the machine's 1-minute load when
the row ran. `us_per_eval` is the run time per right-hand-side evaluation (empty for a method that counts none, e.g. the
LGVI), `flops` the run's floating-point operations (XLA's cost model of one compiled step or right-hand side
times the counts; `flops_note` says how, or why a row has none) and `implementation`
the method's declared kind (`jax-compiled` or `scipy-python`).
Errors are against a {ref["integrator"].upper()} reference at rtol {ref["rtol"]:g} / atol {ref["atol"]:g} on the same model. Every row
names the right-hand side it ran (`rhs`: the O(N) closed form unless a run asked for `autodiff`).
Work, for comparing methods independently of this machine, is counted in one unit: `flops`, the
bottom row of the work-precision figures. The raw counts keep their own
columns (`rhs_evals`, `newton_iterations`, `jac_evals`, `lu_decompositions`); `work_evals` is their sum
in unlike units ({WORK_DEFINITION}), kept to compare with tables from before `flops`. Energy error is max|ΔE|/max T
(max|Δ(E − W)|/max T with Carnot loss or reel control), as in the paper.

{timing_text(runs)}

### Time per evaluation, by implementation

{markdown_table(per_eval)}
## Runs that did not finish

{failures}

{markdown_table(status)}
{compared}{orders_section(orders)}
{properties_text(runs, Path(out_dir) / "energy_horizon.csv" if energy_csv is None else energy_csv)}
{TRUST}
## Figures

{_figure_lines(figures)}
"""
    text = re.sub(r"\n{3,}", "\n\n", text)
    path = Path(out_dir) / "README.md"
    atomic_write_text(path, text)
    return path


def failure_sentence(runs: pd.DataFrame, stability_csv: Path | None = None) -> str:
    """`benchmark.runs.ranking.failure_summary` with the stability map's table when there is one."""
    stability = None
    if stability_csv is not None and Path(stability_csv).is_file():
        try:
            stability = pd.read_csv(stability_csv)
            if not {"scene", "integrator", "largest_stable_dt"} <= set(stability.columns):
                stability = None
        except Exception:  # an unreadable map only loses its evidence, not the summary
            stability = None
    return failure_summary(runs, stability)

