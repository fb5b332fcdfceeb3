"""LGVI speed: compile time and time per step vs the number of elements N.

    python -m benchmark.lgvi_speed --elements 10,40,160,640 --scenes fixed_length,deployment --steps 2000

Prints, per scene and N: compile time, time per step (median of repeats after a warm-up run,
compilation excluded), steps/s, Newton iterations per step, and per scene the log-log slope
of time/step vs N (least squares). Run it pinned to one core for the one-core figure, e.g.
``taskset -c 0 python -m benchmark.lgvi_speed``.
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np

from integrators.lgvi import LGVI
from models import load_scene

#: step at N = 10 per scene, scaled by 10/N: the LGVI is explicit in the elastic forces, so it
#: needs h ω_max < 2 with ω_max ∝ N (fixed_length N = 10: h < ~9 ms; deployment: h < ~2.7 ms).
DEFAULT_DT10 = {"fixed_length": 0.005, "deployment": 0.002, "retrieval": 0.004}


def measure(scene_name: str, n: int, steps: int, repeats: int, dt: float | None = None) -> dict:
    scene = load_scene(scene_name, elements=n)
    h = dt or DEFAULT_DT10.get(scene_name, 0.002) * 10.0 / n
    integ = LGVI()
    kw = dict(t_end=steps * h, dt=h, save_every=steps * h / 10)
    first = integ.solve(scene, **kw)  # compiles (and warms up)
    times = []
    for _ in range(repeats):
        tr = integ.solve(scene, **kw)
        times.append(tr.stats["wall_time"] / max(tr.stats["steps"], 1))
    per = statistics.median(times)
    return {"scene": scene_name, "N": n, "compile_s": first.stats["compile_time"], "us_per_step": per * 1e6,
            "steps_per_s": 1.0 / per, "newton_per_step": tr.stats["newton_iterations"] / max(tr.stats["steps"], 1),
            "status": tr.status}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="lgvi_speed", description=__doc__.splitlines()[0])
    ap.add_argument("--elements", default="10,40,160,640", help="comma-separated N values")
    ap.add_argument("--scenes", default="fixed_length,deployment", help="comma-separated scene names")
    ap.add_argument("--steps", type=int, default=2000, help="steps per timed run")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats (median)")
    ap.add_argument("--dt", type=float, default=None, help="step size (default: per-scene stable step at N = 10, times 10/N)")
    args = ap.parse_args(argv)
    ns = [int(v) for v in args.elements.split(",") if v.strip()]
    scenes = [v.strip() for v in args.scenes.split(",") if v.strip()]
    print(f"{'scene':<14}{'N':>6}{'compile s':>11}{'us/step':>10}{'steps/s':>11}{'newton/step':>13}  status")
    for sc in scenes:
        rows = [measure(sc, n, args.steps, args.repeats, args.dt) for n in ns]
        for r in rows:
            print(f"{r['scene']:<14}{r['N']:>6}{r['compile_s']:>11.2f}{r['us_per_step']:>10.2f}"
                  f"{r['steps_per_s']:>11.0f}{r['newton_per_step']:>13.2f}  {r['status']}")
        if len(rows) >= 2:
            slope = np.polyfit(np.log([r["N"] for r in rows]), np.log([r["us_per_step"] for r in rows]), 1)[0]
            print(f"{sc:<14} log-log slope of time/step vs N: {slope:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
