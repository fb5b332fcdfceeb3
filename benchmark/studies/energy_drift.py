"""The energy verdicts behind "which geometric property pays off where": the energy study's
runs (`energy_table`) and each method's properties (`property_table`), from the runs table and
the energy study. The section's text is `benchmark.studies.properties`'s.

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

import numpy as np
import pandas as pd

from reelbench.benchmark.core.policy import axis_of, setting_value
from reelbench.integrators.base import FINISHED_STATUSES, Status

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
