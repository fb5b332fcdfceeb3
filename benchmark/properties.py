"""Which geometric property pays off where: generated from the runs table and the energy study.

The methods split by what they declare (`integrators.Capability`): *variational* (symplectic:
the LGVI family, RATTLE), *group-preserving* (the attitude stays on SO(3) by construction: the
LGVI family, the Lie group Runge–Kutta methods) or neither (the Runge–Kutta baselines on a
quaternion state). Two measured quantities separate the properties:

* energy over a long horizon (the energy study, `energy_horizon.csv`): how the error grows with
  time, as the slope of log(largest |ΔE| in each of `WINDOWS` equal windows) against log(the
  window's end time) (`classify`), fitted over the windows of the horizon's second half
  (`LATE_FROM`): a bounded error can take tens of seconds to fill its band (measured: the LGVI
  at N = 4 rises for 40 s, then stays), and the trend at the end of the horizon is what decides
  beyond it; the slope over every window is reported beside it. An error that stays in a band
  has slope ≈ 0 (the largest excursion of a window does not grow with t), a linear drift slope
  1, a random walk 1/2. The slope's 2σ interval decides: `bounded` when it lies below `DRIFTING_FROM` and the slope is
  below `BOUNDED_BELOW`, `drifting` when it lies above `BOUNDED_BELOW` and the slope is at
  least `DRIFTING_FROM`, otherwise `undecided` (and the figures are reported instead of a word);
* orthogonality (the sweep, `runs.csv`): the largest ‖RᵀR − I‖ over the method's finished runs.

The words are chosen from those numbers, never written by hand: rerun to regenerate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

#: Equal windows of the horizon whose largest energy error the classification fits, and the
#: fraction of the horizon after which they are fitted.
WINDOWS, LATE_FROM = 20, 0.5
#: The least windows with a finite, non-zero maximum for a verdict (a run that stopped early has fewer).
MIN_WINDOWS = 6
#: Slopes of log(window maximum) against log t: bounded below, drifting from (see the docstring).
BOUNDED_BELOW, DRIFTING_FROM = 0.25, 0.5
#: an orthogonality error below this is round-off: products of rotations accumulate ~√n ε over
#: the n ≤ 10⁶ steps of a sweep's finest settings
ROUND_OFF = 1e-10


def window_maxima(t, err, windows: int = WINDOWS) -> tuple[np.ndarray, np.ndarray]:
    """(end time, largest |err|) of each of ``windows`` equal windows of [0, t[-1]] (NaN: empty)."""
    t, err = np.asarray(t, float), np.abs(np.asarray(err, float))
    good = np.isfinite(t) & np.isfinite(err)
    t, err = t[good], err[good]
    if len(t) < 2 or t[-1] <= t[0]:
        return np.array([]), np.array([])
    edges = np.linspace(t[0], t[-1], windows + 1)
    k = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, windows - 1)
    maxima = np.array([err[k == i].max() if (k == i).any() else np.nan for i in range(windows)])
    return edges[1:], maxima


def classify(t, err, windows: int = WINDOWS) -> dict:
    """The energy error's growth: the slope of log(window maximum) against log(window end), its
    2σ interval, the growth (last window's maximum / first's) and the verdict ("bounded",
    "drifting" or "undecided"; see the module's docstring)."""
    ends, maxima = window_maxima(t, err, windows)
    good = np.isfinite(maxima) & (maxima > 0) if len(maxima) else np.array([], bool)
    late = good & (ends > LATE_FROM * ends[-1] + 1e-12) if len(ends) else good
    out = {"windows": int(late.sum()), "slope": np.nan, "slope_low": np.nan, "slope_high": np.nan,
           "slope_all": np.nan, "growth": np.nan, "verdict": "undecided"}
    if late.sum() < MIN_WINDOWS:
        return out
    slope, se = _slope(ends[late], maxima[late])
    low, high = slope - 2 * se, slope + 2 * se
    verdict = ("bounded" if slope < BOUNDED_BELOW and high < DRIFTING_FROM else
               "drifting" if slope >= DRIFTING_FROM and low > BOUNDED_BELOW else "undecided")
    out.update(slope=slope, slope_low=low, slope_high=high, slope_all=_slope(ends[good], maxima[good])[0],
               growth=float(maxima[good][-1] / maxima[good][0]), verdict=verdict)
    return out


def _slope(t: np.ndarray, m: np.ndarray) -> tuple[float, float]:
    """The least-squares slope of log m against log t, and its standard error."""
    x, y = np.log(t), np.log(m)
    A = np.vstack([x, np.ones_like(x)]).T
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    resid = y - A @ coef
    return float(coef[0]), float(np.sqrt(resid @ resid / (len(x) - 2) / np.sum((x - x.mean()) ** 2)))


def is_symplectic(name: str) -> bool:
    return _kind(name)[0]


def _kind(name: str) -> tuple[bool, bool]:
    from integrators import Capability, get_integrator

    try:
        caps = get_integrator(name).capabilities
    except ValueError:  # a method in an old table that is no longer registered
        return False, False
    return Capability.VARIATIONAL in caps, Capability.GROUP_PRESERVING in caps


def energy_table(horizon: pd.DataFrame | None) -> pd.DataFrame:
    """One row per run of the energy study: scene, method, N, setting, horizon reached, largest
    error, the classification (`classify`) and the least tension (N; < 0: compression)."""
    cols = ["scene", "integrator", "symplectic", "elements", "setting", "status", "horizon_s", "energy_error_max",
            "slope", "slope_low", "slope_high", "slope_all", "growth", "verdict", "tension_min", "tension_min_first",
            "tension_min_last"]
    if horizon is None or not len(horizon):
        return pd.DataFrame(columns=cols)
    h = horizon.assign(**{c: horizon[c] if c in horizon else d for c, d in
                          (("scene", "fixed_length"), ("elements", 10), ("status", "ok"), ("tension_min", np.nan))})
    if "setting" not in h:  # a table from before the study had sizes: "lgvi dt=0.005" -> "dt=0.005"
        h = h.assign(setting=h["method"].map(lambda m: str(m).split(" ", 1)[-1]))
    rows = []
    for (scene, name, n, setting), g in h.groupby(["scene", "integrator", "elements", "setting"], sort=False):
        g = g.sort_values("t")
        c = classify(g["t"].to_numpy(), g["energy_error"].to_numpy())
        rows.append({"scene": scene, "integrator": name, "symplectic": is_symplectic(name), "elements": int(n),
                     "setting": setting, "status": str(g["status"].iloc[0]), "horizon_s": float(g["t"].iloc[-1]),
                     "energy_error_max": float(np.nanmax(np.abs(g["energy_error"]))),
                     **{k: c[k] for k in ("slope", "slope_low", "slope_high", "slope_all", "growth", "verdict")},
                     "tension_min": float(pd.to_numeric(g["tension_min"], errors="coerce").min()),
                     **_tension_windows(g)})
    return pd.DataFrame(rows, columns=cols)


def _tension_windows(g: pd.DataFrame) -> dict:
    """The least tension in the first and in the last of the `WINDOWS` windows of a run."""
    t, tension = g["t"].to_numpy(float), pd.to_numeric(g["tension_min"], errors="coerce").to_numpy(float)
    ends, first_last = window_maxima(t, -tension)[0], (np.nan, np.nan)
    if len(ends) and np.isfinite(tension).any():
        first, last = t <= ends[0], t > ends[-2] if len(ends) > 1 else t >= t[0]
        first_last = (float(np.nanmin(tension[first])), float(np.nanmin(tension[last])))
    return {"tension_min_first": first_last[0], "tension_min_last": first_last[1]}


def property_table(runs: pd.DataFrame, horizon: pd.DataFrame | None) -> pd.DataFrame:
    """One row per method of the energy study or the sweep: its properties, its energy verdict
    over the study's runs (one word when every run agrees, else "mixed") with the range of their
    slopes, and the largest orthogonality error."""
    rows = {}
    study = energy_table(horizon)
    for name, g in study.groupby("integrator", sort=False):
        verdicts = set(g["verdict"])
        rows[name] = {"integrator": name, "energy_runs": len(g), "horizon_s": float(g["horizon_s"].max()),
                      "energy_error_max": float(g["energy_error_max"].max()),
                      "energy_verdict": verdicts.pop() if len(verdicts) == 1 else "mixed",
                      "slope_min": float(g["slope"].min()), "slope_max": float(g["slope"].max())}
    ok = runs[runs["status"] == "ok"]
    for name, g in ok.groupby("integrator", sort=True):
        ortho = pd.to_numeric(g["orthogonality_error"], errors="coerce").max()
        rows.setdefault(name, {"integrator": name})["orthogonality_max"] = float(ortho)
    for name, row in rows.items():
        row["symplectic"], row["group_preserving"] = _kind(name)
    cols = ["integrator", "symplectic", "group_preserving", "energy_runs", "horizon_s", "energy_error_max",
            "energy_verdict", "slope_min", "slope_max", "orthogonality_max"]
    return pd.DataFrame(list(rows.values())).reindex(columns=cols)


def _names(df: pd.DataFrame) -> str:
    return ", ".join(f"`{n}`" for n in df["integrator"]) or "none"


def _run_figures(df: pd.DataFrame) -> str:
    return "; ".join(f"`{r.integrator}` N={r.elements} {r.setting}: {r.verdict} (slope {r.slope:.2f}, "
                     f"[{r.slope_low:.2f}, {r.slope_high:.2f}]; over the whole horizon {r.slope_all:.2f}, ×{r.growth:.3g})" if np.isfinite(r.slope) else
                     f"`{r.integrator}` N={r.elements} {r.setting}: undecided ({r.status}, {r.horizon_s:g} s)"
                     for r in df.itertuples())


def _energy_sentence(study: pd.DataFrame) -> str:
    if study.empty:
        return "- No energy study in this run (`--horizon 0`): nothing to say about long-horizon energy."
    horizon = study["horizon_s"].max()
    sym, other = study[study["symplectic"]], study[~study["symplectic"]]
    if not len(sym):
        verdict = "cannot be judged (no symplectic method ran)"
    elif (sym["verdict"] == "bounded").all() and (other["verdict"] == "drifting").any():
        verdict = "pays off over a long horizon: every symplectic run's error is bounded, and some other method's drifts"
    elif (sym["verdict"] == "bounded").all():
        verdict = "is not visible at this horizon: every symplectic run is bounded, but no other method drifts"
    else:
        off = sym[sym["verdict"] != "bounded"]
        verdict = ("is not shown at these sizes and steps: the error of "
                   + ", ".join(f"`{r.integrator}` at N={r.elements} {r.setting} is {r.verdict}" for r in off.itertuples()))
    rule = (f"the slope of log(largest |ΔE| per {horizon / WINDOWS:g} s window) against log t over the last "
            f"{1 - LATE_FROM:.0%} of the horizon: bounded when it is "
            f"below {BOUNDED_BELOW:g} and its 2σ interval below {DRIFTING_FROM:g}, drifting when it is at least "
            f"{DRIFTING_FROM:g} and its interval above {BOUNDED_BELOW:g}, undecided otherwise; a linear drift has "
            "slope 1")
    scenes = ", ".join(dict.fromkeys(study["scene"]))
    by_size = sym.groupby("elements")["verdict"].agg(lambda v: set(v) == {"bounded"}) if len(sym) else pd.Series(dtype=bool)
    if len(by_size) > 1 and by_size.any() and not by_size.all():
        verdict += (f" — bounded at N = {', '.join(str(n) for n in by_size[by_size].index)} but not at N = "
                    f"{', '.join(str(n) for n in by_size[~by_size].index)}: the size of the string decides, at both "
                    "steps (its fastest axial modes are faster at larger N)")
    return (f"- **Symplecticity {verdict}** (the energy study, {horizon:g} s on {scenes}; {rule}). "
            f"Symplectic: {_run_figures(sym) or 'none'}. Not symplectic: {_run_figures(other) or 'none'}.")


def _compression_sentence(study: pd.DataFrame) -> str:
    """Whether the string's compression (least tension < 0) is in the model's solution or in a
    run's resolution: per scene and N, the least tension of the most accurate run of the study
    (the smallest energy error) against the others'."""
    if "tension_min" not in study or study["tension_min"].isna().all():
        return ""
    parts = []
    for (scene, n), g in study.dropna(subset=["tension_min"]).groupby(["scene", "elements"], sort=True):
        best = g.sort_values("energy_error_max").iloc[0]
        where = ("in the most accurate run too: it is in the model's solution, not a resolution effect"
                 if best.tension_min < 0 else "only in less accurate runs: a resolution effect")
        parts.append(f"{scene} N={n}: least tension {g['tension_min'].min():.3g} to {g['tension_min'].max():.3g} N over "
                     f"the runs, {best.tension_min:.3g} N in the most accurate (`{best.integrator}` {best.setting}, "
                     f"energy error ≤ {best.energy_error_max:.1e}; {best.tension_min_first:.3g} N in the first "
                     f"{best.horizon_s / WINDOWS:g} s, {best.tension_min_last:.3g} N in the last), so the compression "
                     f"is {where}")
    return ("\nCompression (`tension_min` < 0: an element shorter than its unstretched length; the `elasticity` law "
            "is two-sided, so it pushes back; the `slack` effect is the tension-only law): "
            + "; ".join(parts) + ".\n")


def _orthogonality_sentence(t: pd.DataFrame) -> str:
    sweep = t.dropna(subset=["orthogonality_max"])
    if sweep.empty:
        return "- No finished runs with an attitude: nothing to say about orthogonality."
    group, other = sweep[sweep["group_preserving"]], sweep[~sweep["group_preserving"]]
    on_group = group[group["orthogonality_max"] < ROUND_OFF]
    worst = other.sort_values("orthogonality_max", ascending=False).head(3)
    off = "; ".join(f"`{r.integrator}` {r.orthogonality_max:.1e}" for r in worst.itertuples()) or "none"
    verdict = "pays off" if len(group) and len(on_group) == len(group) and (other["orthogonality_max"] >= ROUND_OFF).any() \
        else "shows no difference here" if len(group) else "cannot be judged (no group-preserving method ran)"
    return (f"- **Staying on the group {verdict} in orthogonality** (largest ‖RᵀR − I‖ over each method's finished "
            f"runs of the sweep): the group-preserving methods {_names(on_group)} stay below {ROUND_OFF:g}"
            + (f" (not: {_names(group[group['orthogonality_max'] >= ROUND_OFF])})" if len(on_group) < len(group) else "")
            + f"; the others reach {off} (a quaternion state drifts off the unit sphere unless projected or "
              "constrained).")


def properties_text(runs: pd.DataFrame, horizon_csv: Path | None) -> str:
    """The "Which property pays off where" section of results/README.md."""
    from benchmark.report import markdown_table

    horizon = pd.read_csv(horizon_csv) if horizon_csv is not None and Path(horizon_csv).is_file() else None
    t = property_table(runs, horizon)
    study = energy_table(horizon)
    fmt = lambda v: "" if pd.isna(v) else f"{v:.2g}"  # noqa: E731
    shown = t.assign(**{c: t[c].map(fmt) for c in ("energy_error_max", "slope_min", "slope_max", "orthogonality_max")})
    runs_shown = study.assign(**{c: study[c].map(fmt) for c in ("energy_error_max", "slope", "slope_low", "slope_high",
                                                                 "slope_all", "growth", "tension_min", "tension_min_first",
                                                                 "tension_min_last")})
    return (f"## Which property pays off where\n\n{_energy_sentence(study)}\n{_orthogonality_sentence(t)}\n"
            f"\n{markdown_table(shown)}\n"
            + (f"\n### The energy study's runs\n\n{markdown_table(runs_shown)}\n{_compression_sentence(study)}" if len(study) else ""))
