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

That slope test on |ΔE| cannot tell numerical drift from a growing offset of a conserved
modified energy: a symplectic method of order p conserves Ẽ = E + h^p H_p + …, so its E − E0
follows −h^p (H_p − H_p(0)), which grows whenever energy flows into the string's fast modes (it
does, in an accurate solve too). The correction is derived, not fitted (`shadow_coefficient`):
for Störmer–Verlet-like steps (the LGVI, RATTLE) H_2 = U''(v, v)/12 − |∇U|²_{M⁻¹}/24, whose
average over a fast linear mode of the string is ⟨U''(v, v)⟩/24, so the offset is
−(h²/24)⟨P_2⟩ with P_2 = U''(v, v) of the string = P + G (`benchmark.studies.horizon.axial_measures`: P =
Σ EA l ε̇² axial, G = Σ (T/|Δ|)|Δv⊥|² transverse); for the fourth-order compositions
−c_4 h⁴⟨P4⟩, P4 = Σ EA l ε̈², c_4 from the composition's coefficients (the h⁴ term of a
harmonic mode). Each run's verdict (`drift_fit`) is taken on what is left: the means of E − E0
over `WINDOW_S`-s windows are fitted as α + β t + a X + b S, X the state's part h^p⟨P_p⟩ (⟨P⟩
for a method without a modified energy) and S = |Ω|² T_rot the body's spin (the body's own
modified-energy term, whose coefficient is not derived here: fitted, b), and the drift over the
horizon D = β T is compared with the scatter s of the fit's residual: `drifting` when |D| ≥
`DRIFT_SIGMAS` s and D's 2σ interval excludes 0, `bounded` when |D| < `BOUNDED_SIGMAS` s,
`undecided` between. The fitted a beside −c_p checks the derivation. The raw slope verdict stays
in the table (`raw_verdict`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from reelbench.benchmark.core.policy import axis_of, setting_value
from reelbench.integrators.base import FINISHED_STATUSES, Status, is_finished

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
#: Width (s) of the windows the modified-energy analysis averages over: about a hundred periods of
#: the axial modes (≤ 0.05 s at N = 4 and 10) and about one swing of the pendulum.
WINDOW_S = 5.0
#: The drift verdict on the residual (`drift_fit`): drifting from DRIFT_SIGMAS window scatters
#: over the horizon, bounded below BOUNDED_SIGMAS.
DRIFT_SIGMAS, BOUNDED_SIGMAS = 3.0, 1.0


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


def shadow_coefficient(gammas=None, order: int = 2, z: float = 1e-2) -> float:
    """c_p of the mode-averaged modified energy ⟨H̃ − H⟩ = c_p (hω)^p E_m of Störmer–Verlet
    composed with the substeps ``gammas`` (None: one step) on a harmonic mode q'' = −ω² q of
    energy E_m, from the exact modified Hamiltonian of the linear map (H̃ = ½ zᵀ S z with
    exp(h J S) = the step's matrix), at hω = ``z``. 1/24 for Störmer–Verlet (either form);
    Yoshida's triple jump −0.0661, Suzuki's five stages −0.00093 (order 4)."""
    M = np.eye(2)
    for g in gammas or (1.0,):
        kick, drift = np.array([[1.0, 0.0], [-g * z / 2, 1.0]]), np.array([[1.0, g * z], [0.0, 1.0]])
        M = kick @ drift @ kick @ M
    c = np.trace(M) / 2
    theta = np.arccos(c)
    S = np.linalg.solve(np.array([[0.0, 1.0], [-1.0, 0.0]]), theta * (M - c * np.eye(2)) / np.sin(theta)) / z
    return float((0.5 * (S[0, 0] + S[1, 1]) - 1.0) / z ** order)


def correction_of(name: str, setting: str) -> tuple[int, float, float] | None:
    """(order p, c_p, step h) of a run's modified-energy correction −c_p h^p ⟨P_p⟩ (P_2 = U''(v, v)
    of the string, P_4 = P4: the module's docstring), or None for a
    method with none (not symplectic, or adaptive: no fixed h)."""
    from reelbench.integrators import get_integrator

    if not is_symplectic(name) or axis_of(setting) != "dt":
        return None
    integ = get_integrator(name)
    gammas = getattr(getattr(integ, "scheme", None), "gammas", None)
    order = 4 if gammas else 2  # a symmetric second-order step, or its fourth-order composition
    return order, shadow_coefficient(gammas, order), _setting_value(setting)


def _setting_value(setting: str) -> float:
    return setting_value(setting)


def window_means(t, *series, width: float = WINDOW_S) -> tuple[np.ndarray, ...]:
    """(centre, mean of each series) of the windows of ``width`` s tiling [t0, t_end] (the last
    one partial is dropped), windows without a finite sample left out."""
    t = np.asarray(t, float)
    ys = [np.asarray(y, float) for y in series]
    if len(t) < 2 or not np.isfinite(t).any():
        return (np.array([]),) * (1 + len(ys))
    t0 = np.nanmin(t)
    k = np.floor((t - t0) / width + 1e-9).astype(int)
    last = int(np.floor((np.nanmax(t) - t0) / width + 1e-9))
    centres, means = [], [[] for _ in ys]
    for i in range(last):
        sel = (k == i) & np.isfinite(t) & np.all([np.isfinite(y) for y in ys], axis=0)
        if sel.any():
            centres.append(t0 + (i + 0.5) * width)
            for m, y in zip(means, ys):
                m.append(float(y[sel].mean()))
    return (np.array(centres), *(np.array(m) for m in means))


def drift_fit(t, dev, x=None, width: float = WINDOW_S, extra=()) -> dict:
    """The drift of a signed energy error ``dev`` once the part the state explains is taken out:
    window means (`window_means`) fitted as α + β t + a x̄ (``x``: the state's regressor, e.g.
    h² P; None: α + β t; ``extra``: more state regressors, each with its own coefficient), the
    drift over the horizon D = β (t_last − t_first) with its standard error, the scatter s of the
    residual (its standard deviation), a with its standard error, the share of the window
    means' variance the fit explains (r2), and the verdict (module docstring)."""
    x = np.zeros_like(np.asarray(dev, float)) if x is None else np.asarray(x, float)
    tc, d, xm, *em = window_means(t, dev, x, *extra, width=width)
    out = {"windows": len(tc), "drift": np.nan, "drift_se": np.nan, "scatter": np.nan, "a": np.nan, "a_se": np.nan,
           "r2": np.nan, "drift_verdict": "undecided"}
    use_x = bool(len(tc)) and np.ptp(xm) > 0
    cols = [np.ones_like(tc), tc - tc.mean()] + ([xm] if use_x else []) + [e for e in em if len(e) and np.ptp(e) > 0]
    if len(tc) < len(cols) + MIN_WINDOWS:
        return out
    A = np.vstack(cols).T
    coef, *_ = np.linalg.lstsq(A, d, rcond=None)
    resid = d - A @ coef
    dof = len(d) - len(cols)
    s2 = float(resid @ resid) / dof
    cov = s2 * np.linalg.pinv(A.T @ A)
    span = tc[-1] - tc[0]
    drift, drift_se, scatter = coef[1] * span, np.sqrt(cov[1, 1]) * span, np.sqrt(s2)
    total = float(np.sum((d - d.mean()) ** 2))
    verdict = ("drifting" if abs(drift) >= DRIFT_SIGMAS * scatter and abs(drift) > 2 * drift_se else
               "bounded" if abs(drift) < BOUNDED_SIGMAS * scatter else "undecided")
    out.update(drift=float(drift), drift_se=float(drift_se), scatter=float(scatter),
               a=float(coef[2]) if use_x else np.nan, a_se=float(np.sqrt(cov[2, 2])) if use_x else np.nan,
               r2=1.0 - float(resid @ resid) / total if total > 0 else np.nan, drift_verdict=verdict)
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
    from reelbench.integrators import Capability, get_integrator

    try:
        caps = get_integrator(name).capabilities
    except ValueError:  # a method in an old table that is no longer registered
        return False, False
    return Capability.VARIATIONAL in caps, Capability.GROUP_PRESERVING in caps


def energy_table(horizon: pd.DataFrame | None) -> pd.DataFrame:
    """One row per run of the energy study: scene, method, N, setting, horizon reached, largest
    error with its raw slope classification (`classify`, ``raw_verdict``), the modified-energy
    correction (``correction``, its coefficient ``c`` of h^p ⟨P_p⟩ in E − E0), the largest change
    of the window-mean error before (``mean_error_max``) and after it (``corrected_max``), the
    fit of `drift_fit` (``a_fit`` beside ``c``, ``r2``, the drift over the horizon, its standard
    error and the residual's scatter, all relative to max T) and its ``verdict``, the axial
    measure P/max T in the first and last window, and the least tension (N; < 0: compression)
    overall, in the first and in the last window, with the share of saved times with an element
    in compression (or, with `slack`, slack)."""
    cols = ["scene", "integrator", "symplectic", "elements", "setting", "status", "horizon_s", "energy_error_max",
            "slope", "slope_low", "slope_high", "slope_all", "growth", "raw_verdict", "correction", "c",
            "mean_error_max", "corrected_max", "a_fit", "a_se", "r2", "drift", "drift_se", "scatter", "verdict",
            "P_first", "P_last", "tension_min", "tension_min_first", "tension_min_last", "compressed_share"]
    if horizon is None or not len(horizon):
        return pd.DataFrame(columns=cols)
    h = horizon.assign(**{c: horizon[c] if c in horizon else d for c, d in
                          (("scene", "fixed_length"), ("elements", 10), ("status", Status.OK.value), ("tension_min", np.nan),
                           ("energy_dev", np.nan), ("axial_P", np.nan), ("axial_P4", np.nan))})
    if "setting" not in h:  # a table from before the study had sizes: "lgvi dt=0.005" -> "dt=0.005"
        h = h.assign(setting=h["method"].map(lambda m: str(m).split(" ", 1)[-1]))
    rows = []
    for (scene, name, n, setting), g in h.groupby(["scene", "integrator", "elements", "setting"], sort=False):
        g = g.sort_values("t")
        c = classify(g["t"].to_numpy(), g["energy_error"].to_numpy())
        rows.append({"scene": scene, "integrator": name, "symplectic": is_symplectic(name), "elements": int(n),
                     "setting": setting, "status": str(g["status"].iloc[0]), "horizon_s": float(g["t"].iloc[-1]),
                     "energy_error_max": float(np.nanmax(np.abs(g["energy_error"]))),
                     **{k: c[k] for k in ("slope", "slope_low", "slope_high", "slope_all", "growth")},
                     "raw_verdict": c["verdict"], **_shadow(g, name, setting),
                     "tension_min": float(pd.to_numeric(g["tension_min"], errors="coerce").min()),
                     **_tension_windows(g)})
    return pd.DataFrame(rows, columns=cols)


def _shadow(g: pd.DataFrame, name: str, setting: str) -> dict:
    """The modified-energy part of a run's row (`energy_table`)."""
    t = g["t"].to_numpy(float)
    dev = pd.to_numeric(g["energy_dev"], errors="coerce").to_numpy(float)
    P = pd.to_numeric(g["axial_P"], errors="coerce").to_numpy(float)
    P4 = pd.to_numeric(g["axial_P4"], errors="coerce").to_numpy(float)
    G = pd.to_numeric(g["geometric_G"], errors="coerce").to_numpy(float) if "geometric_G" in g else np.zeros_like(P)
    S = pd.to_numeric(g["spin_S"], errors="coerce").to_numpy(float) if "spin_S" in g else None
    out = {"correction": "none", "c": np.nan, "mean_error_max": np.nan, "corrected_max": np.nan, "a_fit": np.nan,
           "a_se": np.nan, "r2": np.nan, "drift": np.nan, "drift_se": np.nan, "scatter": np.nan,
           "verdict": "undecided", "P_first": np.nan, "P_last": np.nan}
    if not np.isfinite(dev).any():  # a table from before the signed error was kept: the raw slope test decides
        out["verdict"] = classify(t, g["energy_error"].to_numpy())["verdict"]
        return out
    corr = correction_of(name, setting)
    if corr is not None:
        order, cp, step = corr
        x = step ** order * (P + np.nan_to_num(G) if order == 2 else P4)
        out.update(correction=f"h^{order} {'U″(v,v)' if order == 2 else 'P4'}", c=-cp)
    else:
        x, cp = (P if np.isfinite(P).any() else None), 0.0
    tc, d, xm, pm = window_means(t, dev, np.zeros_like(dev) if x is None else np.nan_to_num(x), np.nan_to_num(P))
    if len(tc) < 2:
        return out
    r = d + cp * xm
    fit = drift_fit(t, dev, x, extra=() if S is None or not np.isfinite(S).all() else (S,))
    out.update(mean_error_max=float(np.max(np.abs(d - d[0]))), corrected_max=float(np.max(np.abs(r - r[0]))),
               a_fit=fit["a"], a_se=fit["a_se"], r2=fit["r2"], drift=fit["drift"], drift_se=fit["drift_se"],
               scatter=fit["scatter"], verdict=fit["drift_verdict"], P_first=float(pm[0]), P_last=float(pm[-1]))
    return out


def _tension_windows(g: pd.DataFrame) -> dict:
    """The least tension in the first and in the last of the `WINDOWS` windows of a run."""
    t, tension = g["t"].to_numpy(float), pd.to_numeric(g["tension_min"], errors="coerce").to_numpy(float)
    ends, first_last = window_maxima(t, -tension)[0], (np.nan, np.nan)
    if len(ends) and np.isfinite(tension).any():
        first, last = t <= ends[0], t > ends[-2] if len(ends) > 1 else t >= t[0]
        first_last = (float(np.nanmin(tension[first])), float(np.nanmin(tension[last])))
    share = float(np.mean(tension[np.isfinite(tension)] <= 0.0)) if np.isfinite(tension).any() else np.nan
    return {"tension_min_first": first_last[0], "tension_min_last": first_last[1], "compressed_share": share}


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
    ok = runs[runs["status"].isin(FINISHED_STATUSES)]
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
    return "; ".join(_run_line(r) for r in df.itertuples())


def _run_line(r) -> str:
    if not np.isfinite(r.drift):
        why = (f"slope {r.slope:.2f} of log |ΔE|, no signed error in the table" if np.isfinite(r.slope) else
               f"{r.status}, {r.horizon_s:g} s")
        return f"`{r.integrator}` N={r.elements} {r.setting} on {r.scene}: {r.verdict} ({why})"
    corr = ""
    if r.correction != "none":
        p = 2 if r.correction.startswith("h^2") else 4
        corr = (f", after the derived offset {r.c:+.3g} h^{p}⟨{'U″(v,v)' if p == 2 else 'P4'}⟩ {r.corrected_max:.2g} "
                f"(×{r.mean_error_max / r.corrected_max:.3g} less); fitted coefficient {r.a_fit:+.3g} ± "
                f"{2 * r.a_se:.2g} (R² {r.r2:.3f})")
    else:
        corr = f"; the state (⟨P⟩) explains R² {r.r2:.3f} of it" if np.isfinite(r.r2) else ""
    stopped = f" (stopped: {r.status} at {r.horizon_s:g} s)" if not is_finished(r.status) else ""
    return (f"`{r.integrator}` N={r.elements} {r.setting} on {r.scene}: **{r.verdict}**{stopped} — max|ΔE| {r.energy_error_max:.2g}, "
            f"largest change of the {WINDOW_S:g}-s mean {r.mean_error_max:.2g}{corr}; drift over the horizon "
            f"{r.drift:+.2g} ± {2 * r.drift_se:.1g} against a scatter of {r.scatter:.2g} (raw slope test: "
            f"{r.raw_verdict})")


def _scaling(study: pd.DataFrame) -> list[str]:
    """The fitted scaling of the offset with h: for a method run at two steps (same scene and N),
    k = a_fit h^p (the offset per unit of ⟨P_p⟩) at each, and its exponent log(k1/k2)/log(h1/h2)."""
    out = []
    fixed = study[(study["correction"] != "none") & ~study["scene"].astype(str).str.endswith("_slack")]
    for (scene, name, n), g in fixed.groupby(["scene", "integrator", "elements"], sort=False):
        if len(g) < 2:
            continue
        g = g.assign(h=g["setting"].map(_setting_value)).sort_values("h", ascending=False)
        p = np.where(g["correction"].str.startswith("h^2"), 2, 4)
        k = g["a_fit"].to_numpy(float) * g["h"].to_numpy(float) ** p
        if np.all(np.isfinite(k)) and k[0] * k[1] > 0:
            x = float(np.log(k[0] / k[1]) / np.log(g["h"].iloc[0] / g["h"].iloc[1]))
            out.append(f"`{name}` N={n} on {scene}: h^{x:.2f} (derived h^{int(p[0])})")
    return out


def _reference(g: pd.DataFrame):
    """The accurate reference among runs ``g`` (`benchmark.studies.horizon.REFERENCE`, else the smallest
    energy error)."""
    from reelbench.benchmark.studies.horizon import REFERENCE

    ref = g[g["integrator"] == REFERENCE]
    return (ref if len(ref) else g).sort_values("energy_error_max").iloc[0]


def _physics_sentence(study: pd.DataFrame) -> str:
    """What happens, from the reference solve of each scene and N, with the methods' runs as the
    second route."""
    parts = []
    for (scene, n), g in study.dropna(subset=["P_first"]).groupby(["scene", "elements"], sort=True):
        ref = _reference(g)
        others = g[g.index != ref.name]
        growth = ref.P_last / ref.P_first
        seen = (f"; the other runs at this N: ×{(others.P_last / others.P_first).min():.3g} to "
                f"×{(others.P_last / others.P_first).max():.3g}" if len(others) else "")
        word = "compression" if not scene.endswith("_slack") else "slack (tension 0)"
        parts.append(f"{scene} N={n}: P ×{growth:.3g} in the reference (`{ref.integrator}` {ref.setting}, max|ΔE| "
                     f"{ref.energy_error_max:.1e}){seen}; least tension {ref.tension_min_first:.3g} N in the first "
                     f"{ref.horizon_s / WINDOWS:g} s, {ref.tension_min_last:.3g} N in the last, an element in "
                     f"{word} at {ref.compressed_share:.0%} of the saved times")
    if not parts:
        return ""
    return ("- **What drives the energy error**: P = Σ EA l (dε/dt)², the energy in the string's axial vibration "
            f"(times ω²), window means over the first and the last {WINDOW_S:g} s: " + "; ".join(parts) + ".")


def _physics_summary(study: pd.DataFrame) -> str:
    """One or two sentences saying what happens, each backed by two routes: the reference's
    growth of P and the methods' at the same N, and at the other N."""
    plain = study[~study["scene"].astype(str).str.endswith("_slack")].dropna(subset=["P_first"])
    if plain.empty:
        return ""
    rows = [(n, _reference(g), g) for n, g in plain.groupby("elements", sort=True)]
    sym = lambda g: g[g["symplectic"]] if g["symplectic"].any() else g  # noqa: E731
    grows = [(n, ref.P_last / ref.P_first, (sym(g).P_last / sym(g).P_first).min()) for n, ref, g in rows]
    compressed = [(n, ref.tension_min) for n, ref, _ in rows]
    if all(gr > 3 and least > 3 for _, gr, least in grows):
        first = ("Energy flows from the pendulum's motion into the string's fast axial modes: the "
                 "axial measure P grows " + ", ".join(f"×{gr:.3g} at N = {n}" for n, gr, _ in grows)
                 + " in the accurate reference, and by at least " + ", ".join(f"×{least:.3g}" for _, _, least in grows)
                 + " in every symplectic run at the same N.")
    else:
        first = ("The axial measure P changes " + ", ".join(f"×{gr:.3g} at N = {n}" for n, gr, _ in grows)
                 + " in the reference (symplectic runs at the same N: at least "
                 + ", ".join(f"×{least:.3g}" for _, _, least in grows)
                 + "): no steady flow into the axial modes is claimed.")
    if all(t < 0 for _, t in compressed) and all((g["tension_min"] < 0).all() for _, _, g in rows):
        second = (" Elements go into compression (least tension " + ", ".join(f"{t:.3g} N at N = {n}" for n, t in compressed)
                  + " in the reference, " + ", ".join(f"{g['tension_min'].max():.3g} to {g['tension_min'].min():.3g} N"
                                                     for _, _, g in rows)
                  + " in the runs at the same N), which the two-sided `elasticity` law pushes back against.")
    else:
        second = ""
    return first + second


def _verdict_words(sym: pd.DataFrame, other: pd.DataFrame) -> str:
    if not len(sym):
        return "cannot be judged (no symplectic method ran)"
    if (sym["verdict"] == "bounded").all() and (other["verdict"] == "drifting").any():
        return ("pays off over a long horizon: once the modified-energy offset is taken out, every symplectic "
                "run is bounded, and the other methods' errors drift")
    if (sym["verdict"] == "bounded").all():
        return "is not visible at this horizon: every symplectic run is bounded, but no other method drifts"
    off = sym[sym["verdict"] != "bounded"]
    return ("is not shown everywhere: after the modified-energy offset, the error of "
            + ", ".join(f"`{r.integrator}` at N={r.elements} {r.setting} on {r.scene} is {r.verdict}"
                        for r in off.itertuples()))


def _energy_sentence(study: pd.DataFrame) -> str:
    if study.empty:
        return "- No energy study in this run (`--horizon 0`): nothing to say about long-horizon energy."
    horizon = study["horizon_s"].max()
    slack_rows = study["scene"].astype(str).str.endswith("_slack")
    plain = study[~slack_rows] if (~slack_rows).any() else study
    sym, other = study[study["symplectic"]], study[~study["symplectic"]]
    verdict = _verdict_words(plain[plain["symplectic"]], plain[~plain["symplectic"]])
    if slack_rows.any() and (~slack_rows).any():
        verdict += " (the string as the scene has it; the tension-only string below)"
    psym = plain[plain["symplectic"]]
    raw = psym[psym["raw_verdict"] != "bounded"]
    rule = (f"window means of E − E0 over {WINDOW_S:g} s fitted as α + β t + a X + b S, X = h^p⟨P_p⟩ the string's "
            "part, S = |Ω|² T_rot the body's spin (its coefficient fitted); "
            f"drifting when the drift over the horizon β T is at least {DRIFT_SIGMAS:g} times the residual's scatter "
            f"and outside its 2σ interval, bounded when below {BOUNDED_SIGMAS:g} scatter, undecided otherwise")
    scenes = ", ".join(dict.fromkeys(study["scene"]))
    scaling = _scaling(study)
    return (f"- **Symplecticity {verdict}** (the energy study, {horizon:g} s on {scenes}; {rule}). "
            + (f"The raw slope test on |ΔE| (the earlier label) calls {len(raw)} of these {len(psym)} symplectic runs "
               "not bounded: it cannot tell a growing modified-energy offset from drift. " if len(raw) else "")
            + f"{_physics_summary(study)}\n"
            + (f"{_physics_sentence(study)}\n" if _physics_sentence(study) else "")
            + f"- **Symplectic runs** (the offset −c_p h^p⟨P_p⟩ derived from the step: −(1/24) h²⟨U″(v,v)⟩ for the "
              f"LGVI and RATTLE, U″(v,v) = P + G the string's elastic Hessian along the velocity; c_4 h⁴⟨P4⟩ from the "
              f"composition's coefficients for `lgvi_yoshida4` and `lgvi_suzuki4`): "
            + (_run_figures(sym) or "none") + ".\n"
            + (f"- **Scaling of the offset with h** (fitted, from the two steps): {'; '.join(scaling)}.\n" if scaling else "")
            + f"- **Not symplectic** (no modified energy: nothing to take out but the part the state explains): "
            + (_run_figures(other) or "none") + "."
            + _slack_sentence(study))


def _slack_orders_sentence(path: Path) -> str:
    """The observed orders with and without `slack` (`benchmark.studies.slack_orders`), from ``path``."""
    from reelbench.benchmark.studies import slack_orders

    try:
        table = pd.read_csv(path)
    except Exception:  # noqa: BLE001 - no such measurement: nothing to say
        return ""
    o = slack_orders.orders(table)
    fmt = lambda v: ", ".join("—" if not np.isfinite(x) else f"{x:.2f}" for x in v)  # noqa: E731
    dts = ", ".join(f"{d:g}" for d in sorted(table["dt"].unique(), reverse=True))
    parts = [f"`{r.integrator}` on {r.scene}: {fmt(r.position_orders)} in position, {fmt(r.energy_orders)} in energy"
             for r in o.itertuples()]
    n = int(table["elements"].iloc[0]) if "elements" in table else slack_orders.ELEMENTS
    return (f"\n- **Observed orders with the C¹ potential** (`{slack_orders.TABLE}`: N = {n}, {slack_orders.T_END:g} s, "
            f"dt = {dts} s, largest body-position and energy error against {slack_orders.REFERENCE} at rtol "
            f"{slack_orders.REFERENCE_SETTINGS['rtol']:g}; an element slack or compressed at "
            + ", ".join(f"{r.slack_share:.0%} ({r.scene})" for r in o.drop_duplicates("scene").itertuples())
            + " of the reference's saved times; — a step that did not finish): " + "; ".join(parts) + ".")


def _slack_sentence(study: pd.DataFrame) -> str:
    """The tension-only string beside the two-sided one: the reference's growth of P and its
    time slack, and each method's verdict, at each N both were run."""
    slack = study[study["scene"].astype(str).str.endswith("_slack")].dropna(subset=["P_first"])
    if slack.empty:
        return ""
    parts = []
    for (scene, n), g in slack.groupby(["scene", "elements"], sort=True):
        base = study[(study["scene"] == scene[: -len("_slack")]) & (study["elements"] == n)].dropna(subset=["P_first"])
        ref = _reference(g)
        steps = g[g["correction"] != "none"].assign(h=lambda d: d["setting"].map(_setting_value))
        ratios = [f"`{name}` max|ΔE| {m.sort_values('h')['energy_error_max'].iloc[-1]:.2g} at h = "
                  f"{m['h'].max():g} s, {m.sort_values('h')['energy_error_max'].iloc[0]:.2g} at {m['h'].min():g} s"
                  for name, m in steps.groupby("integrator", sort=False) if m["h"].nunique() > 1]
        line = (f"N={n}: P ×{ref.P_last / ref.P_first:.3g} in the reference with `slack`"
                + (f" (×{(lambda r: r.P_last / r.P_first)(_reference(base)):.3g} without)" if len(base) else "")
                + f", an element slack at {ref.compressed_share:.0%} of the saved times; "
                + ", ".join(f"`{r.integrator}` {r.setting}: {r.verdict}"
                            + (f" ({r.status} at {r.horizon_s:g} s)" if not is_finished(r.status) else "")
                            for r in g.itertuples() if r.Index != ref.name)
                + (f" ({'; '.join(ratios)}; the derived offset does not apply: the potential is only C¹)" if ratios else ""))
        parts.append(line)
    return ("\n- **The string that cannot push** (`slack`: tension-only, a C¹ potential): " + "; ".join(parts) + ".")


def _compression_sentence(study: pd.DataFrame) -> str:
    """Whether the string's compression (least tension < 0) is in the model's solution or in a
    run's resolution: per scene and N, the least tension of the most accurate run of the study
    (the smallest energy error) against the others'."""
    if "tension_min" not in study or study["tension_min"].isna().all():
        return ""
    parts = []
    two_sided = study[~study["scene"].astype(str).str.endswith("_slack")]  # a slack string's tension is ≥ 0
    for (scene, n), g in two_sided.dropna(subset=["tension_min"]).groupby(["scene", "elements"], sort=True):
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
    from reelbench.benchmark.core.report import markdown_table

    horizon = pd.read_csv(horizon_csv) if horizon_csv is not None and Path(horizon_csv).is_file() else None
    t = property_table(runs, horizon)
    study = energy_table(horizon)
    fmt = lambda v: "" if pd.isna(v) else f"{v:.2g}"  # noqa: E731
    shown = t.assign(**{c: t[c].map(fmt) for c in ("energy_error_max", "slope_min", "slope_max", "orthogonality_max")})
    runs_shown = study.assign(**{c: study[c].map(fmt) for c in ("energy_error_max", "slope", "slope_low", "slope_high",
                                                                 "slope_all", "growth", "tension_min", "tension_min_first",
                                                                 "tension_min_last")})
    orders = _slack_orders_sentence(Path(horizon_csv).parent / "energy_slack_orders.csv") if horizon_csv else ""
    return (f"## Which property pays off where\n\n{_energy_sentence(study)}{orders}\n{_orthogonality_sentence(t)}\n"
            f"\n{markdown_table(shown)}\n"
            + (f"\n### The energy study's runs\n\n{markdown_table(runs_shown)}\n{_compression_sentence(study)}" if len(study) else ""))


#: The heading of the energy study's section in a results README (`write_energy_section`).
SECTION = "## Which property pays off where"


def write_energy_section(out: Path) -> Path | None:
    """The energy study's text from ``out``/energy_horizon.csv (with ``out``/runs.csv for the
    orthogonality, when there is one): ``out``/energy_horizon.md, and the section `SECTION` of
    ``out``/README.md replaced by it where the README has one. Returns the file written (None:
    no energy study in ``out``)."""
    from reelbench.models.io import atomic_path

    out = Path(out)
    if not (out / "energy_horizon.csv").is_file():
        return None
    runs_csv = out / "runs.csv"
    runs = pd.read_csv(runs_csv) if runs_csv.is_file() else pd.DataFrame(columns=["integrator", "status",
                                                                                  "orthogonality_error"])
    text = properties_text(runs, out / "energy_horizon.csv")
    study = pd.read_csv(out / "energy_horizon.csv", usecols=["scene", "t"])
    horizon = float(study["t"].max())
    figures = [f"energy_horizon_{s}.png" for s in dict.fromkeys(study["scene"]) if (out / f"energy_horizon_{s}.png").is_file()]
    if figures:
        text = text.rstrip("\n") + "\n\nThe energy study's figures (`python -m benchmark energy`): " + ", ".join(
            f"[{f}]({f})" for f in figures) + ".\n"
    target = out / "energy_horizon.md"
    readme = out / "README.md"
    if readme.is_file():
        import re

        old = re.sub(r"(Horizons — [^\n]*?energy study: )[0-9.]+ s", rf"\g<1>{horizon:g} s", readme.read_text(encoding="utf-8"))
        start = old.find(SECTION + "\n")
        if start >= 0:
            end = old.find("\n## ", start + len(SECTION))
            new = old[:start] + text.rstrip("\n") + "\n" + (old[end:] if end >= 0 else "")
            with atomic_path(readme) as tmp:
                Path(tmp).write_text(new, encoding="utf-8")
            target = readme
    if target.name == "energy_horizon.md":
        with atomic_path(target) as tmp:
            Path(tmp).write_text(text, encoding="utf-8")
    return target
