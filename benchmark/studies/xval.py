"""Cross-validation against MoorDyn and MuJoCo (``python -m benchmark xval``).

The same fixed-length string is built in three codes from one scene:

* **ours**: `models` with ``string.mass_model`` "consistent" (the paper's) and "lumped"
  (models/README.md). The study integrates both with our LGVI at the outside codes' step /
  `OURS_REFINE` (`run_ours_lgvi`: the cost table, the self-convergence and the Richardson
  limits), and the lumped one also with the benchmark's reference solver (`run_ours`:
  `benchmark.core.reference`, DOP853 at rtol 1e-12 / atol 1e-14 on the closed-form right-hand side):
  that solution, whose time error is far below `MODEL_TOLERANCE`, is the one compared with the
  outside codes at equal N (the LGVI's time error, up to 1.4e-6 m at N = 5 over 5 s, would hide
  the model difference);
* **MoorDyn** (point mass only, in vacuum and in water: `benchmark.studies.xval_moordyn`);
* **MuJoCo** (point mass and rigid body, in vacuum: `benchmark.studies.xval_mujoco`).

Both outside codes are lumped-mass discretisations, so at equal N they and our lumped model are
the *same* discrete system: the study compares our lumped model's DOP853 solution with each
outside code at its step dt (`CFL`), and reruns each outside code at dt/2 (``<code>_half_dt``) so
that the tables show the outside codes' own time error too; both must be below
`MODEL_TOLERANCE` for the equal-N difference to measure the model and not the time steppers
(tests/test_xval.py checks the difference to 1e-8 m in vacuum and 1e-9 m in water); our consistent
model converges to the same continuum limit.

As a study on the one runner (`study`, `benchmark.core.study.run`), one job is one (case, N):
every code of the case at that N (`run_job`, in this process: the per-step costs are compared).
Its table is ``cost.csv``, one row per (case, N, code), saved after every job with the tips beside
it (``tips.npz``); a rerun keeps the jobs made from the same key, and the runs of other N already
in the output when they can join this one (`benchmark.studies.xval_output`). The other tables,
plots and README are derived from the whole table (`benchmark.studies.xval_report`).

Not translated (refused with `Untranslatable`, naming it: `benchmark.studies.xval_translate`): a reel
or its effects, `slack` for MuJoCo (its tendon springs are two-sided; MoorDyn's lines are
tension-only, so MoorDyn takes `slack` as it is, and agrees with the two-sided law only while every
element stays stretched, which `run` checks; tests/test_slack_moordyn.py compares a string that goes
slack), `axial_damping`, an initial compression (`initial.stretch` < 1); MoorDyn is not given the
rigid body (its Body model was not validated here: the body runs are against MuJoCo only).
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from reelbench.benchmark.core import engine
from reelbench.benchmark.core.reference import CACHE_DIR, get_reference
from reelbench.benchmark.runs.metrics import body_positions
# the translation's names, which the study's callers use from here too
from reelbench.benchmark.studies.xval_moordyn import SUBMERGED, moordyn_input, run_moordyn  # noqa: F401
from reelbench.benchmark.studies.xval_mujoco import mujoco_xml, run_mujoco  # noqa: F401
from reelbench.benchmark.studies.xval_translate import (CFL, DT_MAX, FLUID_EFFECTS, WATER, CodeRun,  # noqa: F401
                                                        Untranslatable, check_translatable, steps_per_interval,
                                                        time_step)
from reelbench.models.scene import Scene

#: Default N sequence and horizon of `python -m benchmark xval`.
DEFAULT_ELEMENTS = (5, 10, 20, 40, 80)  # N = 160 (`--elements 5,10,20,40,80,160`) costs 4x the rest
DEFAULT_T_END = 5.0
#: What "the same discrete model" must show at equal N: the largest tip distance between our
#: lumped model (DOP853) and an outside code, and each outside code's own time error (the change
#: when its dt is halved), over the compared horizon.
MODEL_TOLERANCE = 1e-9


# ------------------------------------------------------------------------------------------
# Ours
# ------------------------------------------------------------------------------------------
def _min_strain(model, xs) -> float:
    """The smallest element strain over the saved states: MoorDyn's lines are tension-only, so
    it agrees with ours only while every element stays stretched."""
    return float((np.array([np.asarray(model.tensions(xi)).min() for xi in xs]) / model.EA).min())


def run_ours(scene: Scene, times, cache_dir: str | Path = CACHE_DIR) -> CodeRun:
    """Tip positions of our model (the scene's own mass model) at ``times`` (evenly spaced from
    0): the benchmark's reference solution (`benchmark.core.reference.get_reference`, cached in
    ``cache_dir``). Its cost is per right-hand side (DOP853 takes 12 per step)."""
    from reelbench.models import build_model

    times = np.asarray(times, float)
    ref = get_reference(scene, float(times[-1]), float(times[1] - times[0]), Path(cache_dir))
    if len(ref.t) != len(times) or not np.allclose(ref.t, times, atol=1e-9):
        raise RuntimeError(f"reference saved times {ref.t[:3]}… do not match the output times")
    model = build_model(scene)
    nfev = int(ref.stats["rhs_evals"])
    return CodeRun(f"ours_{scene.string.mass_model}", model.N, None, body_positions(model, ref), nfev,
                   float(ref.stats["wall_time"]), {"rhs_evals": nfev, "min_strain": _min_strain(model, ref.x)})


def run_ours_lgvi(scene: Scene, times, dt: float) -> CodeRun:
    """Tip positions of our model by our LGVI (fixed step ``dt``, compile time excluded).

    The study's own runs: second order, so at the outside codes' CFL-limited dt divided by
    `OURS_REFINE` its time error is far below the spatial differences (the lumped-vs-MoorDyn
    and lumped-vs-MuJoCo rows of the tables measure it: same discrete model)."""
    from reelbench.integrators.lgvi import LGVI
    from reelbench.models import build_model

    times = np.asarray(times, float)
    steps_per_interval(times, dt)
    tr = LGVI().solve(scene, t_end=float(times[-1]), dt=dt, save_every=float(times[1] - times[0]))
    if not tr.ok:
        raise RuntimeError(f"lgvi failed on {scene.name} at dt = {dt:g}: {tr.reason}")
    if len(tr.t) != len(times) or not np.allclose(tr.t, times, atol=1e-9):
        raise RuntimeError(f"lgvi saved times {tr.t[:3]}… do not match the output times")
    model = build_model(scene)
    return CodeRun(f"ours_{scene.string.mass_model}", model.N, dt, body_positions(model, tr), int(tr.stats["steps"]),
                   float(tr.stats["wall_time"]), {"min_strain": _min_strain(model, tr.x), "method": "lgvi"})


#: our LGVI runs at the outside codes' dt / OURS_REFINE (within 1 % of its step before `CFL` was
#: halved, dt/4 at 0.05: its rows of the cost table and the convergence study barely change)
OURS_REFINE = 2
#: the code name of an outside code's rerun at dt/2 (its time-error check)
HALF_DT = "_half_dt"
#: the code name of our lumped model's reference (DOP853) solution: the equal-N comparison's
REFERENCE_CODE = "ours_lumped_dop853"


# ------------------------------------------------------------------------------------------
# Cases
# ------------------------------------------------------------------------------------------
#: Cases and the outside codes that get them: the scene without its rigid body (point mass
#: m_b at the tip), when the scene has one the scene itself, and the point mass in water
#: (buoyancy and Morison drag, `WATER`; MoorDyn only).
CASES = {"point_mass": ("moordyn", "mujoco"), "rigid_body": ("mujoco",), "in_water": ("moordyn",)}


def case_scene(scene: Scene, case: str) -> Scene:
    """The scene of one case: ``point_mass`` drops `rigid_body` and Ω0, ``rigid_body`` keeps it (both in
    vacuum: without the fluid effects), ``in_water`` is ``point_mass`` with buoyancy and drag (`WATER`
    unless the scene has its own)."""
    if case == "point_mass":
        return scene.with_(effects=[e for e in scene.effects if e not in ("rigid_body",) + FLUID_EFFECTS],
                           angular_velocity=[0.0, 0.0, 0.0])
    if case == "in_water":
        dry = [e for e in scene.effects if e != "rigid_body"]
        if all(scene.has(e) for e in FLUID_EFFECTS):
            return scene.with_(effects=dry, angular_velocity=[0.0, 0.0, 0.0])
        return scene.with_(effects=[e for e in dry if e not in FLUID_EFFECTS] + list(FLUID_EFFECTS),
                           angular_velocity=[0.0, 0.0, 0.0], **WATER)
    if case == "rigid_body":
        if not scene.has("rigid_body"):
            raise ValueError(f"case 'rigid_body' needs effect 'rigid_body' in scene {scene.name!r}")
        return scene.with_(effects=[e for e in scene.effects if e not in FLUID_EFFECTS])
    raise ValueError(f"unknown case {case!r}: allowed {', '.join(CASES)}")


def cases_of(scene: Scene) -> tuple[str, ...]:
    return ("point_mass", "rigid_body", "in_water") if scene.has("rigid_body") else ("point_mass", "in_water")


def check_scene(scene: Scene) -> None:
    """Refuse (`Untranslatable`) a scene that some code of some case cannot represent."""
    check_translatable(scene, "mujoco")
    for case in cases_of(scene):
        for code in CASES[case]:
            check_translatable(case_scene(scene, case), code)


OUTPUT_INTERVAL = 0.05  # s between compared samples


def _dt_for(scene: Scene, interval: float) -> float:
    """`time_step` rounded down so that it divides the output interval."""
    return interval / math.ceil(interval / time_step(scene) - 1e-9)



def output_times(t_end: float) -> np.ndarray:
    """The compared times: 0, `OUTPUT_INTERVAL`, … up to ``t_end``."""
    return np.linspace(0.0, t_end, round(t_end / OUTPUT_INTERVAL) + 1)


# ------------------------------------------------------------------------------------------
# The study: one job per (case, N), one table row per (case, N, code)
# ------------------------------------------------------------------------------------------
@dataclass
class Runs:
    """The raw runs of the study: the compared times, and {(case, N): {code: CodeRun}}."""

    times: np.ndarray
    runs: dict

    def cases(self) -> list[str]:
        return sorted({c for c, _ in self.runs}, key=list(CASES).index)

    def elements(self, case: str) -> list[int]:
        return sorted(N for c, N in self.runs if c == case)


class Job(NamedTuple):
    """One (case, N) of the study: every code of the case on the scene at N elements."""

    scene: Scene  # the case's scene at the study's horizon
    case: str
    N: int
    times: np.ndarray


def run_job(job: Job) -> dict:
    """The row of one (case, N): the LGVI runs of our two mass models, our lumped model's reference
    (DOP853) solution (`REFERENCE_CODE`, computed in a temporary cache: never the shared one), and
    each of the case's outside codes at dt and at dt/2 (``<code>_half_dt``)."""
    sc = job.scene.with_(elements=job.N, mass_model="lumped")
    dt = _dt_for(sc, OUTPUT_INTERVAL)
    runs = {"ours_consistent": run_ours_lgvi(job.scene.with_(elements=job.N, mass_model="consistent"), job.times,
                                             dt / OURS_REFINE),
            "ours_lumped": run_ours_lgvi(sc, job.times, dt / OURS_REFINE)}
    with tempfile.TemporaryDirectory(prefix="xval-reference-") as tmp:
        ref = run_ours(sc, job.times, tmp)
    runs[REFERENCE_CODE] = CodeRun(REFERENCE_CODE, ref.N, None, ref.tip, ref.steps, ref.wall_s, ref.extra)
    for code in CASES[job.case]:
        run = run_moordyn if code == "moordyn" else run_mujoco
        runs[code] = run(sc, job.times, dt)
        runs[code + HALF_DT] = run(sc, job.times, dt / 2)
        runs[code + HALF_DT].code = code + HALF_DT
    return {"case": job.case, "N": job.N, "dt": dt, "runs": runs}


def describe(row: dict) -> str:
    """A finished job in the progress log."""
    return (f"xval {row['case']} N={row['N']}: dt={row['dt']:.3g} s; "
            + ", ".join(f"{k} {r.wall_s:.2f} s" for k, r in row["runs"].items()))


def jobs_for(scene: Scene, elements, t_end: float, cases=None) -> list[Job]:
    """Every (case, N) of the study; an untranslatable scene is refused here (`Untranslatable`)."""
    check_scene(scene)
    times = output_times(t_end)
    return [Job(case_scene(scene, case).with_(t_end=t_end), case, int(N), times)
            for case in cases or cases_of(scene) for N in elements]


def compute(scene: Scene, elements=DEFAULT_ELEMENTS, t_end: float = DEFAULT_T_END, cases=None,
            log=engine.log_stderr) -> Runs:
    """Run every code of every case at every N in this process and return the runs, writing
    nothing (the command's study is `study`)."""
    jobs = jobs_for(scene, elements, t_end, cases)
    rows = engine.run_jobs(run_job, jobs, workers=0, describe=describe, log=log)
    return Runs(output_times(t_end), {(r["case"], r["N"]): r["runs"] for r in rows})


#: The study's table (``cost.csv``): one row per (case, N, code), its cost and smallest strain.
TABLE = "cost.csv"
COST_COLUMNS = ["case", "N", "code", "dt_s", "steps", "wall_s", "us_per_step", "us_per_rhs", "min_strain"]
#: A job's rows, which a rerun of the job replaces as a whole.
IDENTITY = ("case", "N")
#: The study's own source (besides the code version of every study): a change recomputes its jobs.
SOURCES = tuple(f"benchmark/studies/{m}.py" for m in ("xval", "xval_translate", "xval_moordyn", "xval_mujoco"))


def cost_row(case: str, N: int, code: str, run: CodeRun) -> dict:
    """The row of ``cost.csv`` of one run: its step, steps, wall time, time per step (per
    right-hand side for a reference run) and smallest element strain."""
    nan = float("nan")
    rhs = run.extra.get("us_per_rhs", (1e6 * run.wall_s / run.extra["rhs_evals"]) if "rhs_evals" in run.extra else nan)
    return dict(case=case, N=N, code=code, dt_s=run.dt, steps=run.steps, wall_s=run.wall_s,
                us_per_step=run.us_per_step if run.dt is not None else nan, us_per_rhs=rhs,
                min_strain=run.extra.get("min_strain", nan))


def expand(row: dict) -> list[dict]:
    """The table rows of a job's row (`Study.expand`): one per code, each with its tips (``tip``:
    not a column, kept beside the table in tips.npz)."""
    return [{**cost_row(row["case"], row["N"], code, run), "tip": run.tip} for code, run in row["runs"].items()]


def run_of(row: dict) -> CodeRun:
    """A table row (with its ``tip``) as the run it records; the costs as the row states them."""
    dt = float(row["dt_s"]) if row["dt_s"] is not None and np.isfinite(row["dt_s"]) else None
    extra = {k: float(row[k]) for k in ("us_per_step", "us_per_rhs", "min_strain")
             if row.get(k) is not None and np.isfinite(row[k])}
    return CodeRun(str(row["code"]), int(row["N"]), dt, np.asarray(row["tip"]), int(row["steps"]),
                   float(row["wall_s"]), extra)


def runs_of(rows: list[dict], t_end: float) -> Runs:
    """The runs of the study's table rows (each with its ``tip``)."""
    runs: dict = {}
    for r in rows:
        runs.setdefault((str(r["case"]), int(r["N"])), {})[str(r["code"])] = run_of(r)
    return Runs(output_times(t_end), runs)


def to_frame(rows: list[dict]):
    """The table, its rows in the order of `CASES` and N (a job's codes in the order it ran them)."""
    from reelbench.benchmark.core import store
    from reelbench.benchmark.core.study import KEY_COLUMN

    order = list(CASES)
    rows = sorted(rows, key=lambda r: (order.index(r["case"]) if r["case"] in order else len(order), int(r["N"])))
    return store.frame(rows, COST_COLUMNS + [KEY_COLUMN], extra=False)


def key(job: Job) -> str:
    """What determines a job's rows: its case's scene at N (both mass models), the horizon, the
    steps and the outside codes' versions, and the code."""
    from importlib.metadata import version

    from reelbench.benchmark.core.study import job_key

    settings = {"case": job.case, "N": job.N, "t_end": float(job.times[-1]), "interval": OUTPUT_INTERVAL,
                "cfl": CFL, "dt_max": DT_MAX, "refine": OURS_REFINE,
                "scenes": [job.scene.with_(elements=job.N, mass_model=m).key() for m in ("lumped", "consistent")],
                "codes": {c: version(c) for c in ("moordyn", "mujoco")}}
    return job_key(settings, *SOURCES)


def study(scene_name: str, elements, t_end: float, out: Path, *, cases=None,
          log: Callable[[str], None] = engine.log_stderr):
    """The cross-validation as a study of `benchmark.core.study.run` into ``out``: cost.csv and
    tips.npz after every job, the other tables, plots, inputs and README from the whole table
    (`benchmark.studies.xval_output.Output`, which keeps or refuses the runs of an earlier study
    there). An untranslatable scene is refused here, before any work."""
    from reelbench.benchmark.core.study import Study
    from reelbench.benchmark.studies.xval_output import Output
    from reelbench.models import load_scene

    scene = load_scene(scene_name)
    jobs = jobs_for(scene, elements, t_end, cases)
    output = Output(Path(out), scene, t_end, {(j.case, j.N) for j in jobs}, log)
    return Study(name="xval", table=TABLE, identity=IDENTITY, jobs=jobs, run_job=run_job,
                 identity_of=lambda j: (j.case, j.N), frame=to_frame, report=output.report, describe=describe,
                 key=key, expand=expand, read_earlier=output.read_earlier, reusable=lambda row: True,
                 beside=output.save_tips, text_columns=("case", "code"), unit="(case, N) jobs")
