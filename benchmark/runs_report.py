"""results/README.md, cheapest.csv and the project README's answer block: what the runs table
says, in words and tables, generated from the data (never edited by hand).

The grid's reading comes from `benchmark.cheapest`: each method's cost at a target read off its
own work–precision curve, with an interval, and a verdict that calls a tie a tie, by the one-unit
work (``flops`` when the table has it, else the RHS-equivalent count), every method ranked. The
sweep gives no wall-time verdict: a single solve of a few ms moves by up to 2× between sweeps
(`benchmark.cheapest.WALL_RESOLUTION`), so the wall-time answer comes from paired, interleaved
timing at searched settings (`benchmark.answer`, ``python -m benchmark answer``). Then the failures and why they were expected, the reproducibility
statement against an earlier table, the changes since it, the observed orders and the statuses.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from benchmark import cheapest as cheap
from benchmark.metrics import WORK_DEFINITION
from benchmark.reference import REFERENCE_METHOD
from benchmark.sweep import MAX_REPEATS, MIN_REPEATS, TIMING_BUDGET
from benchmark.report import Provenance, code_list, markdown_table
from models.io import atomic_write_text

TARGETS = (("energy_error", 1e-4, "energy error (relative to max T)"),
           ("position_error_final", 1e-6, "body position error at t_end (m)"))
LABELS = {metric: label for metric, _, label in TARGETS}
#: The implementation whose wall times are compared with each other (`Integrator.implementation`).
COMPILED = "jax-compiled"
#: The markers of the project README's generated answer block.
ANSWER_START, ANSWER_END = "<!-- answer:start -->", "<!-- answer:end -->"


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
# Cost at a target
# ------------------------------------------------------------------------------------------
def implementations(runs: pd.DataFrame) -> pd.Series:
    """Each row's declared implementation ("" where the table or the method has none)."""
    if "implementation" not in runs:
        return pd.Series("", index=runs.index)
    impl = runs["implementation"]
    return impl.astype(object).where(impl.notna(), "").astype(str)


def compiled_rows(runs: pd.DataFrame) -> tuple[pd.DataFrame, bool]:
    """(the rows ranked by wall time, whether they are the compiled implementations only): every
    row when no method declares its implementation (then nothing says which times compare)."""
    impl = implementations(runs)
    if (impl == COMPILED).any():
        return runs[impl == COMPILED], True
    return runs, False


#: Where the wall-time answer comes from (the sweep's single solves give none, `cheapest_table`).
WALL_ANSWER = ("by wall time: no verdict from the sweep's single solves (a run of a few ms moves by up to "
               f"{1 + cheap.WALL_RESOLUTION:g}× between sweeps); the wall-time answer is timed paired and "
               "interleaved at searched settings by `python -m benchmark answer` (`results/answer/cheapest.csv`)")


def cheapest_table(runs: pd.DataFrame) -> pd.DataFrame:
    """cheapest.csv: for every target, the work costs read off the grid among every method
    (`benchmark.cheapest.cheapest`). No wall-time rows: single solves cannot separate methods
    closer than `benchmark.cheapest.WALL_RESOLUTION`, and paired timing (`benchmark.answer`) can."""
    targets = [(m, t) for m, t, _ in TARGETS if m in runs]
    if runs.empty or not targets:
        return pd.DataFrame(columns=cheap.COLUMNS + ["among"])
    return cheap.cheapest(runs, targets, cost_kinds=["work"]).assign(among="every method")


def write_cheapest(out_dir: Path, table: pd.DataFrame) -> Path:
    path = Path(out_dir) / "cheapest.csv"
    atomic_write_text(path, table.to_csv(index=False))
    return path


def _unranked_by_wall(runs: pd.DataFrame) -> list[str]:
    impl = implementations(runs)
    return sorted(set(runs.loc[impl != COMPILED, "integrator"])) if (impl == COMPILED).any() else []


def answers(runs: pd.DataFrame, table: pd.DataFrame) -> str:
    """The cost sections of results/README.md from the cheapest table ``table``."""
    out = []
    out.append("### By wall time\n\n" + WALL_ANSWER[0].upper() + WALL_ANSWER[1:] + ".")
    others = _unranked_by_wall(runs)
    if others:
        out.append(f" Never ranked by wall time: {code_list(others)} (not compiled: their time is mostly the "
                   "interpreter between right-hand-side calls, see the µs per evaluation below).")
    out.append("\n\n")
    g = table[table["cost_kind"] == "work"]
    if not g.empty:
        col = g["cost_column"].iloc[0]
        what = ("floating-point operations (`flops`)" if col == "flops" else f"`{col}`: {WORK_DEFINITION}")
        out.append(f"### By work, among {g['among'].iloc[0]}, read off the step grid\n\n"
                   f"Work in {what}; two costs within {cheap.WORK_RESOLUTION:.0%} of each other are a tie. A cost "
                   "the grid bounds (`bound`: stability, sweep range) is an upper bound; the searched cost at each "
                   "target is `python -m benchmark answer`'s.\n\n")
        out.append("\n".join(cheap.summary_lines(g, LABELS)) + "\n\n")
    return "".join(out)


def evaluation_costs(runs: pd.DataFrame) -> pd.DataFrame:
    """µs of run time per right-hand-side evaluation of each method over its finished runs
    (median and range), by implementation; a method without an evaluation count says so."""
    ok = runs[runs["status"] == "ok"].assign(implementation=implementations(runs))
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
    ok = runs[runs["status"] == "ok"]
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
        f"Run times of a few ms move by up to {1 + cheap.WALL_RESOLUTION:g}× between sweeps on a shared machine, so "
        "the sweep gives no wall-time verdict; paired timing does (`python -m benchmark answer`).")


# ------------------------------------------------------------------------------------------
# The project README's answer block
# ------------------------------------------------------------------------------------------
def _short(g: pd.DataFrame) -> str:
    """One scene at one target and cost kind, in a few words: the winner and the factor to the
    next, or the tie."""
    win, tie = g[g["verdict"] == "winner"], g[g["verdict"] == "tie"]
    slower = g[g["verdict"] == "slower"]
    if len(win):
        w = win.iloc[0]
        nxt = (f", next `{slower.iloc[0]['entry']}` {cheap._relative(slower.iloc[0].to_dict())}"
               if len(slower) else "")
        return f"`{w['entry']}`{nxt}"
    if len(tie):
        return "tie of " + ", ".join(f"`{n}`" for n in tie["entry"])
    return "no method reached it"


def _power(x: float) -> str:
    """A target in few characters: 1e-4, 2.5e-7, 0.5."""
    if 1e-3 <= abs(x) < 1e4:
        return f"{x:.3g}"
    m, e = f"{x:.2e}".split("e")
    return f"{m.rstrip('0').rstrip('.')}e{int(e)}"


def answer_block(runs: pd.DataFrame, table: pd.DataFrame, failures: str) -> str:
    """Five lines for the project README when no searched answer is committed: per target, the
    verdicts by work read off the grid; where wall time comes from; the failures; how to read it."""
    lines = []
    for metric, target, label in TARGETS:
        k = table[(table["metric"] == metric) & (table["target"] == target) & (table["cost_kind"] == "work")]
        if k.empty:
            continue
        lines.append(f"- **{label[0].upper() + label[1:]} ≤ {_power(target)}** — by work, off the step grid: "
                     + "; ".join(f"{scene} {_short(s)}" for scene, s in k.groupby("scene")) + ".")
    lines.append(f"- A work verdict needs {cheap.WORK_RESOLUTION:.0%} between intervals; {WALL_ANSWER}.")
    lines.append(f"- {failures}")
    lines.append("- Generated from `results/runs.csv` by `python -m benchmark run`; each method's cost with its "
                 "interval: `results/cheapest.csv`; the reading: `results/README.md`.")
    return "\n".join(lines[:5]) + "\n"


def write_answer(readme: Path, block: str) -> str:
    """Replace the text between `ANSWER_START` and `ANSWER_END` in ``readme`` with ``block``,
    atomically; the rest of the file is untouched. Returns what it did, in words (without both
    markers, in order, it writes nothing)."""
    readme = Path(readme)
    try:
        text = readme.read_text(encoding="utf-8")
    except OSError as exc:
        return f"{readme} cannot be read ({exc.strerror or exc}): the answer block was not written"
    start, end = text.find(ANSWER_START), text.find(ANSWER_END)
    if start < 0 or end < start or text.count(ANSWER_START) != 1 or text.count(ANSWER_END) != 1:
        return (f"{readme} has no single {ANSWER_START} ... {ANSWER_END} pair: the answer block was not written "
                "(add the two markers where it belongs)")
    new = text[: start + len(ANSWER_START)] + "\n" + block + text[end:]
    if new == text:
        return f"{readme}: the answer block is unchanged"
    atomic_write_text(readme, new)
    return f"{readme}: the answer block between {ANSWER_START} and {ANSWER_END} was rewritten"


# ------------------------------------------------------------------------------------------
# Against an earlier table
# ------------------------------------------------------------------------------------------
def reproducibility(before: pd.DataFrame, runs: pd.DataFrame, label: str) -> str:
    """The reproducibility statement (`benchmark.reproducibility.statement`) over the runs both
    tables have; the rows only one has are counted, not compared."""
    from benchmark import reproducibility as repro

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
    """What changed against an earlier run's table ``before``: the reproducibility statement,
    each target's verdicts by work then and now (work: comparable across machines and timing
    methods), and each method's median speed-up on the runs both tables finished."""
    # an earlier table is the user's file: a number column holding text is not a number
    numeric = [c for c in (*cheap.WALL_COLUMNS, "flops", "work_evals", "steps", "dt", "rtol", "t_end", *LABELS)
               if c in before]
    before = before.assign(**{c: pd.to_numeric(before[c], errors="coerce") for c in numeric})
    out = [f"## Compared with {label}\n\n", reproducibility(before, runs, label)]
    targets = [(m, t) for m, t, _ in TARGETS if m in before and m in runs]
    # one unit then and now: flops where both tables have them, else the sum of counts
    count = "flops" if cheap.work_column(before) == cheap.work_column(runs) == "flops" else "work_evals"
    if targets and count in before and count in runs and "dt" in before and "rtol" in before:
        then, now = (cheap.cheapest(t, targets, cost_kinds=["work"], work_count=count) for t in (before, runs))
        out.append(f"Cheapest by work ({count}, the count both tables have), then and now:\n\n"
                   "| scene | target | then | now |\n|---|---|---|---|\n")
        for metric, target in targets:
            for scene in sorted(set(runs["scene"]) | set(before["scene"])):
                cells = []
                for t in (then, now):
                    g = t[(t["metric"] == metric) & (t["scene"] == scene)]
                    cells.append(_short(g) if len(g) else "not in the table")
                out.append(f"| {scene} | {LABELS[metric]} ≤ {target:g} | {cells[0]} | {cells[1]} |\n")
        out.append("\n")
    key = ["scene", "integrator", "setting"]
    both = before[before["status"] == "ok"].merge(runs[runs["status"] == "ok"], on=key, suffixes=("_then", "_now"))
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
                 figures: list, horizons: dict | None = None, compared: str = "", table: pd.DataFrame | None = None,
                 failures: str | None = None, merged: str = "") -> Path:
    """results/README.md from the (merged) runs table. ``figures``: file names, or (name, note)
    pairs; ``table``: the cheapest table (computed when not given); ``failures``: the failure
    sentence (`benchmark.cheapest.failure_summary`); ``merged``: what this run added to the table."""
    table = cheapest_table(runs) if table is None else table
    failures = cheap.failure_summary(runs) if failures is None else failures
    figures = [(f, "") if isinstance(f, str) else tuple(f) for f in figures]
    status = runs.groupby(["integrator", "status"]).size().unstack(fill_value=0).reset_index()
    ref = REFERENCE_METHOD
    per_eval = evaluation_costs(runs)
    from benchmark.orders import section as orders_section
    from benchmark.properties import properties_text

    text = f"""# Benchmark results

{provenance.header()}
{horizons_text(horizons)}
{merged}

`runs.csv` has one row per run (scene × integrator × setting) with status, cost and accuracy;
`runs.md` is the same as a table; `cheapest.csv` each method's cost at each target below, with
its interval and verdict. Run time is the whole `solve()` call (output conversion included, e.g.
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
ranking by work below and the bottom row of the work-precision figures. The raw counts keep their own
columns (`rhs_evals`, `newton_iterations`, `jac_evals`, `lu_decompositions`); `work_evals` is their sum
in unlike units ({WORK_DEFINITION}), kept to compare with tables from before `flops`. Energy error is max|ΔE|/max T
(max|Δ(E − W)|/max T with Carnot loss or reel control), as in the paper.

## What accuracy costs

Each method's cost at a target is read off its own work–precision curve (log–log between the two
settings that bracket the target, never extrapolated); a method is the winner only when its whole
interval lies below every other method's, otherwise the methods whose intervals overlap are a tie.
A cost *bounded by the stability limit or by the sweep's range* comes from the coarsest setting
that finished, which already met the target: the method may be cheaper than stated.

{answers(runs, table)}
{timing_text(runs)}

### Time per evaluation, by implementation

{markdown_table(per_eval)}
## Runs that did not finish

{failures}

{markdown_table(status)}
{compared}{orders_section(orders)}
{properties_text(runs, Path(out_dir) / "energy_horizon.csv")}
{TRUST}
## Figures

{_figure_lines(figures)}
"""
    text = re.sub(r"\n{3,}", "\n\n", text)
    path = Path(out_dir) / "README.md"
    atomic_write_text(path, text)
    return path


def failure_sentence(runs: pd.DataFrame, stability_csv: Path | None = None) -> str:
    """`benchmark.cheapest.failure_summary` with the stability map's table when there is one."""
    stability = None
    if stability_csv is not None and Path(stability_csv).is_file():
        try:
            stability = pd.read_csv(stability_csv)
            if not {"scene", "integrator", "largest_stable_dt"} <= set(stability.columns):
                stability = None
        except Exception:  # an unreadable map only loses its evidence, not the summary
            stability = None
    return cheap.failure_summary(runs, stability)

