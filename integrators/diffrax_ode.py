"""Baselines from diffrax: Tsit5 (adaptive, or constant step when only ``dt`` is given) and
Kvaerno5 (implicit ESDIRK, adaptive).

The right-hand side is the O(N) closed form by default, the autodiff one with
``rhs="autodiff"`` (`integrators.rhs`); Kvaerno5's Newton differentiates it by forward mode.

The whole solve is one jitted function of (y0, t1, saved times, rtol, atol, dt0, min_step),
compiled ahead of time with ``jax.jit(...).lower(...).compile()`` and cached per
(model, rhs, solver, step-size mode, number of saved times, max_steps, dt0 given), so repeated
calls with other tolerances, horizons or step sizes do not recompile; ``stats["compile_time"]``
is that compilation (0 when cached) and ``stats["wall_time"]`` the rest of the ``solve()`` call,
output conversion included (`integrators.base.stamp_wall_time`).

``stats["rhs_evals"]`` (Tsit5) is the algorithm's count: 6 per attempted step (7 stages, the
first shared with the previous step's last: FSAL), 1 at the start, and 2 more for the initial
step-size guess when no ``dt`` is given (diffrax's PID controller evaluates f at y0 and at
y0 + h0 f0). Checked against a counting right-hand side in tests/test_rhs.py: exact with a
``dt``; without one XLA may merge the repeated f(t0, y0) evaluations, so the executed count
is 1-2 lower (measured: 6n + 1 or 6n + 2). Kvaerno5's Newton iterations are not
exposed by diffrax, so its evaluation counts are left empty (NaN), not estimated.

Failures never raise (``throw=False``); ``sol.result`` is mapped to a status:
``max_steps_reached`` -> "max_steps", ``dt_min_reached`` -> "step_size_collapse" (the PID
controller gets ``dtmin = min_step``, default 1e-12 t_end, with ``force_dtmin=False``), other
errors -> "failed" with diffrax's message. A terminating `diffrax.Event` stops the run when the
deployed length leaves (0, L - b) ("length_limit", at the crossing found by a root find on the dense
output, like scipy's events) or the state becomes non-finite or blows up
("diverged"); the trajectory is kept up to the last saved point before that.

The quaternion is not renormalised. No ``@register``: found through the entry-point group.
"""

from __future__ import annotations

import math
import time
from typing import ClassVar

import diffrax as dfx
import numpy as np
import optimistix as optx

from integrators import rhs as _rhs
from integrators.base import (Capability, Integrator, Status, Trajectory, check_positive,
                              energy_error_ode, energy_reason, save_times, stamp_wall_time,
                              build_model_timed)
from integrators.lifecycle import (blowup_reason, check_max_steps, check_options, check_tolerances, energy_guard,
                                   finite_prefix, guards_timed, length_reason, ode_trajectory, resolve_scene,
                                   state_ok)
from models._jax import jax, jnp

#: Default step budget (diffrax's own default, 4096, is too small for tight tolerances here).
DEFAULT_MAX_STEPS = 100_000
#: Default minimum step for the PID controller, relative to t_end: below it -> step_size_collapse.
DEFAULT_MIN_STEP_REL = 1e-12

#: Kvaerno5's Newton tolerances, relative to the step-size controller's rtol/atol.
NEWTON_TOL_FACTOR = 1e-2

_COMPILED: dict[tuple, object] = {}


#: diffrax result -> status (diffrax's public API: items compared with ``==``, messages by
#: ``RESULTS[item]``); an event is resolved by `_stop_condition`'s guards, other results are "failed".
_RESULT_STATUS = (
    (dfx.RESULTS.successful, Status.OK),
    (dfx.RESULTS.max_steps_reached, Status.MAX_STEPS),
    (dfx.RESULTS.dt_min_reached, Status.STEP_SIZE_COLLAPSE),
)


def _status_of(result) -> Status | None:
    """The status of a (concrete) diffrax result; None for an event, FAILED for any other."""
    if bool(result == dfx.RESULTS.event_occurred):
        return None
    return next((status for item, status in _RESULT_STATUS if bool(result == item)), Status.FAILED)


def _result_message(result) -> str:
    try:
        return dfx.RESULTS[result]
    except Exception:  # pragma: no cover - depends on the diffrax version
        return f"diffrax result {result!r}"


def _stop_condition(model):
    """Event conditions: a non-finite / blown-up state or an energy balance error beyond the
    bound (a boolean, checked at the end of every step) and, with a reel, the deployed-length
    margin (a real number: the run stops where it crosses zero, located by a root find on the
    step's dense output, as scipy's events are). The thresholds are the solve's ``args`` =
    (E0, energy bound, blow-up bound) (`integrators.lifecycle.Guards`): run-time values, not
    constants of the compiled solve."""
    lay = model.layout

    def guards(t, y, args, **kwargs):
        E0, e_bound, blowup = args
        bad = ~jnp.all(jnp.isfinite(y)) | (jnp.max(jnp.abs(y)) >= blowup)
        return bad | ~(energy_error_ode(model, y, E0) <= e_bound)

    if not lay.has_reel:
        return guards

    def length_margin(t, y, args, **kwargs):
        return model.deployed_length_margin(y[lay.y_x])

    return (guards, length_margin)


#: tolerances of the event time's root find (s; the margin is in m and moves at ~m/s)
EVENT_TIME_TOL = 1e-10


def _build(model, solver_name: str, adaptive: bool, n_save: int, max_steps: int, dt0_given: bool,
           rhs: str = _rhs.DEFAULT_RHS):
    f = _rhs.ode_rhs(model, rhs)
    term = dfx.ODETerm(lambda t, y, args: f(t, y))
    event = dfx.Event(_stop_condition(model),
                      root_finder=optx.Newton(rtol=EVENT_TIME_TOL, atol=EVENT_TIME_TOL) if model.layout.has_reel else None)

    def run(y0, t1, ts, rtol, atol, dt0, min_step, E0, e_bound, blowup):
        if solver_name == "kvaerno5":
            # Full Newton (Jacobian every iteration): diffrax's default VeryChord (Jacobian frozen
            # over the step) failed to converge on about half the steps on the string and the
            # controller rejected them (207 accepted / 198 rejected vs 16 / 1 with Newton).
            solver = dfx.Kvaerno5(root_finder=optx.Newton(rtol=NEWTON_TOL_FACTOR * rtol, atol=NEWTON_TOL_FACTOR * atol))
        else:
            solver = dfx.Tsit5()
        if adaptive:
            controller = dfx.PIDController(rtol=rtol, atol=atol, dtmin=min_step, force_dtmin=False)
        else:
            controller = dfx.ConstantStepSize()
        sol = dfx.diffeqsolve(
            term, solver, t0=0.0, t1=t1, dt0=dt0 if dt0_given else None, y0=y0,
            saveat=dfx.SaveAt(ts=ts, t1=True), stepsize_controller=controller, event=event,
            max_steps=max_steps, throw=False, args=(E0, e_bound, blowup),
        )
        return {
            "ts": sol.ts, "ys": sol.ys, "result": sol.result,
            "num_steps": sol.stats["num_steps"], "num_accepted_steps": sol.stats["num_accepted_steps"],
            "num_rejected_steps": sol.stats["num_rejected_steps"],
        }

    return jax.jit(run)


def _compiled(model, solver_name, adaptive, n_save, max_steps, dt0_given, example_args, rhs=_rhs.DEFAULT_RHS):
    """(compiled solve, compile time in s; 0 when it was cached)."""
    key = (model, rhs, solver_name, adaptive, n_save, max_steps, dt0_given)
    fn = _COMPILED.get(key)
    if fn is not None:
        return fn, 0.0
    tc = time.perf_counter()
    fn = _build(model, solver_name, adaptive, n_save, max_steps, dt0_given, rhs).lower(*example_args).compile()
    compile_time = time.perf_counter() - tc
    _COMPILED[key] = fn
    return fn, compile_time


def clear_cache() -> None:
    """Forget the compiled solves (tests, memory)."""
    _COMPILED.clear()


class DiffraxODE(Integrator):
    """Adapter for diffrax solvers on the model's quaternion ODE state."""

    solver_name: ClassVar[str] = ""
    allows_constant_step: ClassVar[bool] = False
    option_names: ClassVar[tuple[str, ...]] = ("min_step",)
    #: stages of an explicit FSAL Runge-Kutta method (rhs_evals follow from the steps); 0: not counted
    fsal_stages: ClassVar[int] = 0

    def solve(self, scene, t_end=None, *, dt=None, rtol=None, atol=None, save_every=None, max_steps=None,
              rhs=_rhs.DEFAULT_RHS, **options) -> Trajectory:
        """``rhs``: "closed_form" (default, O(N)) or "autodiff" (see `integrators.rhs`)."""
        started = time.perf_counter()  # run time = the whole call minus compilation (issue #11)
        # ---- arguments, all checked before any work ----
        check_options(self.name, options, self.option_names)
        _rhs.check_rhs(rhs)
        scene = resolve_scene(scene)
        t_end = scene.t_end if t_end is None else t_end
        check_positive("t_end", t_end)
        check_positive("dt", dt, allow_none=True)
        check_positive("save_every", save_every, allow_none=True)
        check_max_steps(max_steps)
        t_end = float(t_end)
        constant = self.allows_constant_step and dt is not None and rtol is None and atol is None
        if constant:
            if "min_step" in options:
                raise ValueError(f"{self.name}: min_step applies to adaptive steps only (allowed: omit it with a constant dt)")
        else:
            if self.allows_constant_step and rtol is None and atol is None:
                raise ValueError(f"{self.name} needs rtol and atol (adaptive; allowed: finite numbers, 0 < rtol < 1, "
                                 f"atol > 0) or dt alone (constant step; allowed: a finite number > 0)")
            check_tolerances(rtol, atol)
        min_step = options.get("min_step", DEFAULT_MIN_STEP_REL * t_end)
        check_positive("min_step", min_step)

        model, setup_time = build_model_timed(scene)  # a first build is setup: booked with compile time
        y0 = jnp.asarray(model.initial_ode_state())
        guards, guards_time = guards_timed(model)  # the guards' thresholds: setup, booked with compile time
        setup_time += guards_time
        if constant:
            t_save = save_times(t_end, save_every, dt)
            t1 = float(math.floor(t_end / dt + 1e-9) * dt)  # whole steps only, like the LGVI
            n_steps = int(round(t1 / dt))
            if t1 <= 0:
                raise ValueError(f"dt = {dt!r} is invalid for t_end = {t_end!r} (allowed: 0 < dt <= t_end)")
            budget = max_steps if max_steps is not None else max(DEFAULT_MAX_STEPS, n_steps + 16)
        else:
            t_save = save_times(t_end, save_every)
            t1 = t_end
            budget = max_steps if max_steps is not None else DEFAULT_MAX_STEPS
        settings = {"rtol": rtol, "atol": atol, "dt": dt, "save_every": save_every, "max_steps": budget,
                    "t_end": t_end, "step_size": "constant" if constant else "pid", "min_step": None if constant else min_step,
                    "rhs": rhs}
        t_save = np.minimum(t_save, t1)  # diffrax refuses saved times past t1, even by an ulp
        dt0_given = dt is not None
        args = (y0, jnp.asarray(t1), jnp.asarray(t_save), jnp.asarray(rtol if rtol is not None else 0.0),
                jnp.asarray(atol if atol is not None else 0.0), jnp.asarray(min(dt, t1) if dt0_given else 0.0),
                jnp.asarray(min_step), *map(jnp.asarray, (guards.E0, guards.energy_bound, guards.blowup)))
        fn, compile_time = _compiled(model, self.solver_name, not constant, len(t_save), int(budget), dt0_given, args, rhs)
        compile_time += setup_time
        e_err, e_bound = energy_guard(model)  # used on the saved points of a failed run
        if compile_time > setup_time:  # a first solve of this model: compile the guard with it, not in the run time
            tc = time.perf_counter()
            e_err(np.asarray(y0))
            compile_time += time.perf_counter() - tc

        # ---- run ----
        out = jax.block_until_ready(fn(*args))

        ts = np.asarray(out["ts"], dtype=float)
        ys = np.asarray(out["ys"], dtype=float)
        result = out["result"]
        code_status = _status_of(result)
        # diffrax writes the saved points in order and pads the rest with inf; the SaveAt(t1=True)
        # entry (the state where the solve stopped, for any result) follows the last saved time.
        n_valid = int(np.sum(np.isfinite(ts)))
        t_final, y_final = ts[n_valid - 1], ys[n_valid - 1]
        ts, ys = ts[: n_valid - 1], ys[: n_valid - 1]
        if len(ts) == 0:  # stopped before the first accepted step: keep the initial state
            ts, ys = np.zeros(1), np.asarray(y0, dtype=float)[None, :]
        reason = ""
        if code_status is None:  # the event: which guard stopped the run
            if not state_ok(y_final):
                status = Status.DIVERGED
                reason = blowup_reason(f"the step ending at t = {t_final:.6g}")
            elif not e_err(y_final) <= e_bound:
                status = Status.DIVERGED
                reason = energy_reason(e_err(y_final), e_bound, float(t_final),
                                       "; trajectory kept up to the last saved point before it")
            else:
                status = Status.LENGTH_LIMIT
                ell = float(model.L - y_final[0])
                reason = length_reason(model, ell, f"at t = {t_final:.6g} s")
        else:
            status = code_status
            if status is not Status.OK:
                reason = f"{_result_message(result)} (stopped at t = {t_final:.6g})"

        # keep the saved points the solve actually reached, finite, inside the length range
        n = finite_prefix(ys)
        if n < len(ys) and status is Status.OK:
            status, reason = Status.DIVERGED, "non-finite saved state"
        ts, ys = ts[:n], ys[:n]
        # the event stops the solve at the end of the step that crossed the energy bound, and that
        # point may be a saved one: keep only saved points within the bound
        errs = np.array([e_err(y) for y in ys]) if status is not Status.OK else np.zeros(len(ys))
        over = np.flatnonzero(~(errs <= e_bound))
        if over.size:
            m = int(over[0])  # >= 1: the error is 0 at the initial state
            if status is not Status.DIVERGED:
                status = Status.DIVERGED
                reason = energy_reason(float(errs[over[0]]), e_bound, float(ts[over[0]]))
            ts, ys = ts[:m], ys[:m]
        if status is Status.LENGTH_LIMIT and model.layout.has_reel:
            s = ys[:, 0]
            ell = model.L - s
            inside = (ell > model.ell_min) & (model.L - model.b - ell > 0)
            m = int(np.argmin(inside)) if not inside.all() else len(ts)
            ts, ys = ts[:m], ys[:m]

        stats = {
            "steps": int(out["num_accepted_steps"]),
            "rejected_steps": int(out["num_rejected_steps"]),
            "attempted_steps": int(out["num_steps"]),
            "compile_time": compile_time,
            "rhs": rhs,
        }
        if self.fsal_stages:  # explicit FSAL Runge-Kutta: the count follows from the steps (docstring)
            stats["rhs_evals"] = (self.fsal_stages - 1) * int(out["num_steps"]) + 1 + (0 if dt0_given else 2)
            stats["jac_evals"] = stats["lu_decompositions"] = 0
        if status is Status.LENGTH_LIMIT:
            stats["event_time"] = float(t_final)
        traj = ode_trajectory(model, scene, ts, ys, status=status, reason=reason, stats=stats,
                               integrator=self.name, settings=settings)
        return stamp_wall_time(traj, started)


class Tsit5(DiffraxODE):
    name = "tsit5"
    solver_name = "tsit5"
    allows_constant_step = True
    fsal_stages = 7
    capabilities = frozenset({Capability.ADAPTIVE, Capability.FIXED_STEP})
    order = 5
    description = "diffrax Tsit5: PID-adaptive (rtol/atol) or constant step (dt alone), quaternion attitude"
    horizon_settings = {"rtol": 1e-6, "atol": 1e-8}


class Kvaerno5(DiffraxODE):
    name = "kvaerno5"
    solver_name = "kvaerno5"
    capabilities = frozenset({Capability.ADAPTIVE, Capability.IMPLICIT})
    order = 5
    description = "diffrax Kvaerno5 (implicit ESDIRK 5(4), full Newton), PID-adaptive, quaternion attitude"
    #: measured on the shared 2-core machine: 245-300 s of compilation per scene
    #: measured 2026-11-30 (one core): 0.2 s of stiff_string had not finished after 6 min; its full
    #: Newton re-forms the Jacobian at every iteration
    expensive = "re-forms its Jacobian at every Newton iteration (0.2 s of stiff_string ran over 6 min here)"
    cost_hint = (30.0, 3.0)
