"""The answer for a reader: one table per string size (scene × target → the fastest method by
paired wall time and the one doing the least work, each with its runner-up and ratio), one
sentence per scene on which family to use and what limits it, the work–precision figures drawn
from every setting the searches ran, and results/README.md around them. The ranking of one
target's rows is read once (`_ranking`), for the table's cells (`best_and_next`) and the
bullets (`use_line`).

Reads the answer's tables (cheapest.csv's rows, `benchmark.answer.table`; search.csv's points);
writes nothing but the files it is asked for, the project README's answer block among them
(`answer_block`, `write_answer`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from reelbench.benchmark.answer import search
from reelbench.benchmark.core.policy import BEST_VERDICTS, CHEAPEST_FILE, RANKED_VERDICTS, SLOWER, TIE

#: The markers of the project README's generated answer block.
ANSWER_START, ANSWER_END = "<!-- answer:start -->", "<!-- answer:end -->"

#: What limits a setting, in words (`benchmark.answer.search` bounds).
LIMITED_BY = {search.TARGET: "accuracy", search.STABILITY: "stability",
              search.LARGEST_SETTING: "the largest setting allowed", search.BUDGET: "the search's budget"}


def family(integrator: str) -> str:
    """The family a method belongs to, from what it declares (a plugin gets one too)."""
    from reelbench.integrators import Capability, get_integrator

    try:
        integ = get_integrator(integrator)
    except ValueError:
        return "an unregistered method"
    caps = integ.capabilities
    if Capability.VARIATIONAL in caps and Capability.GROUP_PRESERVING in caps:
        return "the Lie group variational family"
    if Capability.VARIATIONAL in caps:
        return "a variational method"
    if Capability.GROUP_PRESERVING in caps:
        return "the Lie group Runge–Kutta family"
    if integ.implementation == "jax-compiled":
        return "a compiled Runge–Kutta pair"
    return "a scipy solver"


def _ratio(r) -> str:
    if not np.isfinite(r["ratio_high"]):
        return f"≥ {r['ratio_low']:.2f}× (a lower bound)"
    return f"{r['ratio']:.2f}× [{r['ratio_low']:.2f}–{r['ratio_high']:.2f}]"


def _amount(r, kind: str) -> str:
    return f"{r['cost'] * 1e3:.3g} ms" if kind == "wall" else f"{r['cost']:.3g} flops"


def _ranking(g: pd.DataFrame):
    """(the ranked rows in order, the best, the other members of its tie, the slower ones) of one
    cost kind's rows of one target; None when no method reached it."""
    ranked = g[g["verdict"].isin(RANKED_VERDICTS)].sort_values(["ratio", "entry"])
    if ranked.empty:
        return None
    return ranked, ranked.iloc[0], ranked[ranked["verdict"] == TIE].iloc[1:], ranked[ranked["verdict"] == SLOWER]


def best_and_next(g: pd.DataFrame) -> tuple[str, str, pd.Series | None]:
    """(the best cell, the runner-up cell, the best row) of one cost kind's rows of one target: a
    tie names its members with their ratios, the runner-up is then the first method outside it."""
    ranking = _ranking(g)
    if ranking is None:
        return "no method reached it", "", None
    _, best, ties, rest = ranking
    head = f"`{best['entry']}` ({best['setting']}, {_amount(best, g['cost_kind'].iloc[0])})"
    if best["verdict"] == TIE:
        head = "tie: " + ", ".join([head] + [f"`{r['entry']}` {_ratio(r)}" for _, r in ties.iterrows()])
    nxt = "—" if rest.empty else f"`{rest.iloc[0]['entry']}` {_ratio(rest.iloc[0])}"
    return head, nxt, best


def use_line(g: pd.DataFrame) -> str:
    """"use X (setting, cost, interval); next Y at r× [lo–hi]" for one cost kind's rows; a tie
    (only where the intervals overlap) names its members with their ratios, then the first
    method outside it."""
    ranking = _ranking(g)
    if ranking is None:
        return "no method reached it"
    ranked, best, ties, rest = ranking
    kind = g["cost_kind"].iloc[0]
    own = (f"{best['setting']}, {_amount(best, kind)}, {int(best['pairs'])} pairs" if kind == "wall"
           else f"{best['setting']}, {_amount(best, kind)} [{best['cost_low']:.3g}–{best['cost_high']:.3g}]")
    if best["verdict"] == TIE:
        head = f"tie: `{best['entry']}` ({own}), " + ", ".join(f"`{r['entry']}` at {_ratio(r)}"
                                                                    for _, r in ties.iterrows())
    else:
        head = f"use `{best['entry']}` ({own})"
    if rest.empty:
        return head + ("" if len(ranked) > 1 else "; no other method reached it")
    nxt = rest.iloc[0]
    # a tie goes by the intervals, the order by the ratios: a wide interval can keep a member at
    # 1.33x in the tie while a narrow one puts 1.18x outside it, so "next" would misread
    after = "first outside the tie" if best["verdict"] == TIE else "next"
    return head + f"; {after} `{nxt['entry']}` at {_ratio(nxt)}"


def answer_lines(table: pd.DataFrame, labels: dict | None = None) -> list[str]:
    """The answer in bullets: one per scene × N × target (by wall time, paired, and by work), then
    per scene × target one line on how the wall-time answer changes from the smallest N to the
    largest."""
    labels = labels or {}
    lines = []
    for (scene, metric, target), g in table.groupby(["scene", "metric", "target"], sort=True):
        sizes = sorted(g["elements"].unique())
        for n in sizes:
            h = g[g["elements"] == n]
            parts = [f"{'by wall time' if k == 'wall' else 'by work'}: {use_line(h[h['cost_kind'] == k])}"
                     for k in ("wall", "work") if (h["cost_kind"] == k).any()]
            lines.append(f"- **{scene}**, N = {n}, {labels.get(metric, metric)} ≤ {target:g}: " + "; ".join(parts) + ".")
        if len(sizes) > 1:
            first, last = (g[(g["elements"] == n) & (g["cost_kind"] == "wall")] for n in (sizes[0], sizes[-1]))
            win = [(x.sort_values(["ratio", "entry"])["entry"].iloc[0] if len(x) else "none") for x in (first, last)]
            lines.append(f"  - from N = {sizes[0]} to N = {sizes[-1]}: fastest `{win[0]}` → `{win[1]}`"
                         + (" (unchanged)" if win[0] == win[1] else ""))
    return lines


def _target_text(metric: str, target: float, labels: dict) -> str:
    return f"{labels.get(metric, metric)} ≤ {target:g}"


def tables(table: pd.DataFrame, labels: dict | None = None) -> list[str]:
    """Markdown: per N, one table of scene × target, then one sentence per scene."""
    labels = labels or {}
    out = []
    for n, h in table.groupby("elements", sort=True):
        out += [f"**N = {int(n)}**", "",
                "| scene | target | fastest (paired wall time) | runner-up | least work (flops) | runner-up |",
                "|---|---|---|---|---|---|"]
        for (scene, metric, target), g in h.groupby(["scene", "metric", "target"], sort=True):
            wall = best_and_next(g[g["cost_kind"] == "wall"]) if (g["cost_kind"] == "wall").any() else ("not timed", "", None)
            work = best_and_next(g[g["cost_kind"] == "work"]) if (g["cost_kind"] == "work").any() else ("—", "", None)
            out.append(f"| {scene} | {_target_text(metric, target, labels)} | {wall[0]} | {wall[1]} | {work[0]} | "
                       f"{work[1]} |")
        out.append("")
        out += [f"- {line}" for line in sentences(h, labels)]
        out.append("")
    return out


def sentences(h: pd.DataFrame, labels: dict) -> list[str]:
    """One sentence per scene of one N: which family to use for each target (the fastest by wall
    time, else the least work), and what holds its setting (accuracy or stability)."""
    lines = []
    for scene, g in h.groupby("scene", sort=True):
        parts = []
        for (metric, target), t in g.groupby(["metric", "target"], sort=True):
            kind = "wall" if (t["cost_kind"] == "wall").any() else "work"
            _, _, best = best_and_next(t[t["cost_kind"] == kind])
            if best is None:
                parts.append(f"for {_target_text(metric, target, labels)} no method reached it")
                continue
            work = t[(t["cost_kind"] == "work") & (t["entry"] == best["entry"])]
            bound = work["bound"].iloc[0] if len(work) else ""
            held = f"; its setting held by {LIMITED_BY[bound]}" if bound in LIMITED_BY else ""
            tie = ", in a tie" if best["verdict"] == TIE else ""
            parts.append(f"for {_target_text(metric, target, labels)} use {family(best['integrator'])} "
                         f"(`{best['entry']}`{tie}{held})")
        lines.append(f"**{scene}**: " + "; ".join(parts) + ".")
    return lines


def answer_block(table: pd.DataFrame, labels: dict | None = None, command: str = "python -m benchmark answer",
                 table_file: str = str(CHEAPEST_FILE)) -> str:
    """The project README's answer block: one table per N, one sentence per scene, how it was made."""
    from reelbench.benchmark.answer import paired
    from reelbench.benchmark.answer.table import LOWER_BOUND_NOTE

    bounded = sorted(table.loc[table["note"].fillna("").eq(LOWER_BOUND_NOTE), "integrator"].unique())
    return "\n".join(tables(table, labels) + how_made(command, bounded, paired.EQUIVALENCE, search.CONFIRM,
                                                      table_file)) + "\n"


def how_made(command: str, bounded: list[str], equivalence: float, confirm: int, table_file: str) -> list[str]:
    bounds = (f" {', '.join(f'`{b}`' for b in bounded)} by work: its flops leave out its Newton solves, a lower bound (`≥`), "
              "never a winner." if bounded else "")
    from reelbench.benchmark.answer.search import RESOLUTION

    return [f"Each setting is the cheapest found by search (to {RESOLUTION * 100:g} % in cost) that stands: the {confirm} "
            "settings just "
            "finer meet the target too. Wall time is timed in pairs on one pinned core: the ratio to the fastest and its "
            f"90 % interval; a winner needs every other interval above {1 + equivalence:g}, else a tie. scipy's methods "
            f"are ranked by work only.{bounds}",
            "", f"Generated by `{command}`; every row: `{table_file}`."]


def points(searched: pd.DataFrame) -> pd.DataFrame:
    """Every setting the searches ran, one row per scene × N × method × axis × setting: the runs
    table the work–precision figures are drawn from (status, run time, flops, every metric)."""
    rows = []
    for r in searched.to_dict("records"):
        text = r.get("points")
        if not isinstance(text, str) or not text:
            continue
        for p in json.loads(text):
            cost_col = p.get("cost_column", "flops")
            rows.append({"scene": r["scene"], "elements": int(r["elements"]), "integrator": r["integrator"],
                         "axis": r["sweep"], "dt": p["setting"] if r["sweep"] == "dt" else math.nan,
                         "rtol": p["setting"] if r["sweep"] == "rtol" else math.nan,
                         "flops": p["cost"] if cost_col == "flops" else math.nan,
                         **{k: v for k, v in p.items() if k not in ("setting", "cost", "cost_column")}})
    if not rows:
        return pd.DataFrame(columns=["scene", "elements", "integrator", "axis", "dt", "rtol", "status"])
    df = pd.DataFrame(rows)
    return df.drop_duplicates(["scene", "elements", "integrator", "axis", "dt", "rtol"]).reset_index(drop=True)


def figures(searched: pd.DataFrame, out: Path) -> list[str]:
    """work_precision_SCENE.png (the smallest N of each scene) from every setting searched."""
    from reelbench.benchmark.figures import plots

    pts = points(searched)
    made = []
    for scene, g in pts.groupby("scene", sort=True):
        n = int(g["elements"].min())
        made.append(plots.work_precision(g[g["elements"] == n], scene, Path(out), searched=True).name)
    return made


def readme(block: list[str], figures_made: list[str], provenance: str, compared: list[str] = ()) -> str:
    """results/README.md: the answer, how it was made, its figures, and where the other results are."""
    figs = "\n".join(f"![{f}]({f})" for f in figures_made)
    return "\n".join([
        "# The answer: which integrator, and what accuracy costs in time", "",
        "Generated by the main job; do not edit by hand.", "", *block, "",
        "## Work–precision", "",
        "Every setting the searches ran, error against work; the wall-time ranking is the paired timing's above.", "",
        figs, "",
        *((["## Compared with earlier answers", "", *compared, ""]) if compared else []),
        "## Where the other results are", "",
        "- `search.csv`: every search (its bracket, bound and points); `timing.csv`: every paired timing;",
        "  `cheapest.csv`: the answer's rows.",
        "- `grid/`: the fixed grid sweep (`python -m benchmark run`): one row per method and setting.",
        "- `energy_horizon.md` and `energy_horizon.csv`: the long-horizon energy study (`python -m benchmark energy`).",
        "- `stability/`, `xval/`, `orders.csv`, `lgvi_speed.md`, `work_rule.md`: their own commands.", "",
        "## Provenance", "", provenance, ""])


def _front(g: pd.DataFrame) -> tuple[str, set]:
    """(the best entry, the entries of its tie or just it) of one cost kind's rows of one target."""
    ranked = g[g["verdict"].isin(RANKED_VERDICTS)].sort_values(["ratio", "entry"])
    if ranked.empty:
        return "", set()
    best = ranked["entry"].iloc[0]
    return best, set(ranked.loc[ranked["verdict"].isin(BEST_VERDICTS), "entry"]) | {best}


def agreement(mine: pd.DataFrame, other: pd.DataFrame) -> pd.DataFrame:
    """Per scene × N × metric × target × cost kind both tables answer: whether they agree (the
    same winner, ties that contain each other's best, or a winner inside the other's tie), and
    each one's best and front."""
    keys = ["scene", "elements", "metric", "target", "cost_kind"]
    rows = []
    theirs = {k: g for k, g in other.groupby(keys, sort=True)}
    for k, g in mine.groupby(keys, sort=True):
        if k not in theirs:
            continue
        (a, front_a), (b, front_b) = _front(g), _front(theirs[k])
        # the same winner; two ties, each holding the other's best; or a winner inside the other's tie
        agree = (a == b or (a in front_b and b in front_a) or (front_a == {a} and a in front_b)
                 or (front_b == {b} and b in front_a))
        rows.append({**dict(zip(keys, k)), "agree": bool(agree), "best": a, "front": ", ".join(sorted(front_a)),
                     "other_best": b, "other_front": ", ".join(sorted(front_b))})
    return pd.DataFrame(rows, columns=keys + ["agree", "best", "front", "other_best", "other_front"])


def agreement_text(mine: pd.DataFrame, other: pd.DataFrame, label: str) -> str:
    """A paragraph: how many answers two tables share and agree on, and the ones that differ."""
    a = agreement(mine, other)
    if a.empty:
        return f"Compared with {label}: no scene, N and target in common.\n"
    lines = [f"Compared with {label}: {int(a['agree'].sum())} of {len(a)} answers agree (the same winner, ties "
             "that contain each other's best, or a winner inside the other's tie)."]
    for r in a[~a["agree"]].itertuples():
        lines.append(f"- {r.scene}, N = {r.elements}, {r.metric} ≤ {r.target:g}, by {r.cost_kind}: `{r.best}` here "
                     f"({r.front}), `{r.other_best}` there ({r.other_front})")
    return "\n".join(lines) + "\n"


def accounting(searched: pd.DataFrame, timed: pd.DataFrame, wall: float, workers: int, kept=frozenset()) -> str:
    """Where a run's time went, against its floor: the searches' solves, their compilation and the
    rest (metrics, flops), each solve counted once, on ``workers`` processes; the paired timing; the
    floor (the solves it must run plus the compilation, shared by the workers, plus the timing).
    Rows whose ``row_digest`` is in ``kept`` were read from an earlier run: not counted (their
    time is not in this run's wall)."""
    def this_run(df):
        return df[~df["row_digest"].isin(list(kept))] if kept and "row_digest" in df else df

    before = len(searched) + len(timed)
    searched, timed = this_run(searched), this_run(timed)
    left_out = before - len(searched) - len(timed)
    pts = points(searched)
    if pts.empty or "run_time" not in pts:
        return "Time: every search was kept from an earlier run." if kept else ""
    total = {k: float(pd.to_numeric(pts.get(k), errors="coerce").fillna(0.0).sum())
             for k in ("run_time", "compile_time", "other_time")}
    timing = float(pd.to_numeric(timed.get("seconds", pd.Series(dtype=float)), errors="coerce").fillna(0.0).sum())
    floor = (total["run_time"] + total["compile_time"]) / max(workers, 1) + timing
    return (f"Time: {wall:.0f} s wall on {workers} worker(s). The searches ran {len(pts)} solves: {total['run_time']:.0f} s "
            f"of solving, {total['compile_time']:.0f} s of compilation, {total['other_time']:.0f} s of metrics and "
            f"flops (worker seconds); the paired timing took {timing:.0f} s. Floor (solves and compilation over the "
            f"workers, plus the timing): {floor:.0f} s, so this run took {wall / floor if floor else float('nan'):.2f}× "
            "its floor." + (f" {left_out} row(s) kept from earlier runs are not counted." if left_out else ""))


# ------------------------------------------------------------------------------------------
# The project README's answer block
# ------------------------------------------------------------------------------------------
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
    from reelbench.models.io import atomic_write_text

    atomic_write_text(readme, new)
    return f"{readme}: the answer block between {ANSWER_START} and {ANSWER_END} was rewritten"
