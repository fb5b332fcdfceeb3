"""The long-horizon energy study: energy error vs time of the methods that declare settings for
it (`benchmark.sweep.horizon_methods`), at two sizes of the string (`ELEMENTS`) and two
settings each (the declared one and one `FINER`: half the step, or a tolerance 100x tighter),
one engine job per run. Its table is energy_horizon.csv (one history per run; a rerun replaces
its own runs' histories and keeps the others), classified by `benchmark.properties.classify`.

It runs on the fixed-length scenes it is given (`run`: those of the run; `energy`: its
--scenes, default `DEFAULT_SCENE`): a scene with a reel ends when the reel reaches its limit,
too soon for a long horizon, so `run` leaves it out and says so.
"""

from __future__ import annotations

from typing import NamedTuple

from benchmark.options import SOLVE_MAX_STEPS
from benchmark.sweep import MethodSettings

DEFAULT_SCENE = "fixed_length"
SAVE_EVERY = 0.1
#: The sizes of the string: the paper's N = 10 and a coarse N = 4 (whether what is seen depends on N).
ELEMENTS = (4, 10)
#: The second setting of a fixed-step method: its step / FINER (an adaptive one: its tolerances / TIGHTER).
FINER, TIGHTER = 2.0, 100.0
#: The step budget of each run: every solve's (`benchmark.options.SOLVE_MAX_STEPS`), not a
#: library's default (diffrax's 100,000 stopped Tsit5 at rtol 1e-8 short of 100 s at N = 10).
MAX_STEPS = SOLVE_MAX_STEPS
#: Identity of one run in energy_horizon.csv (a rerun replaces the rows of the same run).
RUN_KEY = ("scene", "elements", "integrator", "setting")


def finer(method: MethodSettings) -> MethodSettings:
    s = dict(method.settings)
    if "dt" in s:
        s["dt"] = s["dt"] / FINER
    else:
        s = {k: v / TIGHTER for k, v in s.items()}
    return MethodSettings(method.name, s)


def methods(selected=None) -> list[MethodSettings]:
    """The study's methods (`benchmark.sweep.horizon_methods`) among ``selected`` (None: all);
    ValueError for a selected name that is unknown (the registry's message)."""
    from benchmark.sweep import horizon_methods
    from integrators import get_integrator

    for name in selected or ():
        get_integrator(name)
    return [m for m in horizon_methods() if selected is None or m.name in selected]


def runs(selected=None, elements=ELEMENTS) -> list[tuple[int, MethodSettings]]:
    """(N, settings) of every run of the study, declared setting first."""
    return [(n, s) for m in methods(selected) for n in elements for s in (m, finer(m))]


def setting_of(method: MethodSettings) -> str:
    return ", ".join(f"{k}={v:g}" for k, v in method.settings.items())


def label(scene: str, elements: int, method: MethodSettings) -> str:
    """The run's name in tables and legends: "lgvi dt=0.005 N=10" (the scene is its own column)."""
    return f"{method.label} N={elements}"


class Job(NamedTuple):
    scene: str
    elements: int
    method: MethodSettings
    t_end: float
    overrides: tuple  # ((key, value), ...) of the scene


def run_job(job: Job) -> dict:
    """One run's row: its label (with the status when the run stopped early) and its energy
    history (`benchmark.metrics.energy_history`) with the least element tension (N; < 0:
    compression) at each saved time."""
    import time

    from benchmark.metrics import energy_history
    from integrators import get_integrator
    from models import load_scene

    started = time.perf_counter()
    scene = load_scene(job.scene, **dict(job.overrides), elements=job.elements)
    traj = get_integrator(job.method.name).solve(scene, t_end=job.t_end, save_every=SAVE_EVERY, max_steps=MAX_STEPS,
                                                 **job.method.settings)
    from models.diagnostics import evaluate

    name = label(job.scene, job.elements, job.method) + ("" if traj.ok else f" [{traj.status}]")
    history = energy_history(scene, traj).assign(tension_min=evaluate(scene, traj)["tension_min"].to_numpy())
    return {"label": name, "status": traj.status, "history": history,
            "task_time": time.perf_counter() - started}


def crash_row(job: Job, exc: BaseException) -> dict:
    from benchmark.engine import crash_reason

    return {"label": f"{label(job.scene, job.elements, job.method)} [crashed]", "status": "crashed",
            "reason": crash_reason(exc), "history": None}


def describe(row: dict) -> str:
    return f"horizon {row['label']}: {row['status']}"
