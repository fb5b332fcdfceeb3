"""Orders of the fixed-step methods across a reel reversal (s_p-dot changes sign).

    python -m benchmark reel-reversal [--elements 5] [--t-end 0.96] [--integrators lgvi,lgvi_sym,...]

Runs the hard scene ``reel_reversal`` (the Carnot force's ṡ|ṡ| is only C¹ where ṡ_p = 0) with
each method at halving step sizes and writes a markdown table of the errors against the
benchmark's reference solution (`benchmark.core.reference`: DOP853 at rtol 1e-12, atol 1e-14):
maximum over the compared times (every `COMPARE_EVERY` s) of the body position
|q_{N+1} − q_ref|, of |s_p − s_ref| and of |(E − W) − E0|, with the observed orders. Also says
when ṡ_p changes sign in the reference. Every (method, step) run is one engine job.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

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
    from benchmark.core.reference import get_reference

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
    from models.diagnostics import evaluate

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


def run_job(job: Job) -> dict:
    """One method at one step: its status and its errors against the (cached) reference."""
    from integrators import get_integrator
    from models import load_scene
    from models.diagnostics import evaluate

    scene = load_scene(job.scene_name, elements=job.elements)
    ref = reference(scene, job.t_end, job.cache_dir).traj
    tr = get_integrator(job.method).solve(scene, t_end=job.t_end, dt=job.h, save_every=COMPARE_EVERY)
    row = {"method": job.method, "h": job.h, "status": tr.status, "reason": tr.reason}
    if tr.ok:
        row["errors"] = errors(scene, tr, ref, float(evaluate(scene, ref).energy_minus_work.iloc[0]))
    return row


def describe(row: dict) -> str:
    what = ", ".join(f"{k} {v:.2e}" for k, v in row["errors"]._asdict().items()) if "errors" in row else row["status"]
    return f"{row['method']} h = {row['h'] * 1e3:g} ms: {what}"


def table(scene, t_end: float, flips, rows: list[dict]) -> str:
    """The Markdown table of the rows (in method, then step order), orders between successive steps."""
    lines = [f"scene {scene.name}, N = {scene.string.elements}, t_end = {t_end:g} s; s_p-dot changes sign at t = "
             + ", ".join(f"{t:.3f}" for t in flips) + " s",
             "", "| method | h [ms] | body [m] | s_p [m] | E-W [J] | orders (body / s_p / E-W) |", "|---|---|---|---|---|---|"]
    from benchmark.studies.orders import slopes  # the observed order between two steps, as the order ladders compute it

    prev = prev_h = None
    for i, r in enumerate(rows):
        if i == 0 or r["method"] != rows[i - 1]["method"]:
            prev = None
        if "errors" not in r:
            lines.append(f"| {r['method']} | {r['h'] * 1e3:g} | {r['status']}: {r['reason']} | | | |")
            continue
        e = r["errors"]
        steps = (prev_h, r["h"])
        orders = " / ".join(f"{slopes(steps, (a, b))[0]:.2f}" for a, b in zip(prev, e)) if prev else ""
        lines.append(f"| {r['method']} | {r['h'] * 1e3:g} | {e.body:.2e} | {e.s_p:.2e} | {e.energy:.2e} | {orders} |")
        prev, prev_h = e, r["h"]
    return "\n".join(lines)
