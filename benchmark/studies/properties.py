"""The generated section "Which property pays off where" of a results README, and the energy
study's text (`write_energy_section`), from the verdicts of `benchmark.studies.energy_drift`: the
energy study's runs and each method's properties (read that module's docstring for the rules).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from reelbench.benchmark.core.policy import setting_value
from reelbench.benchmark.studies.energy_drift import (  # noqa: F401 - the verdicts, importable from here too
    BOUNDED_BELOW, BOUNDED_SIGMAS, DRIFT_SIGMAS, DRIFTING_FROM, ROUND_OFF, WINDOW_S, WINDOWS, classify, correction_of,
    drift_fit, energy_table, is_symplectic, property_table, shadow_coefficient, window_means)
from reelbench.integrators.base import is_finished


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
        g = g.assign(h=g["setting"].map(setting_value)).sort_values("h", ascending=False)
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
        steps = g[g["correction"] != "none"].assign(h=lambda d: d["setting"].map(setting_value))
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
