"""results/stability/: the stability map's plot and its README with a written reading, generated
from the rows of `benchmark.studies.stability` (never edited by hand).

Which methods the reading compares follows from their declared capabilities (VARIATIONAL or
not), never from names in this code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from matplotlib.lines import Line2D

from reelbench.benchmark.figures import styles
from reelbench.benchmark.figures.plots import plt, save_figure, style_axes
from reelbench.benchmark.core.report import Provenance, code_list, fmt, markdown_table
from reelbench.benchmark.studies.stability import ADAPTIVE_ATOL, ADAPTIVE_RTOL, CASES, DT_MAX, LADDER_RUNGS, SKIPPED
from reelbench.models.io import atomic_write_text
from reelbench.integrators.base import FINISHED_STATUSES, Status

#: The scenes whose largest stable steps the summary compares with the adaptive methods' steps.
STIFF_SCENES = ("stiff_string", "many_elements")


#: Share of a scene's slot its bars (or points) take, so neighbouring scenes stay apart.
SLOT = 0.8


def _offsets(n: int) -> tuple[np.ndarray, float]:
    """Offsets of ``n`` bars or points inside one scene's slot, and each one's width."""
    width = SLOT / max(n, 1)
    return (np.arange(n) - (n - 1) / 2) * width, width


def plot(df: pd.DataFrame, out_dir: Path) -> Path:
    """Top: the fixed-step methods' largest stable steps, one bar per method inside each scene's
    slot; bottom: the adaptive methods' steps per simulated second. Every method in its own style
    (`benchmark.figures.styles.style`), one legend outside the axes."""
    scenes = list(dict.fromkeys(df["scene"]))
    x = np.arange(len(scenes))
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(max(9.0, 1.35 * len(scenes)), 8.6))
    floor = DT_MAX / 2 ** LADDER_RUNGS
    fixed = df[df["kind"] == "fixed"]
    names = list(dict.fromkeys(fixed["integrator"]))
    offsets, width = _offsets(len(names))
    drawn = set()
    for k, integ in enumerate(names):
        g = fixed[fixed["integrator"] == integ].set_index("scene").reindex(scenes)
        xs = x + offsets[k]
        dt = pd.to_numeric(g["largest_stable_dt"], errors="coerce")
        a1.bar(xs, dt.fillna(0.0), width=width * 0.92, bottom=0, color=styles.style(integ).color,
               edgecolor="white", linewidth=0.4)
        drawn.add((integ, "dt"))
        for xi, v in zip(xs, dt):
            if not np.isfinite(v):
                a1.text(xi, floor * 1.1, "none", rotation=90, ha="center", va="bottom", fontsize=6)
    a1.set_yscale("log")
    a1.set_ylim(floor, DT_MAX * 1.5)
    a1.set(ylabel="largest stable step dt (s)", title="fixed-step methods: largest dt that stays bounded")
    adaptive = df[df["kind"] == "adaptive"]
    names = list(dict.fromkeys(adaptive["integrator"]))
    offsets, _ = _offsets(len(names))
    unbounded = False
    for k, integ in enumerate(names):
        g = adaptive[adaptive["integrator"] == integ].set_index("scene").reindex(scenes)
        steps, reached = (pd.to_numeric(g[c], errors="coerce") for c in ("steps", "t_reached"))
        rate = (steps / reached.where(reached > 0)).to_numpy(float)
        xs = x + offsets[k]
        ok = (g["bounded"] == True).to_numpy()  # noqa: E712
        kw = styles.style(integ).kwargs("rtol")
        a2.plot(xs[ok], rate[ok], linestyle="none", **{k2: v for k2, v in kw.items() if k2 != "linestyle"})
        drawn.add((integ, "rtol"))
        bad = (~ok) & g["status"].notna().to_numpy()
        if bad.any():
            unbounded = True
            a2.plot(xs[bad], np.where(np.isfinite(rate[bad]), rate[bad], 1.0), linestyle="none", marker="x",
                    color=kw["color"], markersize=7)
    a2.set_yscale("log")
    a2.set(ylabel="accepted steps per simulated second",
           title=f"adaptive methods at rtol {ADAPTIVE_RTOL:g}: steps per second of horizon")
    for ax in (a1, a2):
        ax.set_xticks(x)
        ax.set_xticklabels(scenes, rotation=30, ha="right", fontsize=8)
        ax.set_xlim(-0.5, len(scenes) - 0.5)
        for b in x[:-1] + 0.5:  # the slots' borders: each scene's bars stay inside its own
            ax.axvline(b, color="0.85", lw=0.8, zorder=0)
        style_axes(ax, grid="y", legend=None)
    fig.tight_layout()
    handles, labels = styles.legend_entries(drawn)
    if unbounded:
        handles.append(Line2D([], [], marker="x", color="k", linestyle="none"))
        labels.append("x: not bounded or skipped (see the table), at 1 when it has no steps")
    styles.legend_outside(fig, handles, labels)
    return save_figure(fig, Path(out_dir) / "stability.png")


# ------------------------------------------------------------------------------------------
# The reading
# ------------------------------------------------------------------------------------------
def _per_second(r) -> float:
    """Run time per simulated second (horizons differ between methods)."""
    return r["run_time"] / r["t_reached"] if r["t_reached"] and np.isfinite(r["t_reached"]) and r["t_reached"] > 0 else np.nan


def _variational(name: str) -> bool:
    """Whether ``name`` declares VARIATIONAL (False for a name no longer registered)."""
    from reelbench.integrators import Capability, get_integrator

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


def _nonfinite(df: pd.DataFrame) -> int:
    """Bounded runs whose energy error is not finite (a run that went NaN without a status)."""
    ok = df[df["bounded"] == True]  # noqa: E712
    return int((~np.isfinite(ok["energy_error"].astype(float))).sum())


def _typical_step(r) -> float:
    return r["median_step"] if np.isfinite(r["median_step"]) else r["mean_step"]


def _fixed_parts(fx: pd.DataFrame) -> list[str]:
    """What the ladders of one scene found (``fx``: its fixed-step rows, indexed by integrator)."""
    parts = []
    for name, l in fx.iterrows():
        if np.isfinite(l["largest_stable_dt"]):
            top = " (the ladder's top rung for this horizon: its limit is at least that)" if l["rungs_tried"] == 1 else ""
            parts.append(f"`{name}` stays bounded up to dt = {fmt(l['largest_stable_dt'])} s{top} "
                         f"({fmt(_per_second(l))} s of run time per simulated second, energy error {fmt(l['energy_error'])})")
        else:
            parts.append(f"`{name}` found no stable rung down to {DT_MAX / 2 ** (LADDER_RUNGS - 1):.2g} s "
                         f"({l['status']})")
        if isinstance(l.get("unstable_status"), str):
            parts[-1] += f"; at 2x that it ends `{l['unstable_status']}`"
    pair = _best_pair(fx)
    if pair is not None:
        v, o = pair
        parts.append(f"variational/other fixed-step stable step ratio {fmt(v['largest_stable_dt'] / o['largest_stable_dt'], '.2g')} "
                     f"(`{v.name}` vs `{o.name}`, the largest stable step of each), `{o.name}` costs "
                     f"{fmt(_per_second(o) / _per_second(v), '.2g')}x `{v.name}`'s run time per simulated second "
                     "at its own largest stable step")
    return parts


def _adaptive_parts(ad: pd.DataFrame) -> list[str]:
    """What the adaptive runs of one scene did (``ad``: its adaptive rows)."""
    parts = []
    ran = ad[ad["status"] != SKIPPED]
    ok = ran[ran["bounded"] == True]  # noqa: E712
    if len(ran):
        text = f"at rtol {ADAPTIVE_RTOL:g}, {len(ok)} of {len(ran)} adaptive runs stay bounded"
        if len(ok):
            ok = ok.assign(per_s=[_per_second(r) for _, r in ok.iterrows()]).sort_values("per_s")
            best, slow = ok.iloc[0], ok.iloc[-1]
            text += (f"; the cheapest per simulated second is `{best['integrator']}` ({fmt(best['per_s'])} s/s, "
                     f"{fmt(best['steps'], '.0f')} steps over {best['t_reached']:.3g} s, typical step {fmt(_typical_step(best))} s)")
            if slow["integrator"] != best["integrator"]:
                text += f", the dearest `{slow['integrator']}` ({fmt(slow['per_s'])} s/s)"
        parts.append(text)
    bad = ran[ran["bounded"] != True]  # noqa: E712
    if len(bad):
        parts.append("not bounded: " + ", ".join(f"`{r['integrator']}` ({r['status']})" for _, r in bad.iterrows()))
    skipped = ad[ad["status"] == SKIPPED]
    if len(skipped):
        parts.append("left out: " + code_list(skipped["integrator"]))
    return parts


def _scene_line(scene: str, g: pd.DataFrame) -> str:
    parts = _fixed_parts(g[g["kind"] == "fixed"].set_index("integrator")) + _adaptive_parts(g[g["kind"] == "adaptive"])
    horizons = sorted(set(float(h) for h in g.loc[g["status"] != SKIPPED, "horizon"] if np.isfinite(h)))
    return f"- **{scene}** (horizon {' / '.join(f'{h:g}' for h in horizons)} s): " + "; ".join(parts) + "."


def _stiff(df: pd.DataFrame):
    """(the stiff scenes present, the range of their largest stable steps or None)."""
    scenes = [c.scene for c in CASES if c.scene in STIFF_SCENES and c.scene in set(df["scene"])]
    stable = df.loc[df["scene"].isin(scenes), "largest_stable_dt"].astype(float)
    return scenes, ((float(np.nanmin(stable)), float(np.nanmax(stable))) if stable.notna().any() else None)


def _robustness(df: pd.DataFrame) -> list[str]:
    ratios, costs = [], []
    for _, g in df[df["kind"] == "fixed"].groupby("scene", sort=False):
        pair = _best_pair(g.set_index("integrator"))
        if pair is not None:
            v, o = pair
            ratios.append(v["largest_stable_dt"] / o["largest_stable_dt"])
            costs.append(_per_second(o) / _per_second(v))
    if not ratios:
        return []
    scenes, stiff_dt = _stiff(df)
    text = (f"**Robustness.** On each scene, the largest stable step of the best variational method is "
            f"{fmt(min(ratios), '.2g')}–{fmt(max(ratios), '.2g')}x that of the best other fixed-step method "
            "(ladder resolution: a factor 2)")
    if stiff_dt:
        text += (f"; on {code_list(scenes, ' and ')} the fixed-step methods' largest stable steps are "
                 f"{fmt(stiff_dt[0])}–{fmt(stiff_dt[1])} s")
    text += (f". **Cost.** At its largest stable step the other method needs "
             f"{fmt(min(costs), '.2g')}–{fmt(max(costs), '.2g')}x the variational one's run time per simulated second.")
    return [text]


def _past_the_limit(df: pd.DataFrame) -> list[str]:
    ended = df.loc[df["kind"] == "fixed", "unstable_status"].dropna()
    ended = ended[ended.astype(str) != ""]
    if not len(ended):
        return []
    counts = ended.value_counts()
    return [f"**Past the limit.** On the rung above the largest stable step, {len(ended)} ladder(s) ended "
            "with a status not counted as bounded on their scene: " + ", ".join(f"`{k}` {v}x" for k, v in counts.items())
            + f" ({_nonfinite(df)} bounded run(s) report a non-finite energy error)."]


def _long_horizon(df: pd.DataFrame) -> list[str]:
    longh = df[(df["scene"] == "long_horizon") & (df["kind"] == "fixed")].set_index("integrator")
    pair = _best_pair(longh) if len(longh) else None
    if pair is None:
        return []
    v, o = pair
    return [f"**Long horizon.** Over {fmt(float(v['horizon']), 'g')} s, `{v.name}` at dt = "
            f"{fmt(v['largest_stable_dt'])} s keeps its energy error at {fmt(v['energy_error'])} of max T, "
            f"while `{o.name}` at dt = {fmt(o['largest_stable_dt'])} s ends at {fmt(o['energy_error'])} "
            f"({fmt(o['energy_error'] / v['energy_error'], '.2g')}x), both bounded."]


def _adaptive_summary(df: pd.DataFrame) -> str:
    ad = df[df["kind"] == "adaptive"]
    ran = ad[ad["status"] != SKIPPED]
    unbounded = ran[ran["bounded"] != True]  # noqa: E712
    scenes, stiff_dt = _stiff(df)
    stiff = df[df["scene"].isin(scenes)]
    typical = [_typical_step(r) for _, r in stiff[(stiff["kind"] == "adaptive") & (stiff["status"] != SKIPPED)].iterrows()]
    text = (f"**Adaptive methods.** {len(ran) - len(unbounded)} of {len(ran)} adaptive runs stayed bounded"
            + (" (not bounded: " + ", ".join(f"{r['integrator']} on {r['scene']} ({r['status']})"
                                             for _, r in unbounded.iterrows()) + ")" if len(unbounded) else "")
            + f"; {len(ad) - len(ran)} were left out (reasons in the table)."
            + (f" On {code_list(scenes, ' and ')} their typical (median or mean) steps are "
               f"{fmt(min(typical))}–{fmt(max(typical))} s, against {fmt(stiff_dt[0])}–{fmt(stiff_dt[1])} s "
               "for the fixed-step methods." if typical and stiff_dt else ""))
    limits = [c.scene for c in CASES if Status.LENGTH_LIMIT.value in c.bounded and c.scene in set(df["scene"])]
    at_limit = df[df["scene"].isin(limits) & (df["status"] != SKIPPED)]
    if len(at_limit):
        text += (f" On the length-limit scenes ({code_list(limits)}) "
                 f"{int((at_limit['status'] == Status.LENGTH_LIMIT.value).sum())} of {len(at_limit)} runs end with "
                 f"`{Status.LENGTH_LIMIT.value}`.")
    return text


def reading(df: pd.DataFrame) -> str:
    """A short written reading of the map, generated from the rows: one line per scene, then
    what holds over all of them."""
    lines = [_scene_line(scene, g) for scene, g in df.groupby("scene", sort=False)]
    summary = _robustness(df) + _past_the_limit(df) + _long_horizon(df) + [_adaptive_summary(df)]
    return "\n".join(lines) + "\n\n" + "\n\n".join(summary) + "\n"


# ------------------------------------------------------------------------------------------
# The README
# ------------------------------------------------------------------------------------------
_SHOWN = ["scene", "integrator", "kind", "horizon", "bounded", "largest_stable_dt", "first_unstable_dt",
          "unstable_status", "status", "steps", "rejected_steps", "min_step", "median_step", "mean_step",
          "energy_error", "run_time"]
_REASONS = ["scene", "integrator", "kind", "status", "reason", "unstable_status", "unstable_reason", "horizon_note"]


def write_readme(out_dir: Path, df: pd.DataFrame, *, provenance: Provenance) -> Path:
    cases = "\n".join(f"| `{c.scene}` | {c.horizon:g} s | {', '.join(c.bounded)} | "
                      f"{', '.join(f'{k}={v}' for k, v in c.overrides) or '–'} | {c.note} |" for c in CASES
                      if c.scene in set(df["scene"]))
    reasons = df[~df["status"].isin(FINISHED_STATUSES) | df["unstable_reason"].notna()][_REASONS]
    fixed_names = code_list(dict.fromkeys(df.loc[df["kind"] == "fixed", "integrator"])) or "none here"
    text = f"""# Stability map of the hard scenes

{provenance.header()}

`stability.csv` has one row per scene × integrator × kind with every column; `stability.md` is
the table below; `stability.png` the plot.

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

{markdown_table(df[_SHOWN])}
## Statuses and reasons of the runs that stopped

{markdown_table(reasons)}
![stability map](stability.png)
"""
    path = Path(out_dir) / "README.md"
    atomic_write_text(path, text)
    return path
