"""The plot layer every figure is drawn with (`save_figure`: atomic PNG; `style_axes`: labels,
log-grid and legend), and the runs' figures: work–precision and the paper's panels (a)–(d). The
energy study's, the stability map's and the cross-validation's figures are drawn by their
writers (`horizon_report`, `stability_report`, `xval_report`) with the same layer."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from reelbench.benchmark.figures import styles  # noqa: E402
from reelbench.benchmark.runs.metrics import FLOPS_DEFINITION, WORK_DEFINITION, pi3_deviation  # noqa: E402
from reelbench.models import build_model  # noqa: E402
from reelbench.models.diagnostics import effect_energy_columns, energy_deviation  # noqa: E402
from reelbench.models.io import atomic_path, inside  # noqa: E402
from reelbench.integrators.base import FINISHED_STATUSES  # noqa: E402

ERROR_LABELS = {
    "energy_error": "energy error  max|ΔE (−W)| / max T",
    "position_error_final": "body position error at t_end (m)",
    "position_error_max": "body position error, max over saved times (m)",
}


def save_figure(fig, path: Path, dpi: int = 110) -> Path:
    """Write ``fig`` as PNG atomically (an interrupted write leaves the old figure) and close it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    plt.close(fig)
    return Path(path)


def style_axes(ax, *, xlabel: str | None = None, ylabel: str | None = None, title: str | None = None,
               grid: str | None = "both", legend: int | None = 8) -> None:
    """Labels, a light grid (``grid``: "both", "y", or None) and a legend of ``legend`` points."""
    ax.set(**{k: v for k, v in (("xlabel", xlabel), ("ylabel", ylabel), ("title", title)) if v is not None})
    if grid:
        ax.grid(True, which="both", axis="y" if grid == "y" else "both", alpha=0.3)
    if legend:
        ax.legend(fontsize=legend)


#: x axes of the work-precision figure: wall time (this machine), then work in one unit that does
#: not depend on the machine, the floating-point operations the methods are ranked by
COST_AXES = (("run_time", "run time (s): solve() after compilation, median of repeats"),
             ("flops", "work (floating-point operations)"))
#: The bottom row of a table from before the ``flops`` column: the sum of counts
_COUNT_AXIS = ("work_evals", "work (RHS-equivalent evaluations)")


def work_column(runs: pd.DataFrame) -> str:
    """The work column of a runs table: ``flops`` when it has any value, else ``work_evals``."""
    if "flops" in runs and runs["flops"].notna().any():
        return "flops"
    return "work_evals"


def _numeric(df: pd.DataFrame, columns) -> pd.DataFrame:
    """``df`` with ``columns`` as numbers (text that is not one becomes NaN: never drawn)."""
    return df.assign(**{c: pd.to_numeric(df[c], errors="coerce") for c in columns if c in df})


def _clash_caption(names) -> str:
    pairs = styles.clashes(names)
    return ("\nsame colour and marker: " + "; ".join(f"{a} and {b}" for a, b in pairs)) if pairs else ""


def log_ticks(ax) -> None:
    """Tick labels that do not overlap on a narrow log panel: a span of two decades or more gets
    one label per decade (at most six), a shorter one labels 1, 2 and 5 of each decade in plain
    numbers; minor ticks stay unlabelled (matplotlib's labelled minor ticks run into each other)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for axis, (lo, hi) in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
        if not (lo > 0 and hi > lo):
            continue
        if np.log10(hi / lo) >= 2:
            axis.set_major_locator(LogLocator(base=10.0, numticks=6))
        else:
            axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())


def work_precision(runs: pd.DataFrame, scene: str, out_dir: Path, *, searched: bool = False) -> Path:
    """Error vs cost, one curve per integrator and sweep axis, log-log: one column per error kind,
    one row per cost axis (`COST_AXES`: wall time, then the work in flops that ranks the methods,
    so a reader on another machine can check the ranking; ``searched``: the rows are the settings a
    search ran, each solved once, drawn against work only). Every method has its own style
    (`benchmark.figures.styles.style`) in every panel; the legend is outside the axes and names a method
    without a work count as such."""
    path = inside(out_dir, f"work_precision_{scene}.png")  # the scene name comes from a table: refused if it walks out
    by_flops = work_column(runs) == "flops"
    cost_axes = COST_AXES if by_flops else (COST_AXES[0], _COUNT_AXIS)
    if searched:  # one solve's time under load is noise beside the paired timing: work only
        cost_axes = (cost_axes[1],)
    work = cost_axes[-1][0]
    cols = [c for c, _ in cost_axes] + list(ERROR_LABELS) + ["dt"]
    sel = runs[runs["scene"] == scene]
    g = _numeric(sel[sel["status"].isin(FINISHED_STATUSES)], cols)
    g = g.assign(axis=np.where(g["dt"].notna(), "dt", "rtol"))
    fig, axes = plt.subplots(len(cost_axes), len(ERROR_LABELS), figsize=(4.6 * len(ERROR_LABELS), 4.0 * len(cost_axes)),
                             squeeze=False)
    drawn, absent = set(), {}
    for row, (cost, cost_label) in zip(axes, cost_axes):
        for ax, (err, label) in zip(row, ERROR_LABELS.items()):
            for (integ, axis), c in g.groupby(["integrator", "axis"]):
                c = c[(c[err] > 0) & (c[cost] > 0)].sort_values(cost) if cost in c else c.iloc[:0]
                if len(c):
                    ax.loglog(c[cost], c[err], **styles.style(integ).kwargs(axis))
                    drawn.add((integ, axis))
            log_ticks(ax)
            style_axes(ax, xlabel=cost_label, ylabel=label, legend=None)
    for integ in sorted(set(g["integrator"])):
        if not (work in g and g.loc[g["integrator"] == integ, work].notna().any()):
            absent[integ] = f"no {'flops' if by_flops else 'work'} count (bottom row)"
    # a method drawn in the top row keeps its one legend entry, and the caption says what the bottom
    # row lacks; only a method drawn nowhere gets a faded legend entry with the reason
    shown = {integ for integ, _ in drawn}
    missing_below = sorted(i for i in absent if i in shown)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    styles.legend_outside(fig, *styles.legend_entries(drawn, {i: why for i, why in absent.items() if i not in shown}))
    failed = sel[~sel["status"].isin(FINISHED_STATUSES)]
    source = "search.csv" if searched else "runs.csv"
    fig.suptitle(f"{scene}: work–precision" + (f"  ({len(failed)} runs failed, see {source})" if len(failed) else "")
                 + f"\n{'' if searched else 'bottom row: '}{FLOPS_DEFINITION if by_flops else WORK_DEFINITION}"
                 + (f"; no {'flops' if by_flops else 'work'} count for {', '.join(missing_below)}" if missing_below else "")
                 + _clash_caption(set(g["integrator"])), fontsize=10)
    return save_figure(fig, path)


def paper_panels(scene, traj, df: pd.DataFrame, out_path: Path, n_snapshots: int = 20) -> Path:
    """The paper's figure for one run: (a) snapshots, (b) energy exchange, (c) lengths and Ω2,
    (d) deviation of conserved quantities and orthogonality error."""
    model = build_model(scene)
    fig = plt.figure(figsize=(13, 9))
    ax = fig.add_subplot(2, 2, 1, projection="3d")
    idx = np.linspace(0, len(traj.t) - 1, min(n_snapshots, len(traj.t))).astype(int)
    for k in idx:
        q = model.r_p + np.asarray(model.nodes(np.asarray(traj.x[k])))
        ax.plot(q[:, 0], q[:, 1], q[:, 2], "b-", lw=0.8, alpha=0.6)
        ax.plot(q[-1:, 0], q[-1:, 1], q[-1:, 2], "ro", ms=3)
    ax.invert_zaxis()  # e3 points down
    ax.set_xlabel("x (m)"), ax.set_ylabel("y (m)"), ax.set_zlabel("z (m, down)")
    ax.set_title(f"(a) snapshots every {traj.t[idx[1]] - traj.t[idx[0]]:.2g} s" if len(idx) > 1 else "(a) snapshot")

    ax = fig.add_subplot(2, 2, 2)
    ax.plot(df["t"], df["energy"], "k-", label="E")
    ax.plot(df["t"], df["kinetic"], "b-", label="T")
    ax.plot(df["t"], df["T_rot"], "g--", label="T_rot")
    ax.plot(df["t"], df["V_gravity"], "m-.", label="V_gravity")
    ax.plot(df["t"], df["V_elastic"], "r:", label="V_elastic")
    # every other effect's potential (buoyancy, a plugin's): with these the parts add up to E
    for k, column in enumerate(effect_energy_columns(model)):
        if column in df:
            ax.plot(df["t"], df[column], linestyle=(0, (3, 1, 1, 1, 1, 1)), color=f"C{(k + 5) % 10}", label=column)
    ax.set_xlabel("t (s)"), ax.set_ylabel("J"), ax.legend(fontsize=8), ax.set_title("(b) energy exchange")

    ax = fig.add_subplot(2, 2, 3)
    ax.plot(df["t"], df["stretched_length"], "b-", label="stretched length")
    ax.plot(df["t"], df["deployed_length"], "b--", label="deployed (unstretched) length")
    ax.set_xlabel("t (s)"), ax.set_ylabel("m")
    ax2 = ax.twinx()
    ax2.plot(df["t"], df["omega_2"], "r-", lw=0.8, label="Ω2")
    ax2.set_ylabel("Ω2 (rad/s)", color="r")
    ax.legend(fontsize=8, loc="upper left"), ax.set_title("(c) length and Ω2")

    ax = fig.add_subplot(2, 2, 4)
    has_work = model.layout.has_work
    dev = energy_deviation(df, has_work=has_work)
    ax.semilogy(df["t"], np.maximum(dev, 1e-17), label=("|Δ(E−W)|" if has_work else "|ΔE|") + " / max T")
    if model.layout.conserves_pi3:  # external forces (drag) change π3: its drift would not be an error
        ax.semilogy(df["t"], np.maximum(pi3_deviation(df), 1e-17), label="|Δπ3| / |π3(0)|")
    if model.layout.has_attitude:
        ax.semilogy(df["t"], np.maximum(df["orthogonality_error"], 1e-17), label="‖I − RᵀR‖")
    title = ("(d) conserved quantities and orthogonality" if model.layout.conserves_pi3
             else "(d) energy balance and orthogonality (π3 not conserved: external forces)")
    style_axes(ax, xlabel="t (s)", title=title)
    status = "" if traj.ok else f"  [stopped: {traj.status}]"
    setting = ", ".join(f"{k} = {v:g}" if isinstance(v, (int, float)) else f"{k} = {v}"
                        for k, v in traj.settings.items() if v is not None)
    fig.suptitle(f"{scene.name} — {traj.integrator} ({setting}){status}")
    fig.tight_layout()
    return save_figure(fig, Path(out_path))
