"""The long-horizon energy study: energy error vs time of a few methods on the fixed-length
scene (`benchmark.sweep.horizon_methods`), one engine job per method."""

from __future__ import annotations

from typing import NamedTuple

from benchmark.sweep import MethodSettings

SCENE = "fixed_length"
SAVE_EVERY = 0.1


class Job(NamedTuple):
    method: MethodSettings
    t_end: float
    overrides: tuple  # ((key, value), ...) of the scene


def run_job(job: Job) -> dict:
    """One method's row: its label (with the status when the run stopped early) and its energy
    history (`benchmark.metrics.energy_history`)."""
    import time

    from benchmark.metrics import energy_history
    from integrators import get_integrator
    from models import load_scene

    started = time.perf_counter()
    scene = load_scene(SCENE, **dict(job.overrides))
    traj = get_integrator(job.method.name).solve(scene, t_end=job.t_end, save_every=SAVE_EVERY, **job.method.settings)
    label = job.method.label + ("" if traj.ok else f" [{traj.status}]")
    return {"label": label, "status": traj.status, "history": energy_history(scene, traj),
            "task_time": time.perf_counter() - started}


def crash_row(job: Job, exc: BaseException) -> dict:
    from benchmark.engine import crash_reason

    return {"label": f"{job.method.label} [crashed]", "status": "crashed", "reason": crash_reason(exc),
            "history": None}


def describe(row: dict) -> str:
    return f"horizon {row['label']}: {row['status']}"


def table(rows: list[dict]):
    """The histories of ``rows`` in one table (t, energy_error, method), in row order."""
    import pandas as pd

    return pd.concat([r["history"].assign(method=r["label"]) for r in rows if r["history"] is not None])
