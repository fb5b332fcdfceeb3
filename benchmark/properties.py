"""Which geometric property pays off where: generated from the runs table and the energy study.

The methods split by what they declare (`integrators.Capability`): *variational* (symplectic:
the LGVI family, RATTLE), *group-preserving* (the attitude stays on SO(3) by construction: the
LGVI family, the Lie group Runge–Kutta methods) or neither (the Runge–Kutta baselines on a
quaternion state). Two measured quantities separate the properties:

* energy over a long horizon (the energy study, `energy_horizon.csv`): the trend of the energy
  error, as the ratio of its drift (the least-squares line's rise over the horizon) to its scatter
  about that line (their standard deviation). A symplectic method's error oscillates without a
  trend (a ratio of order 1: the motion is chaotic, so its excursions do not average out over a
  short horizon); a method that is not symplectic drifts (the ratio grows with the horizon);
* orthogonality (the sweep, `runs.csv`): the largest ‖RᵀR − I‖ over the method's finished runs.

The words are chosen from those numbers, never written by hand: rerun to regenerate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

#: drift-to-scatter ratios below / above which an energy error is called bounded / drifting
BOUNDED_BELOW, DRIFTING_ABOVE = 3.0, 5.0
#: an orthogonality error below this is round-off: products of rotations accumulate ~√n ε over
#: the n ≤ 10⁶ steps of a sweep's finest settings
ROUND_OFF = 1e-10


def drift_ratio(t: np.ndarray, err: np.ndarray) -> float:
    """|slope| · T / std(residual) of the least-squares line through |err|(t) (nan if undefined)."""
    t, err = np.asarray(t, float), np.abs(np.asarray(err, float))
    good = np.isfinite(t) & np.isfinite(err)
    t, err = t[good], err[good]
    if len(t) < 10 or t[-1] <= t[0]:
        return float("nan")
    A = np.vstack([t, np.ones_like(t)]).T
    coef = np.linalg.lstsq(A, err, rcond=None)[0]
    scatter = float(np.std(err - A @ coef))
    return float(abs(coef[0]) * (t[-1] - t[0]) / scatter) if scatter > 0 else float("inf")


def _kind(name: str) -> tuple[bool, bool]:
    from integrators import Capability, get_integrator

    try:
        caps = get_integrator(name).capabilities
    except ValueError:  # a method in an old table that is no longer registered
        return False, False
    return Capability.VARIATIONAL in caps, Capability.GROUP_PRESERVING in caps


def property_table(runs: pd.DataFrame, horizon: pd.DataFrame | None) -> pd.DataFrame:
    """One row per method of the energy study or the sweep: its properties, the largest energy
    error of the study and its drift ratio, and the largest orthogonality error."""
    rows = {}
    if horizon is not None and len(horizon):
        for (name, label), g in horizon.groupby(["integrator", "method"], sort=False):
            g = g.sort_values("t")
            rows[name] = {"integrator": name, "energy_study": str(label), "horizon_s": float(g["t"].iloc[-1]),
                          "energy_error_max": float(np.max(np.abs(g["energy_error"]))),
                          "drift_ratio": drift_ratio(g["t"].to_numpy(), g["energy_error"].to_numpy())}
    ok = runs[runs["status"] == "ok"]
    for name, g in ok.groupby("integrator", sort=True):
        ortho = pd.to_numeric(g["orthogonality_error"], errors="coerce").max()
        rows.setdefault(name, {"integrator": name})["orthogonality_max"] = float(ortho)
    for name, row in rows.items():
        row["symplectic"], row["group_preserving"] = _kind(name)
    cols = ["integrator", "symplectic", "group_preserving", "energy_study", "horizon_s", "energy_error_max",
            "drift_ratio", "orthogonality_max"]
    return pd.DataFrame(list(rows.values())).reindex(columns=cols)


def _names(df: pd.DataFrame) -> str:
    return ", ".join(f"`{n}`" for n in df["integrator"]) or "none"


def _energy_sentence(t: pd.DataFrame) -> str:
    study = t.dropna(subset=["drift_ratio"])
    if study.empty:
        return "- No energy study in this run (`--horizon 0`): nothing to say about long-horizon energy."
    horizon = study["horizon_s"].max()
    def listed(df):
        return "; ".join(f"`{r.integrator}` {r.drift_ratio:.1f} (error up to {r.energy_error_max:.1e})"
                         for r in df.itertuples())
    sym, other = study[study["symplectic"]], study[~study["symplectic"]]
    bounded = sym["drift_ratio"] < BOUNDED_BELOW
    drifting = other["drift_ratio"] > DRIFTING_ABOVE
    verdict = ("pays off over a long horizon" if len(sym) and bounded.all() and drifting.any() else
               "is not visible at this horizon" if len(sym) else "cannot be judged (no symplectic method ran)")
    small = ""
    if len(sym) and len(other) and sym["energy_error_max"].min() > other["energy_error_max"].min():
        best = other.sort_values("energy_error_max").iloc[0]
        small = (f" Bounded is not small: at the study's settings `{best.integrator}` keeps the smaller error over "
                 f"{horizon:g} s; the trend is what decides beyond it.")
    return (f"- **Symplecticity {verdict}** (the energy study, {horizon:g} s on fixed_length; "
            f"the ratio of the energy error's drift over the horizon to its scatter about the fitted line: "
            f"bounded below {BOUNDED_BELOW:g}, drifting above {DRIFTING_ABOVE:g}). "
            f"Symplectic: {listed(sym) or 'none'}. Not symplectic: {listed(other) or 'none'}.{small}")


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
    shown = t.assign(**{c: t[c].map(lambda v: "" if pd.isna(v) else f"{v:.2g}")
                        for c in ("energy_error_max", "drift_ratio", "orthogonality_max")})
    return (f"## Which property pays off where\n\n{_energy_sentence(t)}\n{_orthogonality_sentence(t)}\n"
            f"\n{markdown_table(shown)}\n")
