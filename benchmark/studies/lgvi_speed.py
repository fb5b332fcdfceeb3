"""Speed: time per step of every fixed-step method, and per-call cost of each right-hand side, vs N.

    python -m benchmark speed                      # short: N = 10 on fixed_length (~1.5 CPU-minutes)
    python -m benchmark speed --elements 10,40,160,640 --scenes fixed_length,deployment   # the full run

Into ``--out`` (default results/lgvi_speed.md), a study on the one runner (`study`,
`benchmark.core.study.run`): the rows table beside it (``lgvi_speed.csv``) takes each measurement
as it finishes in place of the earlier one, keeping the others, and the Markdown file is written
from the whole table (also when stopped) and printed. A rerun measures only what the table lacks
from the same code, settings and machine (`key`); ``--fresh`` measures everything again.

Two tables:

1. Every registered method with `Capability.FIXED_STEP` (read from the registry, so a method
   another module registers appears here without a code change), at a constant step: compile
   time, time per step (median over repeats of the whole ``solve()`` after compilation,
   divided by the steps: the run time the benchmark reports), Newton iterations per step where
   the method reports them. The step is each scene's stable step at N = 10, times 10/N (the
   elastic frequency grows like N); a method whose run does not finish at it is retried at
   half the step (up to `MAX_HALVINGS` times) and the table says which step ran.
2. Each right-hand side of the ODE baselines (`integrators.rhs`: closed form, autodiff), per
   call from numpy through its jitted function (how scipy calls it): median µs per call.
   The autodiff one is O(N³) (dense mass matrix and solve); above ``--autodiff-max-n`` it is
   skipped.

Per method and scene: the ratio of time per step at the largest N ≤ 160 to N = 10 (linear in
N would be 16) and the log-log slope over all N. Every measurement is one engine job, run in
this process one after another (they are timings: they never share the cores). Pin to one
core for the one-core figure: ``taskset -c 0 python -m benchmark speed``.

The first solve of each step measurement (compile and warm-up) is bounded by the budget
(--max-steps, --time-limit: `benchmark.studies.budget`). A first solve past it ends the
measurement with its status (max_steps / time_limit: not timed, not retried at a smaller step);
the timed solves are the same work without a budget.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from reelbench.benchmark.core.report import Provenance
from reelbench.benchmark.studies import budget as _budget

#: step at N = 10 per scene, scaled by 10/N: the LGVI is explicit in the elastic forces, so it
#: needs h ω_max < 2 with ω_max ∝ N (fixed_length N = 10: h < ~9 ms; deployment: h < ~2.7 ms).
DEFAULT_DT10 = {"fixed_length": 0.005, "deployment": 0.002, "retrieval": 0.004}
#: a method that does not finish at the scene's step is retried at half of it, this many times at most
MAX_HALVINGS = 3
#: the N whose time per step the ratio compares with N = 10's (the largest measured N up to it)
RATIO_MAX_N = 160


def fixed_step_methods() -> list[str]:
    """Every default method (`benchmark.runs.sweep.default_names`) that takes a constant step."""
    from reelbench.benchmark.runs.sweep import default_names
    from reelbench.integrators import Capability, get_integrator

    return [n for n in default_names() if get_integrator(n).has(Capability.FIXED_STEP)]


def check_methods(methods) -> None:
    """ValueError naming a method that is not a fixed-step one."""
    from reelbench.integrators import Capability, get_integrator

    for m in methods:
        if not get_integrator(m).has(Capability.FIXED_STEP):
            raise ValueError(f"--integrators: {m!r} is not a fixed-step method (allowed: {', '.join(fixed_step_methods())})")


@dataclass(frozen=True)
class SpeedRequest:
    """What `python -m benchmark speed` measures (its options)."""

    # the default run stays short (under a minute on one core); the full run names 160 and 640
    elements: tuple = (10,)
    scenes: tuple = ("fixed_length",)
    methods: tuple | None = None  # None: every fixed-step method
    steps: int = 2000
    repeats: int = 3
    dt: float | None = None  # None: the scene's stable step at N = 10, times 10/N
    rhs: tuple = ("closed_form", "autodiff")
    autodiff_max_n: int = 160
    budget: object = None  # of the first solve of each step measurement (`runner.SolveBudget`); None: the defaults


def measure(scene_name: str, n: int, steps: int, repeats: int, dt: float | None = None, method: str = "lgvi",
            budget=None) -> dict:
    """Time per step of ``method`` at a constant step on ``scene_name`` with N = n; its first
    solve within ``budget`` (None: the defaults)."""
    from reelbench.benchmark.work.flops import run_flops
    from reelbench.integrators import get_integrator  # JAX: only once the options are known good
    from reelbench.integrators.base import BUDGET_STATUSES
    from reelbench.models import build_model, load_scene

    scene = load_scene(scene_name, elements=n)
    h = dt or DEFAULT_DT10.get(scene_name, 0.002) * 10.0 / n
    integ = get_integrator(method)
    for _ in range(MAX_HALVINGS + 1):
        kw = dict(t_end=steps * h, dt=h, save_every=steps * h / 10)
        first = integ.solve(scene, **kw, **_budget.solve_kwargs(budget))  # compiles (and warms up)
        if first.ok or first.status in BUDGET_STATUSES:  # out of budget: a smaller step would cost more
            break
        h /= 2
    times = []
    tr = first
    for _ in range(repeats if first.ok else 0):
        tr = integ.solve(scene, **kw)
        times.append(tr.stats["wall_time"] / max(tr.stats["steps"], 1))
    per = statistics.median(times) if times else float("nan")
    steps_run = max(tr.stats["steps"], 1)
    newton = tr.stats.get("newton_iterations")
    evals = tr.stats.get("rhs_evals")
    flops, note = run_flops(method, build_model(scene), tr.stats, tr.stats.get("rhs"))
    return {"method": method, "scene": scene_name, "N": n, "dt": h, "compile_s": first.stats.get("compile_time", np.nan),
            "us_per_step": per * 1e6, "steps_per_s": 1.0 / per if per > 0 else np.nan,
            "us_per_eval": per * 1e6 * steps_run / evals if evals else np.nan,
            "flops_per_step": flops / steps_run, "flops_note": note,
            "newton_per_step": newton / steps_run if newton is not None else np.nan,
            "status": tr.status}


def measure_rhs(scene_name: str, n: int, rhs: str, calls: int = 200, budget_s: float = 2.0) -> dict:
    """Median µs per call of the jitted right-hand side ``rhs`` from numpy (as scipy calls it)."""
    from reelbench.integrators.rhs import rhs_jit
    from reelbench.models import build_model, load_scene

    model = build_model(load_scene(scene_name, elements=n))
    y = np.asarray(model.initial_ode_state())
    f = rhs_jit(model, rhs)
    tc = time.perf_counter()
    np.asarray(f(0.0, y))
    compile_s = time.perf_counter() - tc
    times, spent = [], 0.0
    while len(times) < calls and spent < budget_s:
        t0 = time.perf_counter()
        np.asarray(f(0.0, y))
        dt = time.perf_counter() - t0
        times.append(dt)
        spent += dt
    return {"scene": scene_name, "N": n, "rhs": rhs, "compile_s": compile_s, "us_per_call": statistics.median(times) * 1e6,
            "calls": len(times)}


# ------------------------------------------------------------------------------------------
# The jobs
# ------------------------------------------------------------------------------------------
class StepJob(NamedTuple):
    method: str
    scene: str
    N: int
    steps: int
    repeats: int
    dt: float | None
    budget: object = None  # of the first solve (`runner.SolveBudget`); None: the defaults


class RhsJob(NamedTuple):
    scene: str
    N: int
    rhs: str
    skip: str = ""  # why it is not measured ("" = it is)


def jobs_for(request: SpeedRequest) -> list:
    methods = request.methods or fixed_step_methods()
    steps = [StepJob(m, sc, n, request.steps, request.repeats, request.dt, request.budget)
             for m in methods for sc in request.scenes for n in request.elements]
    rhs = [RhsJob(sc, n, r, f"O(N³), N > --autodiff-max-n {request.autodiff_max_n}"
                  if r == "autodiff" and n > request.autodiff_max_n else "")
           for sc in request.scenes for r in request.rhs for n in request.elements]
    return steps + rhs


#: A row of the speed tables: one per kind ("step" or "rhs"), method or right-hand side, scene and N
#: (a step row's rhs and an rhs row's method are "", so that rows read back compare equal).
IDENTITY = ("kind", "method", "rhs", "scene", "N")
TEXT_COLUMNS = ("kind", "method", "rhs", "scene", "skipped", "flops_note", "status")


def run_job(job) -> dict:
    from reelbench.integrators.base import Status

    if isinstance(job, StepJob):
        return {"kind": "step", "rhs": "", **measure(job.scene, job.N, job.steps, job.repeats, job.dt, job.method,
                                                     job.budget)}
    if job.skip:
        return {"kind": "rhs", "method": "", "scene": job.scene, "N": job.N, "rhs": job.rhs, "skipped": job.skip}
    return {"kind": "rhs", "method": "", "skipped": "", **measure_rhs(job.scene, job.N, job.rhs), "status": Status.OK.value}


def identity_of(job) -> tuple:
    """The identity (`IDENTITY`) of the row ``job`` makes."""
    if isinstance(job, StepJob):
        return "step", job.method, "", job.scene, job.N
    return "rhs", "", job.rhs, job.scene, job.N


def key(job) -> str:
    """What determines a measurement: the job's settings (its budget: `budget.key_settings`), the
    code and the machine (its name, architecture and the cores this process may use)."""
    import os
    import platform

    from reelbench.benchmark.core.study import job_key

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    budget = job.budget if isinstance(job, StepJob) else None
    settings = job[:-1] if isinstance(job, StepJob) else job
    return job_key({"job": [type(job).__name__, *settings], "host": platform.node(), "machine": platform.machine(),
                    "cores": cores, **_budget.key_settings(budget)}, "benchmark/studies/lgvi_speed.py",
                   "benchmark/work/flops.py")


def rows_file(out) -> Path:
    """The rows table of the speed file ``out``: beside it, ``.csv``."""
    return Path(out).with_suffix(".csv")


def study(request: SpeedRequest, out, *, echo=print):
    """The speed tables as a study of `benchmark.core.study.run` into ``out``'s directory: one
    measurement after another in this process; the rows table beside ``out`` (`rows_file`), and
    ``out`` (Markdown) written from the whole table and echoed."""
    from reelbench.benchmark.core.study import Study

    out = Path(out)

    def report(directory, rows: list[dict], provenance: Provenance) -> str:
        from reelbench.models.io import atomic_write_text

        text = document(rows, provenance)
        atomic_write_text(out, text)
        echo(text)
        return f"wrote {out}"

    return Study(name="speed", table=rows_file(out).name, identity=IDENTITY, jobs=jobs_for(request), run_job=run_job,
                 identity_of=identity_of, frame=to_frame, report=report, describe=describe, key=key,
                 text_columns=TEXT_COLUMNS, workers=0, header=out.name)


def to_frame(rows: list[dict]):
    """The rows table written beside the Markdown file (`benchmark.core.study_store`)."""
    from reelbench.benchmark.core.store import frame

    return frame(rows, list(IDENTITY))


def describe(r: dict) -> str:
    if r["kind"] == "step":
        return (f"{r['method']} {r['scene']} N={r['N']} dt={r['dt']:.3g}: {r['us_per_step']:.2f} us/step, "
                f"{r['us_per_eval']:.2f} us/eval, {r['flops_per_step']:.3g} flops/step, "
                f"compile {r['compile_s']:.2f} s, {r['newton_per_step']:.2f} newton/step, {r['status']}")
    if r.get("skipped"):
        return f"rhs {r['rhs']} {r['scene']} N={r['N']}: skipped ({r['skipped']})"
    return f"rhs {r['rhs']} {r['scene']} N={r['N']}: compile {r['compile_s']:.2f} s, {r['us_per_call']:.1f} us/call"


# ------------------------------------------------------------------------------------------
# The tables
# ------------------------------------------------------------------------------------------
def _ratio(rows, key):
    by_n = {r["N"]: r[key] for r in rows if np.isfinite(r[key])}
    small = [m for m in by_n if RATIO_MAX_N >= m > 10]
    if 10 not in by_n or not small:
        return np.nan, None
    big = max(small)
    return by_n[big] / by_n[10], big


def _slope(rows, key):
    pts = [(r["N"], r[key]) for r in rows if np.isfinite(r[key]) and r[key] > 0]
    if len(pts) < 2:
        return np.nan
    return float(np.polyfit(np.log([p[0] for p in pts]), np.log([p[1] for p in pts]), 1)[0])


def _num(value, fmt: str, why: str) -> str:
    """A number, or why there is none (never a silent blank)."""
    return format(value, fmt) if np.isfinite(value) else f"— ({why})"


def _step_tables(rows: list[dict]) -> tuple[list[str], list[str]]:
    md = ["| method | scene | N | dt (s) | compile (s) | µs/step | µs/evaluation | flops/step | steps/s "
          "| Newton iterations/step | status |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    md += [f"| {r['method']} | {r['scene']} | {r['N']} | {r['dt']:.3g} | {r['compile_s']:.2f} | {r['us_per_step']:.2f} "
           f"| {_num(r['us_per_eval'], '.2f', 'no RHS evaluations')} | {_num(r['flops_per_step'], '.3g', r['flops_note'])} "
           f"| {r['steps_per_s']:.0f} | {_num(r['newton_per_step'], '.2f', 'no Newton solve')} | {r['status']} |"
           for r in rows]
    summary = [f"| method | scene | µs/step at N = 10 | ratio N={RATIO_MAX_N} / N=10 | log-log slope |",
               "|---|---|---|---|---|"]
    for key in dict.fromkeys((r["method"], r["scene"]) for r in rows):
        group = [r for r in rows if (r["method"], r["scene"]) == key]
        ratio, big = _ratio(group, "us_per_step")
        at10 = next((r["us_per_step"] for r in group if r["N"] == 10), np.nan)
        ratio_text = (f"{ratio:.1f} (N = {big})" if big is not None
                      else f"— (needs N = 10 and an N in 11–{RATIO_MAX_N}: give --elements)")
        slope = _slope(group, "us_per_step")
        summary.append(f"| {key[0]} | {key[1]} | {_num(at10, '.2f', 'N = 10 not measured')} | {ratio_text} "
                       f"| {_num(slope, '.2f', 'needs two N')} |")
    return md, summary


def _rhs_table(rows: list[dict]) -> list[str]:
    md = ["| scene | N | right-hand side | compile (s) | µs/call | calls |", "|---|---|---|---|---|---|"]
    for r in rows:
        if isinstance(r.get("skipped"), str) and r["skipped"]:
            md.append(f"| {r['scene']} | {r['N']} | {r['rhs']} | | skipped ({r['skipped']}) | |")
        else:
            md.append(f"| {r['scene']} | {r['N']} | {r['rhs']} | {r['compile_s']:.2f} | {r['us_per_call']:.1f} "
                      f"| {int(r['calls'])} |")
    return md


def _grouped(rows: list[dict], by: tuple) -> list[dict]:
    """``rows`` with those of one group (``by``, in order of first appearance) together, by N."""
    first = {}
    for r in rows:
        first.setdefault(tuple(r[c] for c in by), len(first))
    return sorted(rows, key=lambda r: (first[tuple(r[c] for c in by)], r["N"]))


def document(rows: list[dict], provenance: Provenance) -> str:
    """The speed tables as one Markdown file, under the report header (rows of a merged table
    come in any order: each method's and right-hand side's are put together, by N)."""
    md, summary = _step_tables(_grouped([r for r in rows if r["kind"] == "step"], ("method", "scene")))
    rhs = _rhs_table(_grouped([r for r in rows if r["kind"] == "rhs"], ("scene", "rhs")))
    return (f"# Speed of the fixed-step methods and of the right-hand sides\n\n{provenance.header()}\n\n"
            "Time per step: the whole `solve()` after compilation (output conversion included), divided by the "
            "steps, median of repeats; compile time apart. µs/evaluation: the same time per right-hand-side "
            "evaluation (methods that count them); flops/step: XLA's cost model of the compiled step or right-hand "
            "side times the run's counts (`benchmark.work.flops`).\n\n"
            + "\n".join(md) + "\n\n## Scaling with N\n\n" + "\n".join(summary)
            + "\n\n## Right-hand side per call (jitted, called from numpy)\n\n" + "\n".join(rhs) + "\n")
