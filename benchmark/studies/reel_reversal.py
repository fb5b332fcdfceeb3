"""Orders of the fixed-step methods across a reel reversal (s_p-dot changes sign).

    python -m benchmark reel-reversal [--elements 5] [--t-end 0.96] [--integrators lgvi,lgvi_sym,...] [--max-steps N] [--out DIR]

Runs the hard scene ``reel_reversal`` (the Carnot force's ṡ|ṡ| is only C¹ where ṡ_p = 0) with
each method at halving step sizes and writes a markdown table of the errors against the
benchmark's reference solution (`benchmark.core.reference`: DOP853 at rtol 1e-12, atol 1e-14):
maximum over the compared times (every `COMPARE_EVERY` s) of the body position
|q_{N+1} − q_ref|, of |s_p − s_ref| and of |(E − W) − E0|, with the observed orders. Also says
when ṡ_p changes sign in the reference.

A study on the one runner (`study`, `benchmark.core.study.run`): every (method, step) run is one
job (a method's jobs in one worker: one compile), after the reference is computed into its
cache. Into ``--out`` (default `OUT_DIR`): ``reel_reversal.csv``, a row per case (scene, N,
horizon), method and step, saved as each job finishes (rows of other cases, methods and steps
are kept), and ``reel_reversal.md``, the tables of the whole table under the report header,
also printed. A rerun computes only the rows the table lacks from the same code and settings
(`key`); ``--fresh`` all of them. Each run is bounded by the job's budget
(`benchmark.studies.budget`: --max-steps, --time-limit): a run past it is a row with status
max_steps / time_limit, recomputed on resume.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from reelbench.benchmark.core.order import last_order
from reelbench.benchmark.core.policy import RESULTS, Setting
from reelbench.benchmark.studies import budget as _budget

#: Where the study writes by default.
OUT_DIR = RESULTS / "reel_reversal"
#: step sizes per method (s): each in its asymptotic range on the smooth reel scenes, above round-off
DEFAULT_HS = {"lgvi": (0.004, 0.002, 0.001, 0.0005), "lgvi_sym": (0.004, 0.002, 0.001, 0.0005),
              "lgvi_yoshida4": (0.004, 0.002, 0.001, 0.0005), "lgvi_suzuki4": (0.008, 0.004, 0.002, 0.001),
              "tsit5": (0.016, 0.008, 0.004, 0.002)}  # constant-step Tsit5 (order 5), for comparison
COMPARE_EVERY = 0.08
#: the reference's save interval: the sign changes of ṡ_p are located between its saved points
FLIP_RESOLUTION = 0.001


def check_horizon(t_end: float) -> None:
    """ValueError unless ``t_end`` is a multiple of `COMPARE_EVERY` (the compared times end there)."""
    if abs(t_end / COMPARE_EVERY - round(t_end / COMPARE_EVERY)) > 1e-9:
        raise ValueError(f"--t-end = {t_end:g} is invalid (allowed: a multiple of {COMPARE_EVERY:g} s)")


def check_methods(methods) -> None:
    """ValueError naming a method without a step list."""
    for m in methods:
        if m not in DEFAULT_HS:
            raise ValueError(f"--integrators: {m!r} has no step list (allowed: {', '.join(DEFAULT_HS)})")


class Reference(NamedTuple):
    """The reference trajectory (saved every `FLIP_RESOLUTION` s) and the times where ṡ_p
    changes sign in it (linear interpolation between saved points)."""

    traj: object
    flips: np.ndarray


def reference(scene, t_end: float, cache_dir: str | Path) -> Reference:
    from reelbench.benchmark.core.reference import get_reference

    traj = get_reference(scene, t_end, FLIP_RESOLUTION, Path(cache_dir))
    t, rate = np.asarray(traj.t), np.asarray(traj.velocity)[:, 0]
    k = np.nonzero(np.sign(rate[1:]) != np.sign(rate[:-1]))[0]
    flips = t[k] - rate[k] * (t[k + 1] - t[k]) / (rate[k + 1] - rate[k])
    return Reference(traj, flips)


class Errors(NamedTuple):
    """Maxima over the compared times: body position (m), s_p (m), |(E − W) − E0| (J)."""

    body: float
    s_p: float
    energy: float


def errors(scene, tr, ref, e0: float) -> Errors:
    """The errors of the run ``tr`` against the reference trajectory ``ref`` at the run's saved
    times (which the reference's include); ``e0``: E − W of the reference at t = 0."""
    from reelbench.models.diagnostics import evaluate

    ref_t = np.asarray(ref.t)
    j = np.searchsorted(ref_t, np.asarray(tr.t) - 1e-9)
    if np.any(np.abs(ref_t[j] - tr.t) > 1e-9):
        raise ValueError("the reference is not saved at the run's times")
    x, xr = np.asarray(tr.x), np.asarray(ref.x)[j]
    body = np.linalg.norm(x[:, -3:] - xr[:, -3:], axis=1)  # the body's node q_{N+1} is x's last three
    ew = evaluate(scene, tr).energy_minus_work.to_numpy()
    return Errors(float(body.max()), float(np.abs(x[:, 0] - xr[:, 0]).max()), float(np.max(np.abs(ew - e0))))


class Job(NamedTuple):
    method: str
    h: float
    scene_name: str
    elements: int
    t_end: float
    cache_dir: str
    budget: object = None  # of the run (`runner.SolveBudget`); None: the defaults


def case(scene, t_end: float) -> str:
    """The case a row belongs to: scene, N and horizon (the table holds several)."""
    return f"{scene.name} N={scene.string.elements} t_end={t_end:g}"


def run_job(job: Job) -> dict:
    """One method at one step: its status and its errors against the (cached) reference."""
    from reelbench.integrators import get_integrator
    from reelbench.models import load_scene
    from reelbench.models.diagnostics import evaluate

    scene = load_scene(job.scene_name, elements=job.elements)
    ref = reference(scene, job.t_end, job.cache_dir)
    tr = get_integrator(job.method).solve(scene, t_end=job.t_end, dt=job.h, save_every=COMPARE_EVERY,
                                          **_budget.solve_kwargs(job.budget))
    row = {**_base_row(job, scene), "status": tr.status, "reason": tr.reason,
           "reversals": " ".join(f"{t:.6g}" for t in ref.flips)}
    if tr.ok:
        e = errors(scene, tr, ref.traj, float(evaluate(scene, ref.traj).energy_minus_work.iloc[0]))
        row.update({f"error_{k}": v for k, v in e._asdict().items()})
    return row


def _base_row(job: Job, scene) -> dict:
    return {"case": case(scene, job.t_end), "scene": scene.name, "elements": job.elements, "t_end": job.t_end,
            "method": job.method, "setting": Setting.fixed(job.h).label(), "h": job.h}


#: A row of the table: one per case, method and step.
IDENTITY = ("case", "method", "setting")
TEXT_COLUMNS = ("case", "scene", "method", "setting", "status", "reason", "reversals")
COLUMNS = (*IDENTITY, "scene", "elements", "t_end", "h", "status", "reason", "error_body", "error_s_p", "error_energy",
           "reversals")


def crash_row(job: Job, exc: BaseException) -> dict:
    """The row of a job whose worker died."""
    from reelbench.benchmark.core.engine import crash_reason
    from reelbench.integrators.base import CRASHED
    from reelbench.models import load_scene

    return {**_base_row(job, load_scene(job.scene_name, elements=job.elements)), "status": CRASHED,
            "reason": crash_reason(exc)}


def _errors(row: dict) -> Errors | None:
    """The row's errors, None when its run did not finish."""
    from reelbench.integrators.base import is_finished

    if not is_finished(row.get("status")):
        return None
    return Errors(*(float(row[f"error_{k}"]) for k in Errors._fields))


def describe(row: dict) -> str:
    e = _errors(row)
    what = ", ".join(f"{k} {v:.2e}" for k, v in e._asdict().items()) if e else row["status"]
    return f"{row['method']} h = {row['h'] * 1e3:g} ms: {what}"


def to_frame(rows: list[dict]):
    from reelbench.benchmark.core.store import frame

    return frame(rows, list(COLUMNS))


def table(scene, t_end: float, flips, rows: list[dict]) -> str:
    """The Markdown table of the rows (in method, then step order), orders between successive steps."""
    return _table(f"scene {scene.name}, N = {scene.string.elements}, t_end = {t_end:g} s", flips, rows)


def _table(title: str, flips, rows: list[dict]) -> str:
    lines = [f"{title}; s_p-dot changes sign at t = " + ", ".join(f"{t:.3f}" for t in flips) + " s",
             "", "| method | h [ms] | body [m] | s_p [m] | E-W [J] | orders (body / s_p / E-W) |", "|---|---|---|---|---|---|"]

    prev = prev_h = None
    for i, r in enumerate(rows):
        if i == 0 or r["method"] != rows[i - 1]["method"]:
            prev = None
        e = _errors(r)
        if e is None:
            lines.append(f"| {r['method']} | {r['h'] * 1e3:g} | {r['status']}: {r['reason']} | | | |")
            continue
        steps = (prev_h, r["h"])
        orders = " / ".join(f"{last_order(steps, (a, b)):.2f}" for a, b in zip(prev, e)) if prev else ""
        lines.append(f"| {r['method']} | {r['h'] * 1e3:g} | {e.body:.2e} | {e.s_p:.2e} | {e.energy:.2e} | {orders} |")
        prev, prev_h = e, r["h"]
    return "\n".join(lines)


def tables(rows: list[dict]) -> str:
    """The table of every case of ``rows`` (a merged table's rows, in any order): each case's rows
    by method (`DEFAULT_HS`' order first) and step, coarsest first."""
    cases = list(dict.fromkeys(r["case"] for r in rows))
    methods = list(dict.fromkeys([*DEFAULT_HS, *(r["method"] for r in rows)]))
    out = []
    for c in cases:
        mine = sorted((r for r in rows if r["case"] == c), key=lambda r: (methods.index(r["method"]), -float(r["h"])))
        flips = [float(t) for t in str(mine[0].get("reversals") or "").split()]
        r0 = mine[0]
        out.append(_table(f"scene {r0['scene']}, N = {int(r0['elements'])}, t_end = {float(r0['t_end']):g} s", flips,
                          mine))
    return "\n\n".join(out)


def warm_reference(scene_name: str, elements: int, t_end: float, cache_dir: str) -> None:
    """The reference of the case, computed into its cache (a setup call of the study)."""
    from reelbench.models import load_scene

    reference(load_scene(scene_name, elements=elements), t_end, cache_dir)


def key(job: Job) -> str:
    """What determines a row: the scene's physics, N, horizon, method and step, the budget
    (`budget.key_settings`), the code."""
    from reelbench.benchmark.core.study import job_key
    from reelbench.models import load_scene

    return job_key({"scene": load_scene(job.scene_name, elements=job.elements).key(), "elements": job.elements,
                    "t_end": job.t_end, "method": job.method, "h": job.h, **_budget.key_settings(job.budget)},
                   "benchmark/studies/reel_reversal.py")


def study(scene_name: str = "reel_reversal", elements: int = 5, t_end: float = 0.96, methods=None, *,
          workers: int | None = None, cache_dir: str | None = None, budget=None, echo=print):
    """The reel-reversal orders as a study of `benchmark.core.study.run` (see the module's
    docstring). ``workers``: None, one per method (`engine.default_workers`); ``budget``: of each
    run (None: the defaults)."""
    import functools

    from reelbench.benchmark.core.engine import default_workers
    from reelbench.benchmark.core.reference import CACHE_DIR
    from reelbench.benchmark.core.study import Study
    from reelbench.models import load_scene

    cache_dir = str(cache_dir or CACHE_DIR)
    scene = load_scene(scene_name, elements=elements)
    methods = list(methods or DEFAULT_HS)
    check_methods(methods)
    jobs = [Job(m, h, scene_name, elements, t_end, cache_dir, budget) for m in methods for h in DEFAULT_HS[m]]
    ids = {j: (case(scene, t_end), j.method, Setting.fixed(j.h).label()) for j in jobs}

    def report(out, rows: list[dict], provenance) -> str:
        from reelbench.models.io import atomic_write_text

        text = tables(rows)
        atomic_write_text(Path(out) / "reel_reversal.md", "# Orders across a reel reversal\n\n"
                          f"{provenance.header()}\n\n{text}\n")
        echo(text)
        return f"wrote {out}/reel_reversal.md"

    return Study(name="reel-reversal", table="reel_reversal.csv", identity=IDENTITY, jobs=jobs, run_job=run_job,
                 identity_of=ids.__getitem__, frame=to_frame, report=report, describe=describe, key=key,
                 crash_row=crash_row, group=lambda j: j.method, text_columns=TEXT_COLUMNS,
                 workers=workers if workers is not None else default_workers(len(methods)),
                 setup=(functools.partial(warm_reference, scene_name, elements, t_end, cache_dir),),
                 header="reel_reversal.md")
