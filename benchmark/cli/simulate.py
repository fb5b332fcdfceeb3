"""`python -m benchmark simulate` and `python -m benchmark figures`: one run of one method on one
scene saved as a trajectory (.npz) and its diagnostics (.csv), and the paper's panels drawn from
a saved trajectory. A first Ctrl-C / SIGTERM ends the running solve where it is and saves it
(`_finish_on_stop`); a second stops at once.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable

from benchmark.core import engine
from benchmark.core.engine import log_stderr


@contextlib.contextmanager
def _finish_on_stop(log: Callable[[str], None]):
    """A first Ctrl-C / SIGTERM ends the running solve at its next clock check, as its time budget
    would (`integrators.lifecycle.request_stop`): it returns what it has, to be saved; a second
    stops at once (KeyboardInterrupt). Yields the list that receives the first signal's name."""
    import signal
    import threading

    from integrators import lifecycle

    caught: list[str] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return

    def soft(signum, frame):
        name = signal.Signals(signum).name
        if caught:
            raise KeyboardInterrupt(f"signal {name}")
        caught.append(name)
        lifecycle.request_stop()
        log(f"stopping ({'Ctrl-C' if name == 'SIGINT' else name}): the run ends at its next check and what it "
            "has is saved; stop again to quit at once, without saving")

    old = {sig: signal.signal(sig, soft) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield caught
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        lifecycle.request_stop(False)


def simulate(scene, integrator: str, settings: dict, out: Path, *, estimate: float | None = None,
             log: Callable[[str], None] = log_stderr) -> int:
    """One run: the trajectory (.npz) and its diagnostics (.csv beside it); exit status 1 when
    the run did not finish (its budget ran out: ``max_steps`` / ``time_limit`` in ``settings``),
    130 / 143 when stopped by Ctrl-C / SIGTERM: a first stop ends the run where it is and saves
    it. ``estimate``: its expected seconds (a progress line every 30 s)."""
    import json

    import numpy as np

    from integrators import get_integrator
    from models.diagnostics import evaluate
    from models.io import atomic_write_text

    integ = get_integrator(integrator)
    try:
        with _finish_on_stop(log) as caught, engine.Heartbeat(f"{scene.name} / {integ.name}", estimate, log=log):
            traj = integ.solve(scene, t_end=scene.t_end, **settings)
    except KeyboardInterrupt as exc:
        return engine.stopped(exc, "nothing saved (stopped twice: the run did not reach a point to save)", log)
    stop = KeyboardInterrupt(f"signal {caught[0]}") if caught else None
    if stop is not None:
        reached = float(traj.t[-1]) if len(traj.t) else 0.0
        traj.reason = f"stopped by {engine.stop_cause(stop)} at t = {reached:.6g} s (t_end = {scene.t_end:g} s)"
    traj.scene = scene.to_dict()  # `figures` draws it without the scene file
    try:
        traj.save(out)
        atomic_write_text(out.with_suffix(".csv"), evaluate(scene, traj).to_csv(index=False))
    except OSError as exc:
        log(f"error: {exc}; the run ended ({traj.status}) but is not saved: free space and run it again")
        return 1
    log(f"{scene.name} / {integ.name}: status {traj.status} {traj.reason}; {len(traj.t)} saved points; "
        f"stats {json.dumps({k: v for k, v in traj.stats.items() if np.isscalar(v)}, default=str)}")
    if stop is not None:
        return engine.stopped(stop, f"the run up to t = {traj.t[-1] if len(traj.t) else 0:.6g} s is saved in {out} "
                                    f"and {out.with_suffix('.csv')}", log)
    log(f"wrote {out} and {out.with_suffix('.csv')}")
    return 0 if traj.ok else 1


def draw_figures(scene, traj, out: Path, log: Callable[[str], None] = log_stderr) -> int:
    """The paper's panels (a)-(d) of a saved trajectory."""
    from benchmark.figures import plots
    from models.diagnostics import evaluate

    plots.paper_panels(scene, traj, evaluate(scene, traj), out)
    log(f"wrote {out}")
    return 0

