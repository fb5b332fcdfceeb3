"""One run lifecycle, shared by every integrator.

What every ``solve()`` must do apart from taking steps lives here, once:

* **validation** of the arguments, before any work (`start_run`: the step mode a method's
  capabilities allow, the horizon and its plausibility, the save interval, the budgets, the
  options a method declares);
* the **save grid** (`integrators.base.save_times`, `step_indices` for a fixed step: any dt,
  saved at the step points nearest the save times, the last step shortened to end at t_end);
* the **guards** (`Guards`): the energy balance bound (from the model's own energy scale,
  `StringPendulum.energy_scale`), the blow-up / non-finite state, the deployed-length limits.
  Their thresholds are run-time values (arguments of the compiled loops), not constants baked
  into compiled code. The policy, the same for every method: the cheap state guards after
  every step, the energy balance at saved points only;
* **status codes and reasons** (`Status`, `blowup_reason`, `length_reason`, `energy_reason`,
  `Run.time_limit_reason`);
* **budgets**: ``max_steps`` and the wall-clock ``time_limit`` (`Run.out_of_time`);
* **typed stats** (`RunStats`);
* **timing**: setup and compilation booked apart from the run (`Run.setup`, `Run.compiled`,
  bounded compile caches `CompileCache`), run time = the whole call minus those
  (`integrators.base.stamp_wall_time`);
* **Trajectory assembly** from quaternion ODE states (`ode_trajectory`).

Two templates use them: `integrators.fixed_step.FixedStepMethod` (a method writes one step) and
`LibraryAdapter` (an adapter writes only how it calls its library: `integrate`). See
integrators/README.md. Nothing here imports JAX at module level.
"""

from __future__ import annotations

import abc
import functools
import math
import sys
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, TypedDict

import numpy as np

from reelbench.integrators import rhs as _rhs
from reelbench.integrators.base import (Capability, Integrator, Status, Trajectory, build_model_timed, check_positive,
                              energy_reason, fixed_step_count, initial_energy, save_interval, stamp_wall_time)
from reelbench.models.schema import PLAUSIBLE as _PLAUSIBLE


#: Set (`request_stop`) to end every solve that has a ``time_limit`` at its next clock check, as if
#: its budget had run out: it returns what it has (status "time_limit"). `simulate` sets it on
#: the first Ctrl-C / SIGTERM, so that a stopped run is saved, not lost.
STOP_REQUESTED = threading.Event()


def request_stop(stop: bool = True) -> None:
    (STOP_REQUESTED.set if stop else STOP_REQUESTED.clear)()


__all__ = [
    "BLOWUP", "CHUNK_SECONDS", "CompileCache", "FIRST_CHUNK", "Guards", "LibraryAdapter", "MAX_PLANNED_STEPS", "MAX_SAVED_BYTES", "ODEProblem",
    "Outcome", "Run", "RunStats", "STOP_REQUESTED", "T_END_MAX", "blowup_reason", "check_max_steps", "check_options",
    "check_positive", "check_tolerances", "energy_reason", "length_reason", "ode_trajectory", "resolve_scene",
    "library_attribute", "request_stop", "run_in_chunks", "start_run", "step_indices",
]

#: A state component beyond this magnitude counts as divergence (positions are tens of metres,
#: velocities at most hundreds of m/s in every shipped scene). The default of `Guards.blowup`.
BLOWUP = 1e8

#: The longest horizon ``solve()`` accepts (s): the scene files' own plausible range for
#: ``t_end`` (`models.schema.PLAUSIBLE`, read from there: one rule).
T_END_MAX = _PLAUSIBLE["t_end"][1]
#: A fixed-step run planned with more steps than this (`integrators.base.fixed_step_count`) is
#: refused before any work (the command line's limit too: at ~10 µs per step on the smallest
#: scene it is more than 3 hours).
MAX_PLANNED_STEPS = 1e9
#: A run whose saved trajectory would need more memory than this (bytes) is refused (the command
#: line's limit).
MAX_SAVED_BYTES = 8 * 2**30


# ------------------------------------------------------------------------------------------
# Validation (bad arguments raise ValueError before any work)
# ------------------------------------------------------------------------------------------
def resolve_scene(scene):
    """A `models.Scene` from a scene or a scene name."""
    from reelbench.models import load_scene
    from reelbench.models.scene import Scene

    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, str):
        return load_scene(scene)
    raise ValueError(f"scene = {scene!r} is invalid (allowed: a models.Scene or a scene name)")


#: The tightest relative tolerance a run may ask for: below it the error estimate is float64
#: rounding of the state (scipy raises anything under 100 eps = 2.2e-14 to that itself), so a
#: tighter one only makes the steps shrink until the step budget runs out.
MIN_RTOL = 1e-14
#: The allowed tolerances in words, for every message that refuses one (the CLI's too).
RTOL_RULE = f"a finite number, {MIN_RTOL:g} <= rtol < 1"


def rtol_allowed(rtol) -> bool:
    """Whether a run may ask for the relative tolerance ``rtol`` (`RTOL_RULE`; the command line's
    checks ask this too)."""
    return MIN_RTOL <= rtol < 1


def check_tolerances(rtol, atol) -> None:
    """rtol in [MIN_RTOL, 1), atol > 0; both required."""
    if rtol is None:
        raise ValueError(f"rtol is required for an adaptive method (allowed: {RTOL_RULE})")
    if atol is None:
        raise ValueError("atol is required for an adaptive method (allowed: a finite number > 0)")
    check_positive("rtol", rtol)
    if not rtol_allowed(rtol):
        raise ValueError(f"rtol = {rtol!r} is invalid (allowed: {RTOL_RULE})")
    check_positive("atol", atol)


def check_max_steps(max_steps) -> None:
    if max_steps is None:
        return
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps = {max_steps!r} is invalid (allowed: an integer >= 1, or None)")


def check_options(name: str, options: dict, allowed: tuple[str, ...] = ()) -> None:
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        allowed_txt = ", ".join(allowed) if allowed else "none"
        raise ValueError(f"{name}: unknown option(s) {', '.join(map(repr, unknown))} (allowed options: {allowed_txt})")


def step_mode(method: Integrator, dt, rtol, atol) -> str:
    """"fixed" or "adaptive": what the arguments ask of ``method``, by its declared capabilities.

    A fixed-step-only method refuses tolerances (it would ignore them); an adaptive-only method
    needs rtol and atol and takes dt as its first step; a method that is both takes dt alone
    (constant step) or rtol and atol (adaptive), never both."""
    fixed, adaptive = method.has(Capability.FIXED_STEP), method.has(Capability.ADAPTIVE)
    tols = rtol is not None or atol is not None
    if fixed and not adaptive:
        if tols:
            raise ValueError(f"{method.name} is a fixed-step method: rtol/atol do not apply "
                             f"(got rtol = {rtol!r}, atol = {atol!r}; allowed: dt alone)")
        check_positive("dt", dt)
        return "fixed"
    if fixed and dt is not None and tols:
        raise ValueError(f"{method.name} takes dt (constant step) or rtol and atol (adaptive), not both "
                         f"(got dt = {dt!r}, rtol = {rtol!r}, atol = {atol!r})")
    if fixed and dt is not None:
        check_positive("dt", dt)
        return "fixed"
    if fixed and not tols:
        raise ValueError(f"{method.name} needs rtol and atol (adaptive; allowed: finite numbers, 0 < rtol < 1, "
                         f"atol > 0) or dt alone (constant step; allowed: a finite number > 0)")
    check_tolerances(rtol, atol)
    check_positive("dt", dt, allow_none=True)  # the first step of an adaptive method, optional
    return "adaptive"


def check_horizon(scene, mode: str, t_end, dt, save_every) -> None:
    """t_end plausible, the first (or every) step and the save interval inside it, and a run
    small enough to plan: at most `MAX_PLANNED_STEPS` fixed steps, `MAX_SAVED_BYTES` saved."""
    check_positive("t_end", t_end)
    if t_end > T_END_MAX:
        raise ValueError(f"t_end = {t_end:g} is implausible (allowed: 0 < t_end <= {T_END_MAX:g} s, the range of "
                         "the scene files)")
    check_positive("save_every", save_every, allow_none=True)
    what = "dt" if mode == "fixed" else "the first step dt"
    if dt is not None and dt > t_end:
        raise ValueError(f"{what} = {dt!r} is larger than t_end = {t_end!r} (allowed: 0 < dt <= t_end)")
    if save_every is not None and save_every > t_end:
        raise ValueError(f"save_every = {save_every!r} is larger than t_end = {t_end!r} "
                         "(allowed: 0 < save_every <= t_end)")
    if mode == "fixed" and (steps := fixed_step_count(t_end, dt)) > MAX_PLANNED_STEPS:
        raise ValueError(f"t_end = {t_end:g} s at dt = {dt:g} s would take {steps:.3g} steps (allowed: at most "
                         f"{MAX_PLANNED_STEPS:.0e}): raise dt or shorten t_end")
    points, size = saved_size(scene, t_end, save_every, dt if mode == "fixed" else None)
    interval = saved_interval(t_end, save_every, dt if mode == "fixed" else None)
    if size > MAX_SAVED_BYTES:
        raise ValueError(f"save_every = {interval:g} s over t_end = {t_end:g} s keeps {points:,} saved states "
                         f"(~{size / 2**30:.3g} GiB; allowed: at most {MAX_SAVED_BYTES / 2**30:g} GiB): "
                         "raise save_every or shorten t_end")


def saved_interval(t_end, save_every, fixed_dt=None) -> float:
    """The interval between a run's saved states: ``save_every`` (`integrators.base.save_interval`),
    never finer than a fixed step ``fixed_dt``."""
    interval = save_interval(t_end, save_every)
    return interval if fixed_dt is None else max(interval, fixed_dt)


def saved_size(scene, t_end, save_every, fixed_dt=None) -> tuple[int, int]:
    """(saved states, bytes) of the trajectory a run keeps, at most: the one size `check_horizon`
    refuses beyond `MAX_SAVED_BYTES` and the command line estimates (`benchmark.core.options.run_size`)."""
    from reelbench.models.layout import StateLayout  # JAX-free: the sizes the scene's effects give

    lay = StateLayout.from_scene(scene)
    points = math.floor(t_end / saved_interval(t_end, save_every, fixed_dt)) + 2
    return points, points * 8 * (lay.nx + 2 * lay.nw + 9 + 2)  # x, velocity, momentum, attitude, work, t


def check_time_limit(time_limit) -> None:
    check_positive("time_limit", time_limit, allow_none=True)


def step_indices(t_end, dt, save_every, max_steps):
    """Step indices to save (0 first, the last step run last), the number of steps run and
    whether max_steps cut the run short (`integrators.base.fixed_step_grid`: any dt, the last
    step shortened to end at t_end)."""
    from reelbench.integrators.base import fixed_step_grid

    n, idx = fixed_step_grid(t_end, dt, save_every)
    truncated = max_steps is not None and n > max_steps
    n_run = min(n, max_steps) if max_steps is not None else n
    idx = idx[idx <= n_run]
    if idx[-1] != n_run:
        idx = np.append(idx, n_run)
    return idx, n_run, truncated


#: a save buffer has at least this many slots (runs of other lengths then share compiled code),
#: fewer for a large state, down to `BUCKET_MIN_SLOTS`, so that its empty slots stay below
#: `BUCKET_BYTES` (zero-filling and copying 256 slots of N = 640 cost 6.5 ms per run)
BUCKET_SLOTS, BUCKET_MIN_SLOTS, BUCKET_BYTES = 256, 16, 1 << 20


def bucket(n: int, slot_bytes: int = 0) -> int:
    """Save-buffer length for ``n`` saved states of ``slot_bytes`` each: the next power of two,
    at least `BUCKET_SLOTS` (fewer for a large state, see there)."""
    least = BUCKET_SLOTS
    while least > BUCKET_MIN_SLOTS and least * slot_bytes > BUCKET_BYTES:
        least //= 2
    return max(least, 1 << (int(n) - 1).bit_length())


# ------------------------------------------------------------------------------------------
# Compile caches
# ------------------------------------------------------------------------------------------
class CompileCache:
    """Compiled functions by what they depend on (the key holds the objects themselves, e.g.
    the model, never their ``id()``), the least recently used dropped beyond ``maxsize``."""

    def __init__(self, maxsize: int = 32):
        self.maxsize = int(maxsize)
        self._entries: OrderedDict = OrderedDict()

    def get(self, key, build: Callable[[], Any]) -> tuple[Any, float]:
        """(the value for ``key``, seconds spent building it: 0.0 when it was cached)."""
        if key in self._entries:
            self._entries.move_to_end(key)
            return self._entries[key], 0.0
        t0 = time.perf_counter()
        value = build()
        seconds = time.perf_counter() - t0
        self._entries[key] = value
        while len(self._entries) > self.maxsize:
            self._entries.popitem(last=False)
        return value, seconds

    def __contains__(self, key) -> bool:
        return key in self._entries

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()


#: With a ``time_limit`` a compiled loop runs in chunks of steps, the clock (and `STOP_REQUESTED`)
#: checked on the host between them, never inside the compiled code: the first chunk has this
#: many steps, later ones are sized to take about `CHUNK_SECONDS` (at most a twentieth of the
#: limit). Without a limit the whole run is one call.
FIRST_CHUNK = 64
CHUNK_SECONDS = 0.25


def run_in_chunks(run: "Run", advance: Callable[[int], tuple[int, bool]], total: int,
                  first: int = FIRST_CHUNK) -> bool:
    """Call ``advance(chunk)`` (run up to ``chunk`` more steps; returns (steps taken, finished))
    until the run is finished or, between two calls, out of time (`Run.out_of_time`). Returns
    whether the time limit stopped it. Without a time limit: one call of ``total`` steps."""
    chunk = total if run.time_limit is None else first
    while True:
        t0 = time.perf_counter()
        done, finished = advance(chunk)
        took = time.perf_counter() - t0
        if finished:
            return False
        if run.out_of_time():
            return True
        target = min(CHUNK_SECONDS, run.time_limit / 20.0)
        chunk = max(first, int(target / max(took / max(done, 1), 1e-9)))


# ------------------------------------------------------------------------------------------
# Guards and reasons
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Guards:
    """The run-time thresholds every method stops by, asked of the model.

    ``E0``: the energy of the initial state; ``energy_bound``: the largest |E − W − E0| (J)
    before a run is ``diverged`` (`integrators.base.energy_bound`: ENERGY_GROWTH_FACTOR × the
    model's `energy_scale`); ``blowup``: a state component at least this large is ``diverged``.
    The deployed-length limits are the model's (`deployed_length_margin`).
    """

    E0: float
    energy_bound: float
    blowup: float = BLOWUP

    @classmethod
    def for_model(cls, model) -> "Guards":
        """The model's guards (computed once per model, then cached)."""
        return _model_guards(model)


def guards_timed(model) -> tuple[Guards, float]:
    """(the model's `Guards`, seconds spent computing them): 0.0 when cached. Computing them runs
    eager JAX once per model (setup): booked with ``compile_time``, like
    `integrators.base.build_model_timed`."""
    misses = _model_guards.cache_info().misses
    t0 = time.perf_counter()
    guards = _model_guards(model)
    return guards, (time.perf_counter() - t0 if _model_guards.cache_info().misses > misses else 0.0)


@functools.lru_cache(maxsize=64)
def _model_guards(model) -> Guards:
    from reelbench.integrators.base import energy_bound

    return Guards(E0=initial_energy(model), energy_bound=energy_bound(model))


def finite_prefix(y: np.ndarray, blowup: float = BLOWUP) -> int:
    """Number of leading rows of y that are finite and below ``blowup`` in magnitude."""
    good = np.all(np.isfinite(y), axis=1) & np.all(np.abs(np.nan_to_num(y, nan=np.inf)) < blowup, axis=1)
    bad = np.flatnonzero(~good)
    return int(bad[0]) if bad.size else len(y)


def state_ok(y: np.ndarray, blowup: float = BLOWUP) -> bool:
    """One state is finite and below ``blowup`` in magnitude (the blow-up guard, in numpy)."""
    return bool(np.all(np.isfinite(y)) and np.max(np.abs(y)) < blowup)


@functools.lru_cache(maxsize=64)
def energy_guard(model):
    """(error, bound): ``error(y)`` = |E − W − E0| of an ODE state (float, jitted), and the bound
    of `integrators.base.energy_bound` beyond which the run is ``diverged`` (the model's `Guards`)."""
    from reelbench.integrators.base import energy_error_ode
    from reelbench.models._jax import jax

    guards = Guards.for_model(model)
    f = _rhs.program(_energy_error_program, model)  # one program per model structure
    values, E0 = _rhs.device_values(model), np.float64(guards.E0)
    return (lambda y: float(f(values, y, E0))), guards.energy_bound


@functools.lru_cache(maxsize=64)
def _energy_error_program(structure, template):
    """|E − W − E0| of an ODE state as f(values, y, E0), jitted (`energy_guard`)."""
    from reelbench.integrators.base import energy_error_ode
    from reelbench.models._jax import jax

    return jax.jit(lambda values, y, E0: energy_error_ode(template.bind(values), y, E0))


def blowup_reason(where: str, blowup: float = BLOWUP) -> str:
    """The `reason` of a run stopped by a non-finite or blown-up state; ``where`` says when."""
    return f"non-finite or blown-up state (|y| >= {blowup:g}) in {where}"


def length_reason(model, ell: float, where: str) -> str:
    """The `reason` of a run stopped on the deployed-length limits (wording: the model's)."""
    return f"the deployed length reached {model.length_limit_name(ell)} {where}"


class RunStats(TypedDict, total=False):
    """The fields of `Trajectory.stats` (integrators/README.md says which method reports which)."""

    steps: int
    rejected_steps: int
    attempted_steps: int
    rhs_evals: int
    jac_evals: int
    lu_decompositions: int
    newton_iterations: int
    max_newton_iterations: int
    counts_unavailable: str
    min_step: float
    median_step: float
    max_step: float
    time_per_step: float
    wall_time: float
    compile_time: float
    count_time: float
    event_time: float
    rhs: str


# ------------------------------------------------------------------------------------------
# One solve() call: its checked arguments, model, guards and clock
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ODEProblem:
    """What a step sees: ``f(t, y)`` the right-hand side on the quaternion ODE state
    y = (x, quat, w, W) (closed form by default, `integrators.rhs`), its ``layout``
    (`models.layout.StateLayout`: slices ``y_x``, ``y_quat``, ``y_w``, ``y_work``), the ``model``
    (`models.StringPendulum`) for anything else (energy, forces, mass matrix), and ``params``:
    the run-time values of the method's options (`FixedStepMethod.run_parameters`, traced)."""

    model: Any
    f: Any
    layout: Any
    params: Any = None
    #: which right-hand side ``f`` is (`integrators.rhs`), to rebuild it on a bound model
    rhs: str = _rhs.DEFAULT_RHS

    def bind(self, values, params=None) -> "ODEProblem":
        """This problem on the model bound to ``values`` (`StringPendulum.bind`; traced, inside a
        compiled program), with ``params``: what a compiled program's step sees."""
        model = _rhs.prepare(self.model.bind(values))
        return ODEProblem(model=model, f=_rhs.ode_rhs(model, self.rhs), layout=self.layout, params=params,
                          rhs=self.rhs)


@dataclass
class Run:
    """One ``solve()`` call after its arguments were checked: what an integration reads, and
    the clock that books setup and compilation apart from the run (``compile_time``)."""

    method: Integrator
    scene: Any
    mode: str  # "fixed" or "adaptive"
    t_end: float
    dt: float | None
    rtol: float | None
    atol: float | None
    save_every: float | None
    max_steps: int | None
    time_limit: float | None
    rhs: str | None
    options: dict
    started: float
    model: Any = None
    guards: Guards | None = None
    compile_time: float = 0.0

    def setup(self, fn: Callable, *args):
        """``fn(*args)``, its seconds booked as setup (with ``compile_time``, not the run)."""
        t0 = time.perf_counter()
        out = fn(*args)
        self.compile_time += time.perf_counter() - t0
        return out

    def compiled(self, cache: CompileCache, key, build: Callable[[], Any]):
        """``cache``'s value for ``key``, built (and its seconds booked as compilation) if missing."""
        value, seconds = cache.get(key, build)
        self.compile_time += seconds
        return value

    def run_time(self) -> float:
        """Seconds of this call so far, setup and compilation excluded (`stamp_wall_time`'s)."""
        return time.perf_counter() - self.started - self.compile_time

    def out_of_time(self) -> bool:
        """The run's wall-clock budget is spent, or a stop was asked for (`request_stop`)."""
        return self.time_limit is not None and (self.run_time() >= self.time_limit or STOP_REQUESTED.is_set())

    def time_limit_reason(self, t: float, kept: str = "") -> str:
        return (f"stopped by time_limit = {self.time_limit:g} s after {self.run_time():.3g} s of run time at "
                f"t = {t:.6g} s (t_end = {self.t_end:g} s){kept}")

    def settings(self, **extra) -> dict:
        """The run's settings as recorded in `Trajectory.settings`."""
        out = {"dt": self.dt, "rtol": self.rtol, "atol": self.atol, "t_end": self.t_end,
               "save_every": self.save_every, "max_steps": self.max_steps, "time_limit": self.time_limit}
        if self.rhs is not None:
            out["rhs"] = self.rhs
        out.update(extra)
        return out

    def ode_problem(self) -> ODEProblem:
        rhs = self.rhs or _rhs.DEFAULT_RHS
        return ODEProblem(model=self.model, f=_rhs.ode_rhs(self.model, rhs), layout=self.model.layout, rhs=rhs)

    def finish(self, traj: Trajectory) -> Trajectory:
        """The epilogue: compile time, run time (`stamp_wall_time`, last) and time per step."""
        traj.stats["compile_time"] = self.compile_time
        stamp_wall_time(traj, self.started)
        if "steps" in traj.stats:
            traj.stats["time_per_step"] = traj.stats["wall_time"] / max(int(traj.stats["steps"]), 1)
        return traj


def start_run(method: Integrator, scene, t_end, *, dt, rtol, atol, save_every, max_steps, time_limit, rhs,
              options: dict, allowed: tuple[str, ...] = (), started: float | None = None,
              validate: Callable[[str], Any] | None = None) -> Run:
    """The prologue of every ``solve()``: start the clock, check every argument (ValueError
    before any work: options, rhs, scene, step mode, horizon, budgets, and ``validate(mode)``,
    the method's own checks of its option values), then build the model and its guards (setup,
    booked with ``compile_time``). ``rhs`` None: the method has its own equations."""
    started = time.perf_counter() if started is None else started
    check_options(method.name, options, allowed)
    if rhs is not None:
        _rhs.check_rhs(rhs)
    scene = resolve_scene(scene)
    t_end = scene.t_end if t_end is None else t_end
    mode = step_mode(method, dt, rtol, atol)
    check_horizon(scene, mode, t_end, dt, save_every)
    check_max_steps(max_steps)
    check_time_limit(time_limit)
    if validate is not None:
        validate(mode)
    run = Run(method=method, scene=scene, mode=mode, t_end=float(t_end), dt=None if dt is None else float(dt),
              rtol=rtol, atol=atol, save_every=save_every, max_steps=max_steps, time_limit=time_limit, rhs=rhs,
              options=options, started=started)
    if "reelbench.models.model" not in sys.modules:  # the first solve() of a process imports JAX: setup
        run.setup(_import_jax)
    run.model, setup = build_model_timed(scene)  # a first build also starts JAX's backend: setup
    run.guards, guards_time = guards_timed(run.model)
    run.compile_time += setup + guards_time
    return run


def _import_jax() -> None:
    import reelbench.models._jax  # noqa: F401  (float64 and the XLA options first)
    from reelbench import models
    import reelbench.models.model  # noqa: F401
    from reelbench import models


def ode_trajectory(model, scene, t, y, *, status, reason, stats, integrator, settings) -> Trajectory:
    """A `Trajectory` from quaternion ODE states y (n, ny) saved at times t (`models.layout`)."""
    lay = model.layout
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float).reshape(len(t), lay.ny)
    return Trajectory(
        t=t,
        x=y[:, lay.y_x].copy(),
        attitude=y[:, lay.y_quat].copy() if lay.has_attitude else None,
        attitude_kind="quaternion",
        velocity=y[:, lay.y_w].copy(),
        work=y[:, lay.y_work][:, 0].copy() if lay.has_work else np.zeros(len(t)),
        status=str(status.value if isinstance(status, Status) else status),
        reason=reason,
        stats=dict(stats),
        integrator=integrator,
        settings=settings,
        scene_name=scene.name,
    )


# ------------------------------------------------------------------------------------------
# The adapter template
# ------------------------------------------------------------------------------------------
class library_attribute:
    """A class attribute that is an object of a library, imported on first access: an adapter
    declares ``solver = library_attribute("diffrax", "Tsit5")`` (reads as ``diffrax.Tsit5``) and
    its class definition stays free of the library (and of JAX)."""

    def __init__(self, module: str, name: str):
        self.module, self.name = module, name

    def __get__(self, obj, owner=None):
        import importlib

        return getattr(importlib.import_module(self.module), self.name)

    def __repr__(self) -> str:
        return f"{self.module}.{self.name}"


@dataclass
class Outcome:
    """What an adapter's `LibraryAdapter.integrate` returns: the saved times and quaternion ODE
    states it reached, how the run ended, the library's counters and extra settings."""

    t: np.ndarray
    y: np.ndarray
    status: Status = Status.OK
    reason: str = ""
    stats: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    #: the solution between the saved points where the adapter records one (`Trajectory.dense`)
    dense: Any = None


class LibraryAdapter(Integrator):
    """An adapter to a solver library in one method: `integrate` (how the library is called).

    The prologue (timer, argument checks, model and guards, compile accounting: `start_run`)
    and the epilogue (the finite prefix of the saved states, the `Trajectory`, statuses,
    `stamp_wall_time`) are the lifecycle's. ``integrate`` gets the checked `Run` and returns an
    `Outcome`; it checks the energy balance at its saved points (`Run.guards`) and the budgets
    (``run.max_steps``, `Run.out_of_time`)."""

    #: the solve() options beyond the common ones (with their checks in ``integrate``)
    option_names: ClassVar[tuple[str, ...]] = ()

    def solve(self, scene, t_end=None, *, dt=None, rtol=None, atol=None, save_every=None, max_steps=None,
              time_limit=None, rhs=_rhs.DEFAULT_RHS, **options) -> Trajectory:
        """``rhs``: "closed_form" (default, O(N)) or "autodiff" (see `integrators.rhs`)."""
        run = start_run(self, scene, t_end, dt=dt, rtol=rtol, atol=atol, save_every=save_every,
                        max_steps=max_steps, time_limit=time_limit, rhs=rhs, options=options,
                        allowed=self.option_names, started=time.perf_counter(),
                        validate=lambda mode: self.check_option_values(options, mode))
        return self.finish(run, self.integrate(run))

    def check_option_values(self, options: dict, mode: str) -> None:
        """Refuse a bad value of one of `option_names` (ValueError, before any work)."""

    @abc.abstractmethod
    def integrate(self, run: Run) -> Outcome:
        """Call the library on ``run`` and return what it reached."""

    def finish(self, run: Run, out: Outcome) -> Trajectory:
        """The epilogue: keep the finite prefix, assemble the `Trajectory`, stamp the run time."""
        y = np.asarray(out.y, dtype=float).reshape(len(out.t), run.model.layout.ny)
        n = finite_prefix(y, run.guards.blowup)
        status, reason = out.status, out.reason
        if n < len(y):
            status, reason = Status.DIVERGED, reason or "non-finite saved state"
        stats = {**out.stats, "rhs": run.rhs}
        traj = ode_trajectory(run.model, run.scene, np.asarray(out.t)[:n], y[:n], status=status, reason=reason,
                              stats=stats, integrator=self.name, settings=run.settings(**out.settings))
        traj.dense = out.dense
        return run.finish(traj)
