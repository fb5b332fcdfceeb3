"""What a sweep runs: scenes × integrators × settings, as a flat list of `Task`s.

Fixed-step methods are swept over one step grid, the same for all (`FULL_DTS`), adaptive ones
over tolerances; a method that is both (diffrax Tsit5) is swept on both axes. Any step size is
allowed: a fixed step saves at its step points nearest the save times and ends at t_end, and
the errors are computed against the reference at the times saved (its dense output,
`benchmark.core.reference`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

from reelbench.benchmark.core.policy import ATOL_FACTOR, ROW_IDENTITY, SAVE_EVERY, Setting  # noqa: F401 (the sweep's names)

PAPER_SCENES = ("fixed_length", "deployment", "retrieval")
#: A string in water (buoyancy and Morison drag): `run --extended` sweeps them after the paper's
FLUID_SCENES = ("deployment_in_water", "towed", "towed_offset")
EXTENDED_SCENES = PAPER_SCENES + FLUID_SCENES
#: The order in which the shipped methods appear in tables and plots (an order only: every
#: registered method runs, plugins after these; which settings a method gets follows from its
#: declared capabilities and the tables below).
PRESENTATION_ORDER = ("lgvi", "lgvi_sym", "lgvi_yoshida4", "lgvi_suzuki4", "rk45", "dop853", "radau", "tsit5",
                      "kvaerno5")
#: The words for a sweep axis in labels: a run with ``dt`` set, or an adaptive one (``rtol``).
SWEEP_WORDS = {"dt": "fixed dt", "rtol": "adaptive"}

# step sizes (s) and relative tolerances (atol = rtol * ATOL_FACTOR, `benchmark.core.policy`)
#: One step grid for every fixed-step method (like with like: a method's curve is never cut
#: shorter or longer than another's by its own list): 20 ms halved 8 times, down to 78.125 µs,
#: from beyond the explicit methods' stability limits (a failed or inaccurate run is a status
#: row) to below 1e-6 m of body position error for the second-order methods on every paper
#: scene (the symmetric LGVI: 6.2e-6 m at 0.3125 ms on deployment, measured). The finest steps
#: cost little: about 80 s more for the default run on 2 cores than the 5 coarsest alone
#: (estimated from the committed runs' µs per step; most of a task's time is its compile).
FULL_DTS = tuple(0.02 / 2 ** k for k in range(9))
FULL_RTOLS = (1e-4, 1e-6, 1e-8, 1e-10)
QUICK_DTS = (0.01, 0.005, 0.0025)
QUICK_RTOLS = (1e-5, 1e-8)
# Implicit adaptive methods cost 10-100x more per step on this non-stiff problem (measured:
# kvaerno5 at rtol 1e-8 took 180 s for 2 s of deployment); their sweep covers the loose
# tolerances at which an implicit method would be chosen, so the default run stays well
# under an hour on 2 cores.
IMPLICIT_FULL_RTOLS = (1e-3, 1e-4, 1e-6)
IMPLICIT_QUICK_RTOLS = (1e-4, 1e-6)
#: The project's methods the default sweep (`run` without ``--integrators``) leaves out, and why.
#: Each runs when ``--integrators`` names it (its rows merge into the same table), and in the
#: extended answer. Every other own method is in the default sweep; a plugin joins when named
#: or with ``--with-plugins``.
EXTENDED_METHODS = {
    "kvaerno5": "an implicit method on a non-stiff problem, 67 s of worker time in the default sweep "
                "(measured); radau represents the implicit ones",
    "crouch_grossman3": "lie_rk4 represents the Lie group methods in the default run",
    "dopri5": "the compiled twin of rk45's tableau (the default run keeps to ~5 min)",
    "dopri8": "the compiled twin of dop853's order (the default run keeps to ~5 min)",
    "rk45_projected": "a variant of rk45 for one side question (does projecting the quaternion help?)",
}
#: An adaptive method's own tolerances in the full default sweep, where the shared ones reach
#: past its useful range; every other method gets the shared ones (`FULL_RTOLS`, or
#: `IMPLICIT_FULL_RTOLS` for an implicit one), and ``--rtols`` and ``--quick`` override these.
#: rk45 and rk45_projected stop at 1e-8: at 1e-10 a fifth-order pair takes 20-36 s of
#: Python-level steps per scene (measured), a third of the default run's time, for an accuracy
#: DOP853 and the compiled twin `dopri5` reach in the same sweep.
SWEEP_RTOLS = {"rk45": (1e-4, 1e-6, 1e-8), "rk45_projected": (1e-4, 1e-6, 1e-8)}
QUICK_T_END = 1.0
#: s of timed solves per run (`benchmark.runs.runner.timing_repeats`): a run is timed
#: clamp(floor(TIMING_BUDGET / first solve), --repeats, MAX_REPEATS) times, or once when its
#: first solve alone exceeds the budget (its noise is small next to its length). The timing
#: noise measured on a shared 2-core machine (30 interleaved solves each, load 2.1-2.9): medians of
#: 10 consecutive solves spread 1.2-1.3x, of 5 1.5-1.85x, single solves 2.2-2.7x. 0.5 s: every
#: run under 50 ms (most of the sweep) still gets 10 or more solves, and the default run of 240
#: runs stays near its 5-minute target on 2 cores (1 s cost about 60 s more wall time, measured).
TIMING_BUDGET = 0.5
#: The most timed solves of one run (a run of a few ms gets this many within the budget).
MAX_REPEATS = 30
#: The least timed solves of one run whose first solve fits in the budget (`--repeats`).
MIN_REPEATS = 3
#: Where the runs execute: worker processes (the default), this process, or a Dask cluster.
DEFAULT_EXECUTOR = "process"
EXECUTORS = (DEFAULT_EXECUTOR, "serial", "dask")
#: Length (s) of the long-horizon energy study on fixed_length (`run --horizon`), full and --quick.
FULL_HORIZON, QUICK_HORIZON = 100.0, 10.0


@dataclass(frozen=True)
class Task:
    """One run: a scene (name or path, with overrides), an integrator and one setting."""

    scene: str
    integrator: str
    dt: float | None = None
    rtol: float | None = None
    atol: float | None = None
    t_end: float | None = None
    save_every: float = SAVE_EVERY
    overrides: tuple = field(default_factory=tuple)  # ((key, value), ...)

    @property
    def step(self) -> Setting:
        """The task's setting as a value (`benchmark.core.policy.Setting`)."""
        return Setting(dt=self.dt, rtol=self.rtol, atol=self.atol)

    @property
    def setting(self) -> str:
        """The setting's label, the runs table's ``setting`` column ("dt=0.005", "rtol=1e-06")."""
        return self.step.label()

    @property
    def identity(self) -> tuple:
        """The task's row's place in the runs table (`benchmark.core.policy.ROW_IDENTITY`)."""
        return tuple(getattr(self, c) for c in ROW_IDENTITY)

    def solve_kwargs(self) -> dict:
        return {"t_end": self.t_end, "save_every": self.save_every, **self.step.solve_kwargs()}


def check_settings(dts=(), rtols=()) -> None:
    """ValueError for a step size that is not a finite number > 0 or a tolerance outside its
    range; needs no JAX, so the command line checks this before importing it. Any step size is
    allowed: a fixed step saves at its step points nearest the save times, its last step is
    shortened to end at t_end (`integrators.base.fixed_step_grid`), and the reference is read
    at the times saved (`benchmark.core.reference.reference_at`)."""
    import math

    for v in dts or ():
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"--dts: dt = {v!r} is invalid (allowed: a finite number > 0)")
    if rtols:
        from reelbench.integrators.lifecycle import RTOL_RULE, rtol_allowed

        for v in rtols:
            if not rtol_allowed(v):
                raise ValueError(f"--rtols: rtol = {v!r} is invalid (allowed: {RTOL_RULE})")


def sweep_dts(dts=None, quick: bool = False) -> tuple:
    """The step sizes of a sweep: ``dts`` if given, else the --quick or the full grid."""
    return tuple(dts) if dts else (QUICK_DTS if quick else FULL_DTS)


def sweep_t_end(t_end: float | None = None, quick: bool = False) -> float | None:
    """The horizon of a sweep: ``t_end`` if given, else --quick's, else None (each scene's own)."""
    return t_end if t_end is not None else (QUICK_T_END if quick else None)


def default_names(plugins: bool = False) -> list[str]:
    """The integrators a run without ``--integrators`` uses: the project's own registered
    methods (`integrators.registry.own`) among `PRESENTATION_ORDER` in that order, then its
    others; with ``plugins`` (`run --with-plugins`) every installed plugin after them (test-only
    ``test_*`` excepted). A plugin is a guest: it joins a default only when asked."""
    from reelbench.integrators import available, registry

    names = available() if plugins else registry.own()
    return [n for n in PRESENTATION_ORDER if n in names] + [
        n for n in names if n not in PRESENTATION_ORDER and not n.startswith("test_")]


def default_sweep_names(plugins: bool = False) -> list[str]:
    """The methods of the default sweep: `default_names` less `EXTENDED_METHODS` (with
    ``plugins``, every installed plugin too)."""
    return [n for n in default_names(plugins) if n not in EXTENDED_METHODS]


def plugin_names(names) -> list[str]:
    """Those of ``names`` that are plugins (not the project's own methods)."""
    names = list(names)
    if not names:  # nothing to look up: no import of the registry (a refusal stays JAX-free)
        return []
    from reelbench.integrators import origin

    return [n for n in names if not origin(n).own]


class MethodSettings(NamedTuple):
    """An integrator and the settings of one of its runs, e.g. ("lgvi", {"dt": 0.0025})."""

    name: str
    settings: dict

    @property
    def label(self) -> str:
        return f"{self.name} {', '.join(f'{k}={v:g}' for k, v in self.settings.items())}"


#: The run that draws the paper's panels (`run`'s paper_<scene>.png): the paper's LGVI at
#: dt = 2.5 ms, inside its stability limit (h ω_max < 2) on all three paper scenes at N = 10
#: (deployment's short elements diverge at 5 ms, measured).
PAPER_METHOD = MethodSettings("lgvi", {"dt": 0.0025})


def paper_method() -> MethodSettings:
    """The method whose run draws the paper's panels (`PAPER_METHOD`, a copy)."""
    return MethodSettings(PAPER_METHOD.name, dict(PAPER_METHOD.settings))


def _own(name: str, shared: tuple, overridden: bool) -> tuple:
    """An adaptive method's tolerances in the sweep: its own ones (`SWEEP_RTOLS`) in the full
    default sweep, else the shared ones (also whenever the command line or --quick sets them).
    Step sizes have no such exception: every fixed-step method gets `FULL_DTS`."""
    return shared if overridden or name not in SWEEP_RTOLS else tuple(SWEEP_RTOLS[name])


def build_tasks(
    scenes=PAPER_SCENES,
    integrators=None,
    *,
    quick: bool = False,
    dts=None,
    rtols=None,
    t_end: float | None = None,
    overrides: dict | None = None,
) -> list[Task]:
    """The sweep as tasks. ``integrators=None`` means the project's methods of the default
    sweep (`default_sweep_names`); unknown names raise ValueError before anything runs."""
    from reelbench.integrators import Capability, get_integrator  # JAX: only once the input is known good

    names = list(integrators) if integrators else default_sweep_names()
    dts = sweep_dts(dts, quick)
    given_rtols = bool(rtols)
    implicit_rtols = tuple(rtols) if rtols else (IMPLICIT_QUICK_RTOLS if quick else IMPLICIT_FULL_RTOLS)
    rtols = tuple(rtols) if rtols else (QUICK_RTOLS if quick else FULL_RTOLS)
    t_end = sweep_t_end(t_end, quick)
    methods = {name: get_integrator(name) for name in names}  # raises for unknown names, before any work
    own_rtols = {name: _own(name, implicit_rtols if integ.has(Capability.IMPLICIT) else rtols, given_rtols or quick)
                 for name, integ in methods.items()}
    check_settings(dts,
                   tuple(v for r in own_rtols.values() for v in r) + rtols + implicit_rtols)
    ov = tuple(sorted((overrides or {}).items()))
    tasks = []
    for scene in scenes:
        for name, integ in methods.items():
            if integ.has(Capability.FIXED_STEP):  # one grid for all of them
                tasks += [Task(scene, name, dt=dt, t_end=t_end, overrides=ov) for dt in dts]
            if integ.has(Capability.ADAPTIVE):
                tasks += [Task(scene, name, **vars(Setting.adaptive(r)), t_end=t_end, overrides=ov)
                          for r in own_rtols[name]]
    return tasks
