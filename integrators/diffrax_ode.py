"""Baselines from diffrax, compiled with JAX: Tsit5, Dopri5 and Dopri8 (explicit; adaptive, or a
constant step when only ``dt`` is given) and Kvaerno5 (implicit ESDIRK, adaptive).

``dopri5`` is the Dormand–Prince 5(4) pair of scipy's RK45 (the same tableau), compiled:
the two differ in how they are run, not in the method. ``dopri8`` is diffrax's Dopri8, the
Prince–Dormand 8(7) pair (14 stages, FSAL): an eighth-order Dormand–Prince method like scipy's
DOP853, but not DOP853's 8(5,3) tableau (other nodes and weights).

The right-hand side is the O(N) closed form by default, the autodiff one with
``rhs="autodiff"`` (`integrators.rhs`); Kvaerno5's Newton differentiates it by forward mode.
The solver is a class attribute (``solver``, e.g. diffrax's ``Tsit5``; `make_solver` builds it,
Kvaerno5's with its Newton root finder).

The whole solve is one jitted function of (y0, t1, saved times, rtol, atol, dt0, min_step,
guards, deadline), compiled ahead of time and cached (`CompileCache`, bounded) per (model, rhs,
solver, step-size mode, number of saved times, max_steps, time limit or not), so repeated calls
with other tolerances, horizons or step sizes do not recompile; ``stats["compile_time"]`` is
that compilation (0 when cached) and ``stats["wall_time"]`` the rest of the ``solve()`` call.

Counts: for the explicit FSAL methods ``stats["rhs_evals"]`` follows from the steps: (stages −
1) per attempted step, 1 at the start, and 2 more for the initial step-size guess of an adaptive
run (diffrax's PID controller evaluates f at y0 and at y0 + h0 f0). Checked against a counting
right-hand side in tests/test_rhs.py: exact with a constant step; adaptive, XLA may merge the
repeated f(t0, y0), so the executed count is 1-2 lower. Kvaerno5's Newton iterations are not
exposed by diffrax, and counting them inside the compiled solve takes a host callback per
evaluation (~0.1 ms each here, several times a Newton iteration at small N): so a plain run
says ``stats["counts_unavailable"]`` (why, in words), and ``solve(..., count_evaluations=True)``
replays the run with a counting right-hand side (`_counting`, compiled once more; the replay's
seconds are ``stats["count_time"]``, not run time). Its full Newton linearises f at every
iteration (the residual is the linearisation's value) and factorises the materialised Jacobian
by LU: ``rhs_evals`` = evaluations + linearisations, ``jac_evals`` = ``lu_decompositions`` =
linearisations (measured N = 2, rtol 1e-6: 16 per step, none outside Newton).

Failures never raise (``throw=False``); ``sol.result`` is mapped to a status:
``max_steps_reached`` -> "max_steps", ``dt_min_reached`` -> "step_size_collapse" (the PID
controller gets ``dtmin = min_step``, default 1e-12 t_end, with ``force_dtmin=False``), other
errors -> "failed" with diffrax's message. A terminating `diffrax.Event` stops the run when the
deployed length leaves (ℓ_min, L - b) ("length_limit", at the crossing found by a root find on
the dense output, like scipy's events), when the state becomes non-finite or blows up
("diverged"), or, with a ``time_limit``, when the clock says so ("time_limit": the event reads
the clock through a host callback after every step, in a separately compiled solve, because a
compiled diffrax solve cannot be resumed exactly — its next step size is not part of its saved
state). The energy balance is checked at the saved points (computed inside the same compiled
solve); the trajectory is kept up to the last saved point before any of these.

The quaternion is not renormalised. No ``@register``: found through the entry-point group.
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np

from integrators.base import Capability, Status, energy_reason, fixed_step_grid, save_times
from integrators.lifecycle import (CompileCache, LibraryAdapter, Outcome, Run, blowup_reason, length_reason,
                                   library_attribute, state_ok)

#: Default step budget (diffrax's own default, 4096, is too small for tight tolerances here).
DEFAULT_MAX_STEPS = 100_000
#: Default minimum step for the PID controller, relative to t_end: below it -> step_size_collapse.
DEFAULT_MIN_STEP_REL = 1e-12
#: Kvaerno5's Newton tolerances, relative to the step-size controller's rtol/atol.
NEWTON_TOL_FACTOR = 1e-2
#: tolerances of the event time's root find (s; the margin is in m and moves at ~m/s)
EVENT_TIME_TOL = 1e-10

_SOLVES = CompileCache(maxsize=16)

#: Why Kvaerno5 reports no counts by default (``solve(..., count_evaluations=True)`` counts them)
COUNTS_UNAVAILABLE = ("diffrax does not expose Kvaerno5's Newton iterations; solve(..., count_evaluations=True) "
                      "counts its evaluations and Jacobians in a replay of the run with host callbacks inside the "
                      "compiled solve (one more compilation, and a replay several times the run: measured N = 4, "
                      "157 steps, 2,600 linearisations: 1.5 s against 0.25 s)")


def _stop_condition(model, timed: bool):
    """Event conditions: a non-finite / blown-up state or, with ``timed``, the deadline passed (a
    boolean, checked at the end of every step) and, with a reel, the deployed-length margin (a
    real number: the run stops where it crosses zero, located by a root find on the step's dense
    output, as scipy's events are). The thresholds are the solve's ``args`` = (blow-up bound,
    deadline): run-time values, not constants of the compiled solve."""
    from jax.experimental import io_callback

    from models._jax import jax, jnp

    lay = model.layout

    def guards(t, y, args, **kwargs):
        blowup, deadline = args
        bad = ~jnp.all(jnp.isfinite(y)) | (jnp.max(jnp.abs(y)) >= blowup)
        if timed:
            from integrators.lifecycle import STOP_REQUESTED  # a stop asked for ends the run as the deadline does

            late = io_callback(lambda d: np.bool_(time.perf_counter() >= d or STOP_REQUESTED.is_set()),
                               jax.ShapeDtypeStruct((), jnp.bool_), deadline, ordered=False)
            bad = bad | late
        return bad

    if not lay.has_reel:
        return guards

    def length_margin(t, y, args, **kwargs):
        return model.deployed_length_margin(y[lay.y_x])

    return (guards, length_margin)


def _counting(f, counts: list):
    """``f`` counting its evaluations (counts[0]) and linearisations (counts[1], the Jacobians of
    a Newton iteration) with host callbacks inside the compiled code (Kvaerno5: diffrax does not
    expose the counts)."""
    from models._jax import jax

    def tick(i):
        return lambda *_: counts.__setitem__(i, counts[i] + 1)

    @jax.custom_jvp
    def g(t, y):
        jax.debug.callback(tick(0), t)
        return f(t, y)

    @g.defjvp
    def g_jvp(primals, tangents):
        jax.debug.callback(tick(1), primals[0])
        return jax.jvp(f, primals, tangents)

    return g


class DiffraxODE(LibraryAdapter):
    """Adapter for diffrax solvers on the model's quaternion ODE state."""

    implementation = "jax-compiled"
    solver: ClassVar[Any] = library_attribute("diffrax", "Tsit5")
    option_names = ("min_step",)
    #: stages of an explicit FSAL Runge-Kutta method (rhs_evals follow from the steps); 0: the
    #: solve counts its evaluations itself (`_counting`)
    fsal_stages: ClassVar[int] = 0

    def make_solver(self, rtol, atol):
        """The diffrax solver of this class (traced: rtol/atol are run-time values)."""
        return self.solver()

    def integrate(self, run: Run) -> Outcome:
        from models._jax import jax

        constant = run.mode == "fixed"
        min_step = self._min_step(run, constant)
        t_save, t1, budget = self._grid(run, constant)
        args = self._arguments(run, t_save, t1, min_step)
        key = (run.model, run.rhs, type(self), constant, len(t_save), int(budget), run.dt is not None,
               run.time_limit is not None)
        fn, _ = run.compiled(_SOLVES, key, lambda: self._compile(run, constant, int(budget), args, counting=False))
        deadline = np.float64(time.perf_counter() + run.time_limit - run.run_time()) if run.time_limit else np.float64(0)
        out = jax.block_until_ready(fn(*args[:-1], deadline))
        result = self._ending(run, out, t1)
        result.stats.update(self._counts(run, key, args, out, constant, int(budget)))
        result.settings.update(max_steps=budget, step_size="constant" if constant else "pid",
                               min_step=None if constant else min_step)
        return result

    def check_option_values(self, options: dict, mode: str) -> None:
        from integrators.base import check_positive

        if "min_step" in options:
            if mode == "fixed":
                raise ValueError(f"{self.name}: min_step applies to adaptive steps only (allowed: omit it with a "
                                 "constant dt)")
            check_positive("min_step", options["min_step"])
        count = options.get("count_evaluations", False)
        if not isinstance(count, bool):
            raise ValueError(f"count_evaluations = {count!r} is invalid (allowed: True or False)")

    @staticmethod
    def _min_step(run: Run, constant: bool) -> float | None:
        return None if constant else float(run.options.get("min_step", DEFAULT_MIN_STEP_REL * run.t_end))

    def _grid(self, run: Run, constant: bool):
        """(saved times, end time, step budget): with a constant dt, the step points nearest the
        save times and t_end (diffrax shortens the last step to land on it), like the LGVI."""
        if constant:
            n_steps, _ = fixed_step_grid(run.t_end, run.dt, run.save_every)
            t1 = run.t_end
            t_save = save_times(run.t_end, run.save_every, run.dt)
            # as many saved times for every dt (t_end repeated; `_ending` keeps one), so that a new
            # step size compiles nothing: the compiled solve is keyed by their number
            full = len(save_times(run.t_end, run.save_every))
            t_save = np.append(t_save, np.full(max(0, full - len(t_save)), t1))
            budget = run.max_steps if run.max_steps is not None else max(DEFAULT_MAX_STEPS, n_steps + 16)
        else:
            t1, t_save = run.t_end, save_times(run.t_end, run.save_every)
            budget = run.max_steps if run.max_steps is not None else DEFAULT_MAX_STEPS
        return np.minimum(t_save, t1), t1, budget  # diffrax refuses saved times past t1, even by an ulp

    @staticmethod
    def _arguments(run: Run, t_save, t1, min_step):
        g = run.guards
        f64 = np.float64
        return (np.asarray(run.model.initial_ode_state(), dtype=float), f64(t1), np.asarray(t_save, dtype=float),
                f64(run.rtol or 0.0), f64(run.atol or 0.0), f64(run.dt if run.dt is not None else 0.0),
                f64(min_step or 0.0), f64(g.E0), f64(g.energy_bound), f64(g.blowup), f64(0.0))

    def _compile(self, run: Run, constant: bool, max_steps: int, args, counting: bool):
        """(AOT-compiled solve, the list its counting callbacks add to, or None)."""
        counts = [0, 0] if counting else None
        return self._build(run, constant, max_steps, counts).lower(*args).compile(), counts

    def _build(self, run: Run, constant: bool, max_steps: int, counts: list | None):
        """The jitted solve: (saved times, states, their energy errors, result, step counts)."""
        import diffrax as dfx
        import optimistix as optx

        from integrators import rhs as _rhs
        from integrators.base import energy_error_ode
        from models._jax import jax

        model, dt0_given, timed = run.model, run.dt is not None, run.time_limit is not None
        f = _rhs.ode_rhs(model, run.rhs)
        if counts is not None:
            f = _counting(f, counts)
        term = dfx.ODETerm(lambda t, y, args: f(t, y))
        root = optx.Newton(rtol=EVENT_TIME_TOL, atol=EVENT_TIME_TOL) if model.layout.has_reel else None
        event = dfx.Event(_stop_condition(model, timed), root_finder=root)

        def solve(y0, t1, ts, rtol, atol, dt0, min_step, E0, e_bound, blowup, deadline):
            if constant:
                controller = dfx.ConstantStepSize()
            else:
                controller = dfx.PIDController(rtol=rtol, atol=atol, dtmin=min_step, force_dtmin=False)
            sol = dfx.diffeqsolve(term, self.make_solver(rtol, atol), t0=0.0, t1=t1, dt0=dt0 if dt0_given else None,
                                  y0=y0, saveat=dfx.SaveAt(ts=ts, t1=True), stepsize_controller=controller,
                                  event=event, max_steps=max_steps, throw=False, args=(blowup, deadline))
            errs = jax.vmap(lambda y: energy_error_ode(model, y, E0))(sol.ys)
            return {"ts": sol.ts, "ys": sol.ys, "errs": errs, "result": sol.result,
                    "num_steps": sol.stats["num_steps"], "num_accepted_steps": sol.stats["num_accepted_steps"],
                    "num_rejected_steps": sol.stats["num_rejected_steps"]}

        return jax.jit(solve)

    def _ending(self, run: Run, out: dict, t1: float) -> Outcome:
        """The saved points the solve reached and how it ended (event, result, energy guard)."""
        ts, ys, errs = (np.asarray(out[k], dtype=float) for k in ("ts", "ys", "errs"))
        # diffrax writes the saved points in order and pads the rest with inf; the SaveAt(t1=True)
        # entry (the state where the solve stopped, for any result) follows the last saved time
        n_valid = int(np.sum(np.isfinite(ts)))
        t_final, y_final = float(ts[n_valid - 1]), ys[n_valid - 1]
        ts, ys, errs = ts[: n_valid - 1], ys[: n_valid - 1], errs[: n_valid - 1]
        once = np.r_[True, np.diff(ts) > 0] if len(ts) else np.ones(0, bool)  # a repeated t_end saved once
        ts, ys, errs = ts[once], ys[once], errs[once]
        if len(ts) == 0:  # stopped before the first saved time after 0: keep the initial state
            ts, ys, errs = np.zeros(1), np.asarray(run.model.initial_ode_state(), dtype=float)[None, :], np.zeros(1)
        status, reason = _result_status(run, out["result"], y_final, t_final)
        # the energy guard at the saved points: the first one beyond the bound ends the trajectory
        # there, and it came before whatever stopped the solve
        over = np.flatnonzero(~(errs <= run.guards.energy_bound))
        if over.size:
            m = int(over[0])  # >= 1: the error is 0 at the initial state
            status = Status.DIVERGED
            reason = energy_reason(float(errs[m]), run.guards.energy_bound, float(ts[m]),
                                   f"; trajectory kept up to the previous saved point t = {ts[m - 1]:.6g} s")
            ts, ys = ts[:m], ys[:m]
        elif status is Status.LENGTH_LIMIT:
            ell = run.model.L - ys[:, 0]
            inside = (ell > run.model.ell_min) & (run.model.L - run.model.b - ell > 0)
            m = int(np.argmin(inside)) if not inside.all() else len(ts)
            ts, ys = ts[:m], ys[:m]
        stats = {"event_time": t_final} if status is Status.LENGTH_LIMIT else {}
        return Outcome(t=ts, y=ys, status=status, reason=reason, stats=stats)

    def _counts(self, run: Run, key, args, out: dict, constant: bool, budget: int) -> dict:
        stats = {"steps": int(out["num_accepted_steps"]), "rejected_steps": int(out["num_rejected_steps"]),
                 "attempted_steps": int(out["num_steps"])}
        if self.fsal_stages:  # explicit FSAL Runge-Kutta: the count follows from the steps (docstring)
            stats["rhs_evals"] = (self.fsal_stages - 1) * int(out["num_steps"]) + 1 + (0 if constant else 2)
            stats["jac_evals"] = stats["lu_decompositions"] = 0
            return stats
        if not run.options.get("count_evaluations", False):
            stats["counts_unavailable"] = COUNTS_UNAVAILABLE
            return stats
        # the counting replay: the solve compiled with the counting right-hand side, run again after
        # the timed run (compilation booked as such, the replay as `count_time`, neither as run time)
        fn, counts = run.compiled(_SOLVES, key + ("counting",),
                                  lambda: self._compile(run, constant, budget, args, counting=True))
        t0 = time.perf_counter()
        counts[:] = [0, 0]
        replay = jax_block(fn(*args[:-1], np.float64(np.inf)))
        stats["count_time"] = time.perf_counter() - t0  # not run time (`stamp_wall_time`)
        if int(replay["num_steps"]) != stats["attempted_steps"] or run.time_limit is not None:
            stats["counts_unavailable"] = ("the counting replay did not retrace the run (a time limit stopped it, "
                                           f"or the replay took {int(replay['num_steps'])} steps, not "
                                           f"{stats['attempted_steps']})")
            return stats
        # a Newton iteration linearises f (the residual is the linearisation's value: one evaluation)
        # and factorises the materialised Jacobian by LU
        stats["rhs_evals"] = int(counts[0] + counts[1])
        stats["jac_evals"] = stats["lu_decompositions"] = int(counts[1])
        return stats


def jax_block(out):
    """Wait for a compiled call and for its host callbacks."""
    from models._jax import jax

    out = jax.block_until_ready(out)
    jax.effects_barrier()
    return out


def _result_status(run: Run, result, y_final, t_final: float) -> tuple[Status, str]:
    """The status of a (concrete) diffrax result, and for an event which guard stopped the run."""
    import diffrax as dfx

    if bool(result == dfx.RESULTS.event_occurred):
        if not state_ok(y_final, run.guards.blowup):
            return Status.DIVERGED, blowup_reason(f"the step ending at t = {t_final:.6g}", run.guards.blowup)
        if run.time_limit is not None and run.out_of_time():
            return Status.TIME_LIMIT, run.time_limit_reason(t_final, "; trajectory kept up to the last saved point")
        ell = float(run.model.L - y_final[0])
        return Status.LENGTH_LIMIT, length_reason(run.model, ell, f"at t = {t_final:.6g} s")
    if bool(result == dfx.RESULTS.successful):
        return Status.OK, ""
    statuses = ((dfx.RESULTS.max_steps_reached, Status.MAX_STEPS), (dfx.RESULTS.dt_min_reached, Status.STEP_SIZE_COLLAPSE))
    found = next((s for item, s in statuses if bool(result == item)), Status.FAILED)  # items compare, not hash
    try:
        message = dfx.RESULTS[result]
    except Exception:  # pragma: no cover - depends on the diffrax version
        message = f"diffrax result {result!r}"
    return found, f"{message} (stopped at t = {t_final:.6g})"


class _ExplicitPair(DiffraxODE):
    """An explicit embedded Runge-Kutta pair of diffrax: adaptive with rtol/atol, or a constant step
    with dt alone."""

    capabilities = frozenset({Capability.ADAPTIVE, Capability.FIXED_STEP})


class Tsit5(_ExplicitPair):
    name = "tsit5"
    solver = library_attribute("diffrax", "Tsit5")
    fsal_stages = 7
    order = 5
    description = "diffrax Tsit5: PID-adaptive (rtol/atol) or constant step (dt alone), quaternion attitude"
    horizon_settings = {"rtol": 1e-6, "atol": 1e-8}


class Dopri5(_ExplicitPair):
    name = "dopri5"
    solver = library_attribute("diffrax", "Dopri5")
    fsal_stages = 7
    order = 5
    description = ("diffrax Dopri5: scipy RK45's Dormand-Prince 5(4) tableau, compiled; PID-adaptive or constant "
                   "step, quaternion attitude")
    default_sweep = False  # extended sweep: the compiled twin of rk45's tableau (the default run keeps to ~5 min)


class Dopri8(_ExplicitPair):
    name = "dopri8"
    solver = library_attribute("diffrax", "Dopri8")
    fsal_stages = 14
    order = 8
    description = ("diffrax Dopri8: Prince-Dormand 8(7), compiled (an 8th-order pair like DOP853's, not its "
                   "tableau); PID-adaptive or constant step, quaternion attitude")
    horizon_settings = {"rtol": 1e-8, "atol": 1e-10}
    default_sweep = False  # extended sweep: the compiled twin of dop853's order (the default run keeps to ~5 min)


class Kvaerno5(DiffraxODE):
    name = "kvaerno5"
    solver = library_attribute("diffrax", "Kvaerno5")
    capabilities = frozenset({Capability.ADAPTIVE, Capability.IMPLICIT})
    order = 5
    description = "diffrax Kvaerno5 (implicit ESDIRK 5(4), full Newton), PID-adaptive, quaternion attitude"
    #: extended sweep: an implicit method on a non-stiff problem, 67 s of worker time in the
    #: default sweep (measured); radau represents the implicit ones
    default_sweep = False
    #: measured 2026-11-30 (one core): 0.2 s of stiff_string had not finished after 6 min; its full
    #: Newton re-forms the Jacobian at every iteration
    expensive = "re-forms its Jacobian at every Newton iteration (0.2 s of stiff_string ran over 6 min here)"
    cost_hint = (30.0, 3.0)
    #: ``count_evaluations=True``: count the evaluations and Jacobians in a replay (`COUNTS_UNAVAILABLE`)
    option_names = ("min_step", "count_evaluations")

    def make_solver(self, rtol, atol):
        """Full Newton (Jacobian every iteration): diffrax's default VeryChord (Jacobian frozen
        over the step) failed to converge on about half the steps on the string and the
        controller rejected them (207 accepted / 198 rejected vs 16 / 1 with Newton)."""
        import optimistix as optx

        return self.solver(root_finder=optx.Newton(rtol=NEWTON_TOL_FACTOR * rtol, atol=NEWTON_TOL_FACTOR * atol))
