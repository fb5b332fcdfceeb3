"""results/README.md: what the runs table says, in words and tables, generated from the data
(never edited by hand): the cheapest method per target error, the changes against an earlier
run, the observed orders and the statuses."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from benchmark.metrics import WORK_DEFINITION, fastest_at
from benchmark.reference import REFERENCE_METHOD
from benchmark.report import Provenance, code_list, markdown_table
from models.io import atomic_write_text

TARGETS = (("energy_error", 1e-4, "energy error 1e-4 (relative to max T)"),
           ("position_error_final", 1e-6, "position error 1e-6 m (body, at t_end)"))


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


COSTS = (("run_time", "wall time", "{:.3g} s"), ("work_evals", "work count (RHS-equivalent evaluations, see above)", "{:.3g}"))


def answers(runs: pd.DataFrame) -> str:
    """Which integrator is fastest at each target error, per scene, and by what factor: in wall
    time and in the machine-independent work count."""
    out = []
    for err, target, label in TARGETS:
        for cost, cost_label, fmt in COSTS:
            if cost not in runs:
                continue
            table = fastest_at(runs, err, target, cost)
            out.append(f"### Cheapest to reach {label}, by {cost_label}\n\n")
            for scene in sorted(runs["scene"].unique()):
                t = table[table["scene"] == scene] if not table.empty else table
                if t.empty:
                    out.append(f"- **{scene}**: no run reached it.\n")
                    continue
                best = t.iloc[0]
                if len(t) > 1:
                    second = t.iloc[1]
                    out.append(f"- **{scene}**: `{best['integrator']}` ({best['setting']}, {fmt.format(best[cost])}), "
                               f"{second['factor']:.2g}× cheaper than the next, `{second['integrator']}` "
                               f"({second['setting']}, {fmt.format(second[cost])}).\n")
                else:
                    out.append(f"- **{scene}**: only `{best['integrator']}` reached it ({best['setting']}, "
                               f"{fmt.format(best[cost])}).\n")
            out.append("\n" + markdown_table(table) + "\n")
    return "".join(out)


def changes_since(before: pd.DataFrame, runs: pd.DataFrame, label: str) -> str:
    """What changed against an earlier run's table ``before`` (e.g. the results of an earlier
    version): the cheapest method per scene and target then and now, and each method's
    speed-up on the runs both tables have (same scene, integrator and setting, ok in both)."""
    out = [f"## Compared with {label}\n\n"]
    for err, target, what in TARGETS:
        if err not in before or err not in runs:
            continue
        then, now = fastest_at(before, err, target), fastest_at(runs, err, target)
        out.append(f"Cheapest to reach {what}, by wall time (last column: the two methods ranked first "
                   f"and second then, compared now):\n\n| scene | then | now | then's pair now |\n|---|---|---|---|\n")
        for scene in sorted(set(runs["scene"]) | set(before["scene"])):
            cells = []
            for t in (then, now):
                g = t[t["scene"] == scene] if not t.empty else t
                if g.empty:
                    cells.append("no run reached it")
                    continue
                first = g.iloc[0]
                nxt = (f", {g['factor'].iloc[1]:.2g}× cheaper than `{g['integrator'].iloc[1]}`" if len(g) > 1 else "")
                cells.append(f"`{first['integrator']}` ({first['setting']}, {first['run_time']:.3g} s){nxt}")
            pair = ""
            g_then = then[then["scene"] == scene] if not then.empty else then
            g_now = now[now["scene"] == scene] if not now.empty else now
            if len(g_then) > 1 and not g_now.empty:
                a, b = g_then["integrator"].iloc[0], g_then["integrator"].iloc[1]
                ta = g_now.loc[g_now["integrator"] == a, "run_time"]
                tb = g_now.loc[g_now["integrator"] == b, "run_time"]
                if len(ta) and len(tb):
                    pair = f"`{b}` / `{a}` = {tb.iloc[0] / ta.iloc[0]:.2g}× (then {g_then['factor'].iloc[1]:.2g}×)"
            out.append(f"| {scene} | {cells[0]} | {cells[1]} | {pair} |\n")
        out.append("\n")
    key = ["scene", "integrator", "setting"]
    both = before[before["status"] == "ok"].merge(runs[runs["status"] == "ok"], on=key, suffixes=("_then", "_now"))
    if not both.empty:
        speed = (both["run_time_then"] / both["run_time_now"]).groupby(both["integrator"]).median()
        out.append("Median speed-up of each method (run time then / now, over the "
                   f"{len(both)} runs both tables finished):\n\n| integrator | runs | speed-up |\n|---|---|---|\n")
        counts = both.groupby("integrator").size()
        for name, v in speed.sort_values(ascending=False).items():
            out.append(f"| {name} | {counts[name]} | {v:.3g}× |\n")
        out.append("\n")
    new = sorted(set(runs["integrator"]) - set(before["integrator"]))
    if new:
        out.append(f"New in this run: {code_list(new)}.\n\n")
    return "".join(out)


def write_readme(out_dir: Path, runs: pd.DataFrame, orders: pd.DataFrame, *, provenance: Provenance,
                 figures: list[str], horizons: dict | None = None, compared: str = "") -> Path:
    status = runs.groupby(["integrator", "status"]).size().unstack(fill_value=0).reset_index()
    ref = REFERENCE_METHOD
    text = f"""# Benchmark results

{provenance.header()}
{horizons_text(horizons)}

`runs.csv` has one row per run (scene × integrator × setting) with status, cost and accuracy;
`runs.md` is the same as a table.
Run time is the whole `solve()` call (output conversion included, e.g. the LGVI's
velocity recovery) minus its compilation: the minimum (`run_time`) and the median
(`run_time_median`) over repeated solves (`timing_samples` of them), measured in a separate pass
from the error computation; the tables use the minimum, the least disturbed by other load.
Errors are against a {ref["integrator"].upper()} reference at rtol {ref["rtol"]:g} / atol {ref["atol"]:g} on the same model. Every row
names the right-hand side it ran (`rhs`: the O(N) closed form unless a run asked for `autodiff`).
{WORK_DEFINITION[0].upper() + WORK_DEFINITION[1:]}: column `work_evals`, the bottom row of the
work-precision figures, for comparing methods independently of this machine. Energy error is max|ΔE|/max T
(max|Δ(E − W)|/max T with Carnot loss or reel control), as in the paper.

## What accuracy costs in time

{answers(runs)}
{compared}## Observed convergence orders

Slope p of error ∝ steps^(−p) on the body position at t_end (fixed-step: the order in dt):
the mean over consecutive settings, and from the two finest settings alone. Over these
horizons the system is chaotic and coarse steps sit near stability limits, so read the
finest pair; the classical orders are measured on short horizons in `tests/`.

{markdown_table(orders)}
## Run status by integrator

{markdown_table(status)}
## Figures

{chr(10).join(f"- [{f}]({f})" for f in figures)}
"""
    path = Path(out_dir) / "README.md"
    atomic_write_text(path, text)
    return path
