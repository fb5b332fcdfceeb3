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

The solve runs diffrax's solvers in this module's own compiled loop (`_Loop`), built from
diffrax's public pieces and mirroring `diffrax.diffeqsolve`'s loop: ``solver.init`` / ``step``,
``PIDController`` (``ConstantStepSize`` with dt alone) ``init`` / ``adapt_step_size``, the same
clip-to-t1 rule, the saved times interpolated by the solver's ``interpolation_cls`` on the step's
dense output, and the event's root find; an adaptive solve given no dt starts, as diffeqsolve
does, with a first step of `DIFFRAX_FIRST_STEP`. Its results equal diffeqsolve's bit for bit
here (tests/test_diffrax_loop.py). One compiled function advances up to K steps (a run-time argument) from the
complete loop state (times, next step size, state, solver and controller states, result, step
counts, next saved slot, saved buffers, the last step's dense output for the root find) and
returns it, so a solve can be cut anywhere and resumed exactly. It is compiled ahead of time and
cached (`CompileCache`, bounded) per (model structure, rhs, solver, step-size mode, first step given
or not, number of saved times): the scene's numbers, the step budget, time limit, tolerances,
horizon, dt and K are run-time values, so the budgeted and timed solves of every setting, and
every scene of the same structure, share one program;
``stats["compile_time"]`` is that compilation (0 when cached) and ``stats["wall_time"]`` the rest
of the ``solve()`` call.

No host callback runs inside a compiled solve: with a ``time_limit`` the host reads the clock
(and `integrators.lifecycle.STOP_REQUESTED`) between chunks (`lifecycle.run_in_chunks`, as for
the fixed-step methods), and the inputs are checked before the solve (`DiffraxODE._arguments`)
instead of by equinox's runtime checks. A budgeted solve equals the unbudgeted one bit for bit
(trajectory, status, counts). The one exception is Kvaerno5's opt-in counting replay
(``count_evaluations=True``, below): a separate program, not a timed solve, whose counting
right-hand side keeps its ``jax.debug.callback``.

Counts: for the explicit FSAL methods ``stats["rhs_evals"]`` follows from the steps: (stages −
1) per attempted step, 1 at the start, and 2 more for the initial step-size guess of an adaptive
run (the PID controller's initial-step heuristic evaluates f at y0 and at y0 + h0 f0). Checked
against a counting right-hand side in tests/test_rhs.py: exact with a constant step; adaptive,
the executed count is up to 2 lower: diffeqsolve, and this loop with it, starts from
`DIFFRAX_FIRST_STEP` without that heuristic (the 2 stay in the rule, so that recorded counts
keep their meaning). Kvaerno5's Newton iterations are not
exposed by diffrax, and counting them inside the compiled solve takes a host callback per
evaluation (~0.1 ms each here, several times a Newton iteration at small N): so a plain run
says ``stats["counts_unavailable"]`` (why, in words), and ``solve(..., count_evaluations=True)``
replays the run with a counting right-hand side (`_counting`, compiled once more; the replay's
seconds are ``stats["count_time"]``, not run time). Its full Newton linearises f at every
iteration (the residual is the linearisation's value) and factorises the materialised Jacobian
by LU: ``rhs_evals`` = evaluations + linearisations, ``jac_evals`` = ``lu_decompositions`` =
linearisations (measured N = 2, rtol 1e-6: 16 per step, none outside Newton).

Failures never raise; diffrax's result is mapped to a status: ``max_steps_reached`` (the
budget spent before t_end) -> "max_steps", ``dt_min_reached`` -> "step_size_collapse" (the PID
controller gets ``dtmin = min_step``, default 1e-12 t_end, with ``force_dtmin=False``), other
errors -> "failed" with diffrax's message. Two event conditions, checked after every step as
diffrax's `Event` does, stop the run: a non-finite or blown-up state ("diverged") and, with a
reel, the deployed length leaving (ℓ_min, L - b) ("length_limit", at the crossing found by a
root find on the step's dense output, like scipy's events). A ``time_limit`` spent (or a stop
asked for) between chunks ends it as "time_limit". The energy balance is checked at the saved
points (computed inside the compiled loop as each is saved); the trajectory is kept up to the
last saved point before any of these.

The quaternion is not renormalised. No ``@register``: found through the entry-point group.
"""

from __future__ import annotations

import time
from typing import Any, ClassVar, NamedTuple

import numpy as np

from reelbench.integrators import rhs as _rhs
from reelbench.integrators.base import Capability, Status, energy_reason, fixed_step_grid, save_times
from reelbench.integrators.lifecycle import (CompileCache, LibraryAdapter, Outcome, Run, blowup_reason, length_reason,
                                   library_attribute, run_in_chunks, state_ok)

#: Default step budget (diffrax's own default, 4096, is too small for tight tolerances here).
DEFAULT_MAX_STEPS = 100_000
#: Default minimum step for the PID controller, relative to t_end: below it -> step_size_collapse.
DEFAULT_MIN_STEP_REL = 1e-12
#: Kvaerno5's Newton tolerances, relative to the step-size controller's rtol/atol.
NEWTON_TOL_FACTOR = 1e-2
#: the first step of an adaptive solve given no dt (s): `diffrax.diffeqsolve`'s, whose initial-step
#: heuristic (`PIDController.init`) applies to a bare ODETerm only, and it wraps every term
DIFFRAX_FIRST_STEP = 0.01
#: tolerances of the event time's root find (s; the margin is in m and moves at ~m/s)
EVENT_TIME_TOL = 1e-10

_SOLVES = CompileCache(maxsize=16)

#: Why Kvaerno5 reports no counts by default (``solve(..., count_evaluations=True)`` counts them)
COUNTS_UNAVAILABLE = ("diffrax does not expose Kvaerno5's Newton iterations; solve(..., count_evaluations=True) "
                      "counts its evaluations and Jacobians in a replay of the run with host callbacks inside the "
                      "compiled solve (one more compilation, and a replay several times the run: measured N = 4, "
                      "157 steps, 2,600 linearisations: 1.5 s against 0.25 s)")


class _State(NamedTuple):
    """The complete state of the step loop between two chunks (diffrax's loop state, less what
    our solves leave unused: ``made_jump`` stays a static False, as in diffrax for controllers
    without jump times; no dense or step saving)."""

    tprev: Any
    tnext: Any
    y: Any
    solver_state: Any
    controller_state: Any
    result: Any  # a diffrax RESULTS item
    num_steps: Any
    num_accepted_steps: Any
    num_rejected_steps: Any
    save_index: Any  # the next saved time to write (diffrax's saveat_ts_index = save_index)
    ts: Any  # saved times, inf where not yet written
    ys: Any  # saved states
    errs: Any  # |E - W - E0| at the saved states
    event_tprev: Any  # the last step's interval and dense output (the event's root find)
    event_tnext: Any
    event_dense_info: Any
    event_values: Any  # (guard, margin): the conditions' values after the last step
    event_mask: Any  # (guard, margin): which condition fired


class _Loop:
    """The chunk of a solve: `advance` (state, fresh, y0, t1, ts, rtol, atol, dt0, min_step, E0,
    blowup, k_stop) -> (state, final): from ``state`` (or from y0 when ``fresh``), take steps
    until t1, a result other than success (an event, dt_min, a failed solve) or ``k_stop``
    attempted steps. ``final`` = (t, y, result) where the solve stands: at an event, the root
    find's crossing on the last step's dense output, as `diffrax.diffeqsolve` does. `initial`
    (the same arguments less state, fresh and k_stop) is the state a fresh call starts from.

    The loop is diffrax's (``diffrax._integrate.loop``, 0.7) with our two conditions for its
    `Event`: ``solver.step``, NaN errors made inf, ``controller.adapt_step_size``, the
    clip-to-t1 rule (t1 minus 100 ulps), the saved times by ``solver.interpolation_cls`` on the
    step's ``dense_info``, then the conditions at the new (tprev, y)."""

    def __init__(self, model, rhs: str, counts, solver_of, constant: bool, dt0_given: bool, n_save: int):
        self.model, self.lay, self.reel = model, model.layout, model.layout.has_reel
        self.rhs, self.counts, self.term = rhs, counts, None
        self.solver_of, self.constant, self.dt0_given, self.n_save = solver_of, constant, dt0_given, n_save

    def on(self, values) -> "_Loop":
        """This loop on the model bound to ``values`` (traced: the scene's numbers are arguments
        of the compiled solve, not constants), with its right-hand side as a diffrax term."""
        import copy

        import diffrax as dfx


        loop = copy.copy(self)
        loop.model = _rhs.prepare(self.model.bind(values))
        f = _rhs.ode_rhs(loop.model, self.rhs)
        if self.counts is not None:
            f = _counting(f, self.counts)
        loop.term = dfx.ODETerm(lambda t, y, args: f(t, y))
        return loop

    def conditions(self, y, blowup):
        """(guard, margin): a non-finite / blown-up state (bool) and, with a reel, the deployed
        length's margin (its sign change is the event; 1.0 without a reel)."""
        from reelbench.models._jax import jnp

        bad = ~jnp.all(jnp.isfinite(y)) | (jnp.max(jnp.abs(y)) >= blowup)
        margin = self.model.deployed_length_margin(y[self.lay.y_x]) if self.reel else jnp.ones((), y.dtype)
        return bad, margin

    def pieces(self, rtol, atol, min_step):
        """(solver, step-size controller) with this run's tolerances (traced)."""
        import diffrax as dfx

        if self.constant:
            controller = dfx.ConstantStepSize()
        else:
            controller = dfx.PIDController(rtol=rtol, atol=atol, dtmin=min_step, force_dtmin=False)
        return self.solver_of(rtol, atol), controller

    def initial(self, values, y0, t1, ts, rtol, atol, dt0, min_step, E0, blowup):
        return self.on(values).start_with(y0, t1, ts, rtol, atol, dt0, min_step, E0, blowup)

    def start_with(self, y0, t1, ts, rtol, atol, dt0, min_step, E0, blowup):
        return self.start(y0, t1, dt0, blowup, *self.pieces(rtol, atol, min_step))

    def start(self, y0, t1, dt0, blowup, solver, controller):
        import diffrax as dfx

        from reelbench.models._jax import jax, jnp

        RESULTS, term = dfx.RESULTS, self.term
        t0 = jnp.zeros((), t1.dtype)
        # diffeqsolve's first step when none is given: its initial-step heuristic applies to a bare
        # ODETerm only, and diffeqsolve wraps every term (its time direction), so it starts at 0.01
        first = dt0 if self.dt0_given else jnp.asarray(DIFFRAX_FIRST_STEP, t1.dtype)
        tnext, controller_state = controller.init(term, t0, t1, y0, first, None, solver.func, solver.error_order(term))
        tnext = jnp.minimum(tnext, t1)
        solver_state = solver.init(term, t0, tnext, y0, None)
        _, _, info_struct, _, _ = jax.eval_shape(lambda: solver.step(term, t0, tnext, y0, None, solver_state, False))
        bad, margin = self.conditions(y0, blowup)
        i0, n = jnp.zeros((), jnp.int32), self.n_save
        return _State(
            tprev=t0, tnext=tnext, y=y0, solver_state=solver_state,
            controller_state=jax.tree_util.tree_map(jnp.asarray, controller_state),
            result=RESULTS.where(bad, RESULTS.event_occurred, RESULTS.successful),
            num_steps=i0, num_accepted_steps=i0, num_rejected_steps=i0, save_index=i0,
            ts=jnp.full(n, jnp.inf, t1.dtype), ys=jnp.full((n,) + y0.shape, jnp.inf, y0.dtype),
            errs=jnp.full(n, jnp.inf, y0.dtype), event_tprev=t0, event_tnext=t0,
            event_dense_info=jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), info_struct),
            event_values=(bad, margin), event_mask=(bad, jnp.zeros((), bool)))

    def advance(self, values, state, fresh, *args):
        return self.on(values).advance_bound(state, fresh, *args)

    def advance_bound(self, state, fresh, y0, t1, ts, rtol, atol, dt0, min_step, E0, blowup, k_stop):
        import diffrax as dfx
        import equinox.internal as eqxi

        from reelbench.models._jax import jax

        solver, controller = self.pieces(rtol, atol, min_step)
        state = jax.lax.cond(fresh, lambda s: self.start(y0, t1, dt0, blowup, solver, controller), lambda s: s, state)
        t1_clip_floor = t1
        for _ in range(100):
            t1_clip_floor = eqxi.prevbefore(t1_clip_floor)

        def cond(s):
            return (s.tprev < t1) & (s.result == dfx.RESULTS.successful) & (s.num_steps < k_stop)

        def body(s):
            return self.step(s, solver, controller, t1, t1_clip_floor, ts, E0, blowup)

        s = jax.lax.while_loop(cond, body, state)
        return s, self.final(s, solver)

    def step(self, s, solver, controller, t1, t1_clip_floor, ts, E0, blowup):
        """One attempted step of diffrax's loop body, its saved times and the conditions."""
        import diffrax as dfx

        from reelbench.models._jax import jax, jnp

        RESULTS = dfx.RESULTS
        y, y_error, dense_info, solver_state, solver_result = solver.step(self.term, s.tprev, s.tnext, s.y, None,
                                                                          s.solver_state, False)
        y_error = jnp.where(jnp.isnan(y_error), jnp.inf, y_error)
        keep_step, tprev, tnext, made_jump, controller_state, controller_result = controller.adapt_step_size(
            s.tprev, s.tnext, s.y, y, None, y_error, solver.error_order(self.term), s.controller_state)
        assert made_jump is False  # no jump times: diffrax keeps it a static False too
        tprev = jnp.minimum(tprev, t1)
        tnext = jnp.where(tnext > t1_clip_floor, jnp.where(keep_step, t1, tprev + 0.5 * (t1 - tprev)), tnext)
        keep = lambda a, b: jnp.where(keep_step, a, b)  # noqa: E731
        y = keep(y, s.y)
        solver_state = jax.tree_util.tree_map(keep, solver_state, s.solver_state)
        solver_result = RESULTS.where(keep_step, solver_result, RESULTS.successful)
        okay = (s.result == RESULTS.successful) | (s.result == RESULTS.event_occurred)
        result = RESULTS.where(okay, solver_result, s.result)
        okay = (result == RESULTS.successful) | (result == RESULTS.event_occurred)
        result = RESULTS.where(okay, controller_result, result)
        num_accepted = s.num_accepted_steps + jnp.where(keep_step, 1, 0)
        num_rejected = s.num_rejected_steps + jnp.where(keep_step, 0, 1)
        saved = self.save(s, keep_step, solver.interpolation_cls(t0=s.tprev, t1=s.tnext, **dense_info), ts, E0)
        bad, margin = self.conditions(y, blowup)
        fired = (jnp.sign(s.event_values[1]) != jnp.sign(margin)) if self.reel else jnp.zeros((), bool)
        mask = (bad, fired & ~bad)
        result = RESULTS.where(mask[0] | mask[1], RESULTS.event_occurred, result)
        return _State(tprev, tnext, y, solver_state, controller_state, result, s.num_steps + 1, num_accepted,
                      num_rejected, *saved, s.tprev, s.tnext, dense_info, (bad, margin), mask)

    def save(self, s, keep_step, interpolator, ts, E0):
        """(next slot, ts, ys, energy errors): the saved times the accepted step passed."""
        from reelbench.integrators.base import energy_error_ode
        from reelbench.models._jax import jax

        def save_cond(c):
            j = c[0]
            return keep_step & (ts[j] <= s.tnext) & (j < self.n_save)

        def save_body(c):
            j, ts_buf, ys_buf, errs_buf = c
            t = ts[j]
            y_t = interpolator.evaluate(t)
            return (j + 1, ts_buf.at[j].set(t), ys_buf.at[j].set(y_t),
                    errs_buf.at[j].set(energy_error_ode(self.model, y_t, E0)))

        return jax.lax.while_loop(save_cond, save_body, (s.save_index, s.ts, s.ys, s.errs))

    def final(self, s, solver):
        """(t, y, result) where the solve stands: diffrax's root find for a fired condition."""
        import diffrax as dfx
        import optimistix as optx

        from reelbench.models._jax import jax, jnp

        lax, RESULTS = jax.lax, dfx.RESULTS
        if not self.reel:  # no root finder (diffrax's ``Event(root_finder=None)``): where the loop stopped
            return s.tprev, s.y, s.result
        happened = s.event_mask[0] | s.event_mask[1]
        root_finder = optx.Newton(rtol=EVENT_TIME_TOL, atol=EVENT_TIME_TOL)

        def root_find():
            interpolator = solver.interpolation_cls(t0=s.event_tprev, t1=s.event_tnext, **s.event_dense_info)

            def distance(t, _):
                from_end = s.event_tnext - t
                zero = jnp.zeros_like(from_end)
                # a boolean condition has its root at the end of the last step; the margin its own
                guard_value = lax.cond(s.event_mask[0], lambda: from_end, lambda: zero)
                margin_value = lax.cond(s.event_mask[1], lambda: self.model.deployed_length_margin(
                    interpolator.evaluate(t)[self.lay.y_x]).astype(from_end.dtype), lambda: zero)
                return (jnp.where(happened, guard_value, from_end), jnp.where(happened, margin_value, from_end))

            found = optx.root_find(distance, root_finder, y0=s.event_tnext,
                                   options={"lower": s.event_tprev, "upper": s.event_tnext}, throw=False)
            t = found.value
            y = lax.cond(s.num_steps == 0, lambda: s.y, lambda: interpolator.evaluate(t))
            result = RESULTS.where(found.result == optx.RESULTS.successful, s.result, RESULTS.promote(found.result))
            return t, y, result

        return lax.cond(happened, root_find, lambda: (s.tprev, s.y, s.result))


def _counting(f, counts: list):
    """``f`` counting its evaluations (counts[0]) and linearisations (counts[1], the Jacobians of
    a Newton iteration) with host callbacks inside the compiled code (Kvaerno5: diffrax does not
    expose the counts)."""
    from reelbench.models._jax import jax

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
        constant = run.mode == "fixed"
        min_step = self._min_step(run, constant)
        t_save, t1, budget = self._grid(run, constant)
        args = self._arguments(run, t_save, t1, min_step)
        # one program per method, model, rhs, step-size mode and number of saved times: the budget,
        # the time limit, tolerances, dt and horizon are run-time values
        key = (_rhs.structure_of(run.model), run.rhs, type(self), constant, run.dt is not None, len(t_save))
        prog = run.compiled(_SOLVES, key, lambda: self._compile(run, constant, args, counting=False))
        out, timed_out = _solve(run, prog, args, int(budget), timed=run.time_limit is not None)
        result = self._ending(run, out, timed_out)
        result.stats.update(self._counts(run, key, args, out, constant, int(budget)))
        result.settings.update(max_steps=budget, step_size="constant" if constant else "pid",
                               min_step=None if constant else min_step)
        return result

    def check_option_values(self, options: dict, mode: str) -> None:
        from reelbench.integrators.base import check_positive

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
        """The compiled solve's run-time arguments (y0, t1, saved times, rtol, atol, dt0,
        min_step, E0, blow-up bound), checked here as diffrax's `diffeqsolve` would check them at
        run time (saved times increasing inside [0, t1], dt0 > 0): the compiled loop has no
        runtime checks (no host callbacks)."""
        g = run.guards
        f64 = np.float64
        t_save = np.asarray(t_save, dtype=float)
        if not (np.isfinite(t1) and t1 > 0 and np.all(np.diff(t_save) >= 0) and t_save[0] >= 0
                and t_save[-1] <= t1):  # pragma: no cover - the grid is ours (`_grid`)
            raise ValueError(f"saved times must increase inside [0, t1 = {t1!r}]")
        if run.dt is not None and not (np.isfinite(run.dt) and run.dt > 0):  # pragma: no cover - start_run checks it
            raise ValueError(f"dt = {run.dt!r} is invalid (allowed: a finite number > 0)")
        return (np.asarray(run.model.initial_ode_state(), dtype=float), f64(t1), t_save, f64(run.rtol or 0.0),
                f64(run.atol or 0.0), f64(run.dt if run.dt is not None else 0.0), f64(min_step or 0.0), f64(g.E0),
                f64(g.blowup))

    def _compile(self, run: Run, constant: bool, args, counting: bool) -> "_Program":
        """The chunk of the solve (`_Loop.advance`), compiled ahead of time for these argument
        shapes, with the zero state its first (fresh) call passes and, when ``counting``, the
        list its counting callbacks add to."""
        from reelbench.models._jax import jax, jnp

        counts = [0, 0] if counting else None
        loop = _Loop(run.model, run.rhs, counts, self.make_solver, constant, run.dt is not None, len(args[2]))
        values = _rhs.device_values(run.model)
        shape = jax.eval_shape(loop.initial, values, *args)
        zero = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shape)
        fn = jax.jit(loop.advance).lower(values, zero, np.bool_(True), *args, np.int32(0)).compile()
        return _Program(fn, zero, counts)

    def _ending(self, run: Run, out: dict, timed_out: bool) -> Outcome:
        """The saved points the solve reached and how it ended (event, result, budgets, energy guard)."""
        n = int(out["save_index"])
        ts, ys, errs = (np.asarray(out[k], dtype=float)[:n] for k in ("ts", "ys", "errs"))
        t_final, y_final = float(out["t_final"]), np.asarray(out["y_final"], dtype=float)
        before = ts <= t_final  # as diffrax does: nothing saved after an event's crossing
        ts, ys, errs = ts[before], ys[before], errs[before]
        once = np.r_[True, np.diff(ts) > 0] if len(ts) else np.ones(0, bool)  # a repeated t_end saved once
        ts, ys, errs = ts[once], ys[once], errs[once]
        if len(ts) == 0:  # stopped before the first saved time after 0: keep the initial state
            ts, ys, errs = np.zeros(1), np.asarray(run.model.initial_ode_state(), dtype=float)[None, :], np.zeros(1)
        status, reason = _result_status(run, out, y_final, t_final, timed_out)
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
        if out["timed_out"]:
            stats["counts_unavailable"] = ("the run stopped on its time limit: a counting replay would run past "
                                           "where it stopped")
            return stats
        prog = run.compiled(_SOLVES, key + ("counting",), lambda: self._compile(run, constant, args, counting=True))
        t0 = time.perf_counter()
        prog.counts[:] = [0, 0]
        replay, _ = _solve(run, prog, args, budget, timed=False)
        jax_block(replay["t_final"])
        stats["count_time"] = time.perf_counter() - t0  # not run time (`stamp_wall_time`)
        if int(replay["num_steps"]) != stats["attempted_steps"]:  # pragma: no cover - the same program but f
            stats["counts_unavailable"] = (f"the counting replay did not retrace the run (it took "
                                           f"{int(replay['num_steps'])} steps, not {stats['attempted_steps']})")
            return stats
        counts = prog.counts
        # a Newton iteration linearises f (the residual is the linearisation's value: one evaluation)
        # and factorises the materialised Jacobian by LU
        stats["rhs_evals"] = int(counts[0] + counts[1])
        stats["jac_evals"] = stats["lu_decompositions"] = int(counts[1])
        return stats


class _Program(NamedTuple):
    """A compiled chunk of a solve, the zero state its fresh call passes, and the counting list of
    a counting replay (else None)."""

    fn: Any
    zero: Any
    counts: list | None


def _solve(run: Run, prog: _Program, args, budget: int, timed: bool) -> tuple[dict, bool]:
    """Run the compiled solve from the start: one call, or with ``timed`` chunks of steps with the
    clock read between them (`run_in_chunks`, as the fixed-step methods are run). Every chunk
    continues from the complete loop state, so the result is the same bit for bit however the
    run is cut. Returns (the final state and where the solve stands, on the host; whether the
    time limit stopped it)."""
    import diffrax as dfx

    from reelbench.models._jax import jax


    successful = int(dfx.RESULTS.successful._value)
    t1 = float(args[1])
    values = _rhs.device_values(run.model)
    box = {"state": prog.zero, "fresh": np.bool_(True), "steps": 0, "final": None}

    def advance(chunk: int) -> tuple[int, bool]:
        k_stop = np.int32(min(budget, box["steps"] + chunk))
        state, final = prog.fn(values, box["state"], box["fresh"], *args, k_stop)
        steps, tprev, result = jax.device_get((state.num_steps, state.tprev, state.result._value))
        done = int(steps) - box["steps"]
        box.update(state=state, fresh=np.bool_(False), steps=int(steps), final=final)
        return done, bool(int(result) != successful or float(tprev) >= t1 or int(steps) >= budget)

    if timed:
        timed_out = run_in_chunks(run, advance, budget)
    else:  # one call: it ends the solve (the budget is its chunk)
        advance(budget)
        timed_out = False
    state, (t_final, y_final, result) = jax.device_get((box["state"], box["final"]))
    out = {"ts": state.ts, "ys": state.ys, "errs": state.errs, "save_index": state.save_index,
           "num_steps": state.num_steps, "num_accepted_steps": state.num_accepted_steps,
           "num_rejected_steps": state.num_rejected_steps, "t_final": t_final, "y_final": y_final,
           "result": int(result._value) if hasattr(result, "_value") else int(result),
           "max_steps": int(state.num_steps) >= budget and float(state.tprev) < t1
           and int(state.result._value) == successful, "timed_out": timed_out}
    return out, timed_out


def jax_block(out):
    """Wait for a compiled call and for its host callbacks."""
    from reelbench.models._jax import jax

    out = jax.block_until_ready(out)
    jax.effects_barrier()
    return out


def _result_status(run: Run, out: dict, y_final, t_final: float, timed_out: bool) -> tuple[Status, str]:
    """The status of a finished solve (diffrax's result code, the budgets), and for an event which
    condition stopped it."""
    import diffrax as dfx

    code = out["result"]

    def item(r):
        return int(r._value)

    if timed_out:
        return Status.TIME_LIMIT, run.time_limit_reason(t_final, "; trajectory kept up to the last saved point")
    if out["max_steps"]:
        code = item(dfx.RESULTS.max_steps_reached)
    if code == item(dfx.RESULTS.event_occurred):
        if not state_ok(y_final, run.guards.blowup):
            return Status.DIVERGED, blowup_reason(f"the step ending at t = {t_final:.6g}", run.guards.blowup)
        ell = float(run.model.L - y_final[0])
        return Status.LENGTH_LIMIT, length_reason(run.model, ell, f"at t = {t_final:.6g} s")
    if code == item(dfx.RESULTS.successful):
        return Status.OK, ""
    statuses = ((dfx.RESULTS.max_steps_reached, Status.MAX_STEPS), (dfx.RESULTS.dt_min_reached, Status.STEP_SIZE_COLLAPSE))
    found = next((s for r, s in statuses if code == item(r)), Status.FAILED)
    try:
        message = next(dfx.RESULTS[r] for r in _results() if item(r) == code)
    except Exception:  # pragma: no cover - depends on the diffrax version
        message = f"diffrax result {code!r}"
    return found, f"{message} (stopped at t = {t_final:.6g})"


def _results():
    import diffrax as dfx

    return list(dfx.RESULTS._name_to_item.values())


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


class Dopri5(_ExplicitPair):
    name = "dopri5"
    solver = library_attribute("diffrax", "Dopri5")
    fsal_stages = 7
    order = 5
    description = ("diffrax Dopri5: scipy RK45's Dormand-Prince 5(4) tableau, compiled; PID-adaptive or constant "
                   "step, quaternion attitude")


class Dopri8(_ExplicitPair):
    name = "dopri8"
    solver = library_attribute("diffrax", "Dopri8")
    fsal_stages = 14
    order = 8
    description = ("diffrax Dopri8: Prince-Dormand 8(7), compiled (an 8th-order pair like DOP853's, not its "
                   "tableau); PID-adaptive or constant step, quaternion attitude")


class Kvaerno5(DiffraxODE):
    name = "kvaerno5"
    solver = library_attribute("diffrax", "Kvaerno5")
    capabilities = frozenset({Capability.ADAPTIVE, Capability.IMPLICIT})
    order = 5
    description = "diffrax Kvaerno5 (implicit ESDIRK 5(4), full Newton), PID-adaptive, quaternion attitude"
    cost_hint = (30.0, 3.0)
    #: ``count_evaluations=True``: count the evaluations and Jacobians in a replay (`COUNTS_UNAVAILABLE`)
    option_names = ("min_step", "count_evaluations")

    def make_solver(self, rtol, atol):
        """Full Newton (Jacobian every iteration): diffrax's default VeryChord (Jacobian frozen
        over the step) failed to converge on about half the steps on the string and the
        controller rejected them (207 accepted / 198 rejected vs 16 / 1 with Newton)."""
        import optimistix as optx

        return self.solver(root_finder=optx.Newton(rtol=NEWTON_TOL_FACTOR * rtol, atol=NEWTON_TOL_FACTOR * atol))
