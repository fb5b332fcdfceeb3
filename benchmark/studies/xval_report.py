"""results/xval/: the cross-validation's tables, plots, exact inputs and README, derived from the
study's table (``cost.csv``) and its tips (`benchmark.studies.xval.Runs`; never edited by hand).

Every distance is the maximum over the compared times of the tip distance |Δ(r_p + q_{N+1})|.
Richardson limits assume order 2 in N: x_∞ = x_2N + (x_2N − x_N)/3 for N → 2N.

The equal-N check of "the same discrete model" compares our lumped model's DOP853 solution
(`xval.REFERENCE_CODE`) with each outside code at its step dt, and each outside code with itself at
dt/2 (its time error): both at most `xval.MODEL_TOLERANCE` show that the difference is the model's.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from reelbench.benchmark.figures import styles
from reelbench.benchmark.figures.plots import log_ticks, plt, save_figure, style_axes
from reelbench.benchmark.core.reference import REFERENCE_METHOD
from reelbench.benchmark.core.report import Provenance, fmt
from reelbench.benchmark.core.store import write_npz, write_table
from reelbench.benchmark.studies.xval import (CFL, DT_MAX, HALF_DT, MODEL_TOLERANCE, OURS_REFINE, OUTPUT_INTERVAL,
                                              REFERENCE_CODE, WATER, Runs, case_scene, cost_row, moordyn_input,
                                              mujoco_xml)
from reelbench.models.io import atomic_write_text
from reelbench.models.scene import Scene

REF = REFERENCE_CODE
OUTSIDE = ("moordyn", "mujoco")
#: The pairs compared at equal N, and what each difference measures.
SAME_MODEL, TIME_ERROR, LGVI_ERROR, OTHER_MODEL = ("same discrete model", "outside code's time error (dt vs dt/2)",
                                                  "our LGVI's time error", "different discrete models")
PAIRS = [(REF, "moordyn"), (REF, "mujoco"), ("moordyn", "mujoco"),
         ("moordyn", "moordyn" + HALF_DT), ("mujoco", "mujoco" + HALF_DT), ("ours_lumped", REF),
         ("ours_consistent", "moordyn"), ("ours_consistent", "mujoco"), ("ours_consistent", "ours_lumped")]
PAIR_KIND = dict(zip(PAIRS, [SAME_MODEL] * 3 + [TIME_ERROR] * 2 + [LGVI_ERROR] + [OTHER_MODEL] * 3))
TRAJ_CODES = ("ours_consistent", "ours_lumped", "moordyn", "mujoco")
_NAMES = {"moordyn": "MoorDyn", "mujoco": "MuJoCo"}


def solution(code: str, run) -> str:
    """What a code's tips are: which model, solved how."""
    if code == REF:
        return (f"{code} = our lumped model by {REFERENCE_METHOD['integrator'].upper()} (rtol {REFERENCE_METHOD['rtol']:g}, "
                f"atol {REFERENCE_METHOD['atol']:g}: the benchmark's reference solver)")
    if code in ("ours_consistent", "ours_lumped"):
        return f"{code} = our {code[5:]} model by our LGVI at {fmt(run.dt, '.4g')} s"
    base = code.removesuffix(HALF_DT)
    return f"{code} = {_NAMES.get(base, base)} by RK4 at {fmt(run.dt, '.4g')} s" + (" (dt/2)" if code.endswith(HALF_DT) else "")


def _max_dist(a, b) -> float:
    return float(np.max(np.linalg.norm(a - b, axis=1)))


def _richardson(xa, xb, Na: int, Nb: int):
    """The order-2 Richardson limit of tips ``xa`` (N = Na) and ``xb`` (N = Nb > Na)."""
    return xb + (xb - xa) / ((Nb / Na) ** 2 - 1)


def _e(x) -> str:
    return fmt(x, ".2e", missing="nan")


class Tables(NamedTuple):
    differences: pd.DataFrame  # codes at equal N
    self_convergence: pd.DataFrame  # each code, N -> next N
    limits: pd.DataFrame  # Richardson limits from the two finest N
    cost: pd.DataFrame  # wall time per step (per RHS for a reference run)


def _at_equal_n(case: str, N: int, r: dict) -> tuple[list[dict], list[dict]]:
    diff = [dict(case=case, N=N, pair=f"{a} - {b}", measures=PAIR_KIND[(a, b)],
                 max_tip_distance_m=_max_dist(r[a].tip, r[b].tip),
                 final_tip_distance_m=float(np.linalg.norm(r[a].tip[-1] - r[b].tip[-1])),
                 compared=f"{solution(a, r[a])} vs {solution(b, r[b])}")
            for a, b in PAIRS if a in r and b in r]
    cost = [cost_row(case, N, code, run) for code, run in r.items()]
    return diff, cost


def _self_convergence(study: Runs, case: str) -> list[dict]:
    rows = []
    Ns = study.elements(case)
    for code in TRAJ_CODES:
        have = [N for N in Ns if code in study.runs[(case, N)]]
        prev = None
        for N1, N2 in zip(have[:-1], have[1:]):
            d = _max_dist(study.runs[(case, N1)][code].tip, study.runs[(case, N2)][code].tip)
            rows.append(dict(case=case, code=code, N=N1, N_next=N2, max_change_m=d,
                             observed_order=(math.log(prev / d) / math.log(N2 / N1)) if prev else float("nan")))
            prev = d
    return rows


def _limits(study: Runs, case: str) -> list[dict]:
    Ns = study.elements(case)
    if len(Ns) < 2:
        return []
    Na, Nb = Ns[-2], Ns[-1]
    limits = {code: _richardson(study.runs[(case, Na)][code].tip, study.runs[(case, Nb)][code].tip, Na, Nb)
              for code in TRAJ_CODES if code in study.runs[(case, Nb)]}
    names = list(limits)
    return [dict(case=case, N_pair=f"{Na},{Nb}", pair=f"{a} - {b}", max_limit_distance_m=_max_dist(limits[a], limits[b]))
            for i, a in enumerate(names) for b in names[i + 1:]]


def tables(study: Runs) -> Tables:
    diff, conv, lim, cost = [], [], [], []
    for case in study.cases():
        for N in study.elements(case):
            d, c = _at_equal_n(case, N, study.runs[(case, N)])
            diff += d
            cost += c
        conv += _self_convergence(study, case)
        lim += _limits(study, case)
    return Tables(pd.DataFrame(diff), pd.DataFrame(conv), pd.DataFrame(lim), pd.DataFrame(cost))


def error_vs_limit(study: Runs, case: str) -> pd.DataFrame:
    """Max-over-t distance of ours_consistent and ours_lumped at each N (but the two finest, which
    define it) from the Richardson limit of ours_consistent."""
    runs, Ns = study.runs, study.elements(case)
    if len(Ns) < 3:
        return pd.DataFrame(columns=["case", "N", "consistent_m", "lumped_m", "lumped_over_consistent"])
    limit = _richardson(runs[(case, Ns[-2])]["ours_consistent"].tip, runs[(case, Ns[-1])]["ours_consistent"].tip,
                        Ns[-2], Ns[-1])
    rows = []
    for N in Ns[:-2]:
        ec = _max_dist(runs[(case, N)]["ours_consistent"].tip, limit)
        el = _max_dist(runs[(case, N)]["ours_lumped"].tip, limit)
        rows.append(dict(case=case, N=N, consistent_m=ec, lumped_m=el, lumped_over_consistent=el / ec))
    return pd.DataFrame(rows)


#: One look per code and per pair of codes, fixed (these are codes, not integrators: not the
#: methods' styles): distinct colours and markers, hollow and shrinking so that curves of the
#: same discrete model, which coincide, all stay visible.
CODE_LOOKS = {"ours_consistent": ("#1f77b4", "o", "-"), "ours_lumped": ("#ff7f0e", "s", "--"),
              "moordyn": ("#2ca02c", "^", "-."), "mujoco": ("#d62728", "D", ":")}
PAIR_LOOKS = {(REF, "moordyn"): ("#9467bd", "o", "-"), (REF, "mujoco"): ("#8c564b", "s", "--"),
              ("moordyn", "mujoco"): ("#e377c2", "^", "-."), ("moordyn", "moordyn" + HALF_DT): ("#2ca02c", "x", ":"),
              ("mujoco", "mujoco" + HALF_DT): ("#d62728", "+", ":"), ("ours_lumped", REF): ("#ff7f0e", "*", "-."),
              ("ours_consistent", "moordyn"): ("#17becf", "v", ":"),
              ("ours_consistent", "mujoco"): ("#bcbd22", "D", "-"), ("ours_consistent", "ours_lumped"): ("#7f7f7f", "P", "--")}


def _looks(keys, table) -> list[dict]:
    return [dict(color=c, marker=m, linestyle=ls, markersize=ms, markerfacecolor="none", markeredgecolor=c)
            for (c, m, ls), ms in zip((table[k] for k in keys), [10, 9, 8, 7, 6, 5, 4, 3, 3])]


def plot(study: Runs, case: str, path: Path) -> Path:
    runs, Ns = study.runs, study.elements(case)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    handles, labels = [], []
    for (a, b), look in zip(PAIRS, _looks(PAIRS, PAIR_LOOKS)):
        name = f"{a} − {b}"
        vals = [(N, _max_dist(runs[(case, N)][a].tip, runs[(case, N)][b].tip)) for N in Ns
                if a in runs[(case, N)] and b in runs[(case, N)]]
        if vals:
            handles += ax.loglog(*zip(*vals), **look)
            labels.append(f"left: {name}")
    if Ns:
        handles.append(ax.axhline(MODEL_TOLERANCE, color="0.4", linestyle=(0, (1, 2))))
        labels.append(f"left: {MODEL_TOLERANCE:g} m (same model)")
    style_axes(ax, xlabel="N (elements)", ylabel="max over t of tip distance [m]", title=f"{case}: codes at equal N",
               grid=None, legend=None)
    for code, look in zip(TRAJ_CODES, _looks(TRAJ_CODES, CODE_LOOKS)):
        have = [N for N in Ns if code in runs[(case, N)]]
        vals = [(N2, _max_dist(runs[(case, N1)][code].tip, runs[(case, N2)][code].tip)) for N1, N2 in zip(have[:-1], have[1:])]
        if vals:
            handles += ax2.loglog(*zip(*vals), **look)
            labels.append(f"right: {code}")
    if len(Ns) > 1:
        ref = np.array(Ns[1:], float)
        handles += ax2.loglog(ref, 0.5 * (ref / ref[0]) ** -2, color="0.4", linestyle=(0, (1, 2)))
        labels.append("right: slope −2")
    style_axes(ax2, xlabel="N", ylabel="max |tip(N) − tip(N/2)| [m]", title=f"{case}: self-convergence", grid=None,
               legend=None)
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

    for a in (ax, ax2):
        log_ticks(a)
        if Ns:  # N is one of few integers: label each one
            a.xaxis.set_major_locator(FixedLocator(Ns))
            a.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            a.xaxis.set_minor_locator(NullLocator())
    fig.tight_layout()
    styles.legend_outside(fig, handles, labels)
    return save_figure(fig, path, dpi=120)


# ------------------------------------------------------------------------------------------
# Files
# ------------------------------------------------------------------------------------------
def _write_inputs(study: Runs, scene: Scene, out: Path, kept: dict | None = None) -> dict:
    """The exact inputs given to MoorDyn and MuJoCo (``inputs/``) and ``settings.json``; returns
    the settings. ``kept``: {(case, N): settings entry} of earlier runs merged into the study,
    whose inputs and entries are kept as they were."""
    kept = kept or {}
    inputs = out / "inputs"
    inputs.mkdir(exist_ok=True)
    settings = {"scene": scene.name, "t_end": float(study.times[-1]), "output_interval": OUTPUT_INTERVAL,
                "cfl": CFL, "dt_max": DT_MAX, "ours": {"method": "lgvi", "dt": f"outside dt / {OURS_REFINE}"},
                "same_model": {"ours": REF, "method": dict(REFERENCE_METHOD), "outside": "RK4 at dt",
                               "time_error_check": f"each outside code rerun at dt/2 (code <code>{HALF_DT}; its input is "
                                                   "the one in inputs/ with the time step halved)",
                               "tolerance_m": MODEL_TOLERANCE},
                "runs": []}
    for case in study.cases():
        for N in study.elements(case):
            if (case, N) in kept:
                settings["runs"].append(kept[(case, N)])
                continue
            r = study.runs[(case, N)]
            sc = case_scene(scene, case).with_(elements=N, mass_model="lumped", t_end=settings["t_end"])
            dt = next(v.dt for k, v in r.items() if k in OUTSIDE)
            if "moordyn" in r:
                atomic_write_text(inputs / f"moordyn_{case}_N{N}.txt", moordyn_input(sc, dt))
            if "mujoco" in r:
                atomic_write_text(inputs / f"mujoco_{case}_N{N}.xml", mujoco_xml(sc, dt))
            settings["runs"].append({"case": case, "N": N, "dt": dt, "scene_key_lumped": sc.key(),
                                     "min_strain_ours_lumped": r["ours_lumped"].extra["min_strain"]})
    atomic_write_text(out / "settings.json", json.dumps(settings, indent=1))
    return settings


def write_report(study: Runs, scene: Scene, out: Path, provenance: Provenance, kept: dict | None = None) -> Path:
    """Every file but the study's own table and tips (cost.csv and tips.npz, which the runner
    saves): the derived tables (CSV), plots, the exact inputs given to MoorDyn and MuJoCo, and the
    README. ``kept``: the settings entries of the earlier runs merged into ``study``
    (`benchmark.studies.xval_output.Output`)."""
    out.mkdir(parents=True, exist_ok=True)
    tabs = tables(study)
    err = pd.concat([error_vs_limit(study, c) for c in study.cases()], ignore_index=True)
    for name, df in (*tabs._asdict().items(), ("error_vs_limit", err)):
        if name != "cost":
            write_table(out / f"{name}.csv", df)
    settings = _write_inputs(study, scene, out, kept)
    for case in study.cases():
        plot(study, case, out / f"convergence_{case}.png")
    atomic_write_text(out / "README.md", readme(study, scene, tabs, settings, provenance))
    return out / "README.md"


def write_outputs(study: Runs, scene: Scene, out: Path, provenance: Provenance, kept: dict | None = None) -> Path:
    """Every file of the study from its runs, without the runner: the table (cost.csv), the raw
    tip trajectories (so that the tables can be recomputed without rerunning) and `write_report`'s."""
    out.mkdir(parents=True, exist_ok=True)
    write_table(out / "cost.csv", tables(study).cost)
    write_npz(out / "tips.npz", {"times": study.times, **{f"{case}_N{N}_{code}": run.tip
                                                          for (case, N), r in study.runs.items() for code, run in r.items()}},
              compressed=True)
    return write_report(study, scene, out, provenance, kept)


# ------------------------------------------------------------------------------------------
# The README
# ------------------------------------------------------------------------------------------
def _rows(df: pd.DataFrame, **kw) -> pd.DataFrame:
    for k, v in kw.items():
        df = df[df[k] == v]
    return df


def _pair_max(diff: pd.DataFrame, case: str, N: int | None, a: str, b: str) -> float:
    d = _rows(diff, case=case, pair=f"{a} - {b}")
    if N is not None:
        d = _rows(d, N=N)
    return float(d.max_tip_distance_m.max()) if len(d) else float("nan")


def _agreement(study: Runs, case: str, tabs: Tables, outside: list[str]) -> list[str]:
    """The same discrete model in several codes at equal N (our lumped model's DOP853 solution
    against each outside code, and each outside code's own time error), and our consistent model."""
    Ns, diff = study.elements(case), tabs.differences
    tol = MODEL_TOLERANCE
    cols = [(REF, c) for c in outside] + [(c, c + HALF_DT) for c in outside]
    if len(outside) == 2:
        cols.append(("moordyn", "mujoco"))
    cols.append(("ours_lumped", REF))
    head = {(REF, c): f"{REF} − {c}" for c in outside} | {(c, c + HALF_DT): f"{c}: dt vs dt/2" for c in outside} \
        | {("moordyn", "mujoco"): "moordyn − mujoco", ("ours_lumped", REF): f"ours_lumped (LGVI) − {REF}"}
    table = {(N, p): _pair_max(diff, case, N, *p) for N in Ns for p in cols}
    model = [(N, c, table[(N, (REF, c))]) for N in Ns for c in outside]
    steps = [(N, c, table[(N, (c, c + HALF_DT))]) for N in Ns for c in outside]
    missing = [f"{c} at N = {N}" for N, c, v in model + steps if not np.isfinite(v)]
    over = [f"{c} at N = {N}: {_e(v)} m" for N, c, v in model if v > tol]
    over_steps = [f"{c} at N = {N}: {_e(v)} m" for N, c, v in steps if v > tol]
    finite = [v for _, _, v in model if np.isfinite(v)]
    lines = [f"- Same discrete model (required: at most {tol:g} m at every N, and each outside code's own time error "
             "below that too, so that the difference measures the models, not the time steppers): our lumped model "
             f"solved by {REFERENCE_METHOD['integrator'].upper()} at rtol {REFERENCE_METHOD['rtol']:g}, atol "
             f"{REFERENCE_METHOD['atol']:g} (`{REF}`, the benchmark's reference solver) vs {' and '.join(outside)} by RK4 "
             f"at dt, at equal N: at most {_e(max(finite) if finite else float('nan'))} m over N = {Ns[0]}…{Ns[-1]}; "
             "each outside code's time error (the change of its tip when its dt is halved): at most "
             f"{_e(max((v for *_, v in steps if np.isfinite(v)), default=float('nan')))} m."]
    if over or over_steps or missing:
        lines.append("- NOT shown at every N: " + "; ".join(
            ([f"model difference above {tol:g} m for " + ", ".join(over)] if over else [])
            + ([f"time error of the outside code above {tol:g} m for " + ", ".join(over_steps)] if over_steps else [])
            + ([f"no DOP853 or dt/2 run (kept from an older study) for " + ", ".join(missing)] if missing else [])) + ".")
    else:
        lines.append(f"- Both are at most {tol:g} m at every N of this case.")
    lines += ["", "Max over t of the tip distance at equal N [m] (`differences.csv`, which names the compared solutions "
              "and their steps in its `compared` column):", "",
              "| N | dt [s] | " + " | ".join(head[p] for p in cols) + " |", "|---|---|" + "---|" * len(cols)]
    for N in Ns:
        dt = study.runs[(case, N)][outside[0]].dt
        lines.append(f"| {N} | {fmt(dt, '.3g')} | " + " | ".join(_e(table[(N, p)]) for p in cols) + " |")
    lines.append("")
    if len(outside) == 2:
        lines.append(f"- MoorDyn vs MuJoCo (the same RK4 at the same dt): at most "
                     f"{_e(_pair_max(diff, case, None, 'moordyn', 'mujoco'))} m.")
    lines.append(f"- Our LGVI at dt/{OURS_REFINE} (the runs of the cost table and of the convergence study below) differs "
                 f"from the DOP853 solution by up to {_e(_pair_max(diff, case, None, 'ours_lumped', REF))} m: its time error, "
                 "not a model difference.")
    for c in outside:
        d = _rows(diff, case=case, pair=f"ours_consistent - {c}")
        lines.append(f"- Our consistent model vs {c}: {_e(float(d.max_tip_distance_m.iloc[0]))} m at N = {Ns[0]}, "
                     f"{_e(float(d.max_tip_distance_m.iloc[-1]))} m at N = {Ns[-1]}.")
    return lines


def _convergence(study: Runs, case: str, tabs: Tables, outside: list[str]) -> list[str]:
    """Each code's self-convergence, the agreement of the Richardson limits, the error against
    the consistent model's limit."""
    lines = []
    for code in ("ours_consistent", "ours_lumped") + tuple(outside):
        cv = _rows(tabs.self_convergence, case=case, code=code) if len(tabs.self_convergence) else []
        if not len(cv):  # one N so far (a stopped study)
            continue
        orders = cv.observed_order.dropna()
        lines.append(f"- Self-convergence of {code}: max |tip(N) − tip(N/2)| from {_e(float(cv.max_change_m.iloc[0]))} "
                     f"(N = {int(cv.N_next.iloc[0])}) to {_e(float(cv.max_change_m.iloc[-1]))} m (N = {int(cv.N_next.iloc[-1])}); "
                     f"observed orders {', '.join(f'{o:.2f}' for o in orders)}.")
    if tabs.limits.empty:
        return lines
    lc = _rows(tabs.limits, case=case)
    for c in outside:
        for ours in ("ours_consistent", "ours_lumped"):
            v = _rows(lc, pair=f"{ours} - {c}")
            if len(v):
                lines.append(f"- Richardson limits (N = {v.N_pair.iloc[0]}): {ours} vs {c} agree to "
                             f"{_e(float(v.max_limit_distance_m.iloc[0]))} m.")
    v = _rows(lc, pair="ours_consistent - ours_lumped")
    if len(v):
        lines.append(f"- Richardson limits: ours_consistent vs ours_lumped agree to {_e(float(v.max_limit_distance_m.iloc[0]))} m.")
    err = error_vs_limit(study, case)
    if len(err):
        ratios = ", ".join(f"{r:.2f} (N = {n})" for n, r in zip(err.N, err.lumped_over_consistent))
        lines.append(f"- Error against the Richardson limit of ours_consistent (max over t), lumped / consistent at "
                     f"equal N: {ratios} (`error_vs_limit.csv`).")
    return lines


def _cost_table(study: Runs, case: str, tabs: Tables, outside: list[str]) -> list[str]:
    cost = _rows(tabs.cost, case=case)
    codes = [c for c in (*OUTSIDE, "ours_consistent", "ours_lumped") if c in set(cost.code)]
    lines = ["Wall time per step at equal N (µs; MoorDyn and MuJoCo: one RK4 step = 4 force evaluations, at dt, "
             f"median over the {len(study.times) - 1} output intervals; ours: one LGVI step, at dt/{OURS_REFINE}, "
             f"mean over the run, compile time excluded; the dt/2 reruns and {REF} (per right-hand side) are in "
             "`cost.csv`):", "",
             "| N | dt [s] | " + " | ".join(codes) + " |", "|---|---|" + "---|" * len(codes)]
    for N in study.elements(case):
        cN = _rows(cost, N=N).set_index("code")
        lines.append(f"| {N} | {float(cN.loc[outside[0], 'dt_s']):.3g} | "
                     + " | ".join(f"{float(cN.loc[c, 'us_per_step']):.1f}" for c in codes) + " |")
    return lines


def readme(study: Runs, scene: Scene, tabs: Tables, settings: dict, provenance: Provenance) -> str:
    lines = [
        "# Cross-validation against MoorDyn and MuJoCo", "",
        provenance.header(extra_packages=OUTSIDE), "",
        f"- scene: `{scene.name}` at fixed length ℓ = {scene.initial.deployed_length:g} m, μ = {scene.string.mass_per_length:g} kg/m, "
        f"EA = {scene.string.axial_stiffness:g} N, m_b = {scene.body.mass:g} kg, straight unstretched start along "
        f"{[round(float(x), 6) for x in scene.initial.direction]}, tip velocity {[float(x) for x in scene.initial.tip_velocity]} m/s, "
        f"over {settings['t_end']:g} s; point_mass = the same without `rigid_body`; in_water = point_mass in water "
        "(buoyancy and Morison drag, `benchmark.studies.xval.WATER`: "
        + ", ".join(f"{k} = {v:g}" for k, v in WATER.items()) + "; MoorDyn without added mass).",
        f"- compared quantity: the attachment point r_p + q_(N+1) (the tip) at t = 0, {OUTPUT_INTERVAL:g}, … s; "
        "every distance below is the maximum over those times.",
        f"- MoorDyn and MuJoCo: RK4 at dt = min({DT_MAX:g}, {CFL:g}/ω_max), ω_max = (2/l)√(EA/μ) (dt per N in "
        "`settings.json`), and again at dt/2 (`moordyn_half_dt`, `mujoco_half_dt`: their time error); their exact "
        "inputs (at dt) are in `inputs/`. Ours: our LGVI at that dt / "
        f"{OURS_REFINE} (consistent = the paper's mass matrix, lumped = `mass_model = \"lumped\"`, models/README.md), "
        f"and the lumped model by {REFERENCE_METHOD['integrator'].upper()} at rtol {REFERENCE_METHOD['rtol']:g}, atol "
        f"{REFERENCE_METHOD['atol']:g} (`{REF}`, `benchmark.core.reference`'s solver): the solution compared with the outside "
        "codes at equal N.",
        "- files: `differences.csv` (codes at equal N: what each pair measures, `measures`, and the solutions compared, "
        "`compared`), `self_convergence.csv` (each code, N → next N), "
        "`limits.csv` (Richardson limits, order 2, from the two finest N), `error_vs_limit.csv`, `cost.csv` "
        "(wall time per step), `convergence_*.png`, `tips.npz` (every tip trajectory), `settings.json`.",
        "", "## Reading", "",
    ]
    for case in study.cases():
        outside = [c for c in OUTSIDE if c in study.runs[(case, study.elements(case)[0])]]
        minstrain = min(s["min_strain_ours_lumped"] for s in settings["runs"] if s["case"] == case)
        lines += [f"### {case} (outside codes: {', '.join(outside)})", "",
                  *_agreement(study, case, tabs, outside), *_convergence(study, case, tabs, outside),
                  f"- Smallest element strain of our lumped runs: {minstrain:.2e} (MoorDyn's lines are tension-only; "
                  "a clearly negative value would make MoorDyn differ).", "",
                  *_cost_table(study, case, tabs, outside), ""]
    lines += ["Timings are single runs on a shared machine (see the load average above): read them as magnitudes.", ""]
    return "\n".join(lines)
