"""Baselines from `scipy.integrate`: RK45, Radau (Jacobian by forward-mode autodiff) and DOP853 (references).

They integrate the model's continuous equations (models/README.md) on the quaternion ODE state
``y = (x, quat, w, W)`` of `models.layout`, with a jitted right-hand side returning numpy:
the O(N) closed form by default, the autodiff one with ``rhs="autodiff"`` (`integrators.rhs`).
The quaternion is *not* renormalised (the drift is part of what is measured), except by the
clearly named ``rk45_projected`` variant, which rescales it to unit norm after every accepted
step.

The adapter drives scipy's ``OdeSolver`` step by step (what ``solve_ivp`` does internally) so
that it can count accepted steps, keep to ``max_steps`` (default `DEFAULT_MAX_STEPS`) and
``time_limit`` (the clock is read after every step), stop on the deployed-length limit (a root
of `StringPendulum.deployed_length_margin` located on the dense output) and on a non-finite or
blown-up state, and check the energy balance at its saved points, always returning the
trajectory up to the last good point. The prologue and epilogue are the lifecycle's
(`integrators.lifecycle.LibraryAdapter`); this module is only how scipy is called.

These classes are registered through the ``reelbench.integrators`` entry-point group (see
pyproject.toml), exactly as an outside plugin is: no ``@register`` here. Neither scipy's
integrators nor JAX are imported until a run starts.
"""

from __future__ import annotations

import functools
from typing import Any, ClassVar

import numpy as np

from reelbench.integrators import rhs as _rhs
from reelbench.integrators.base import Capability, Status, energy_reason, save_times
from reelbench.integrators.lifecycle import (LibraryAdapter, Outcome, Run, blowup_reason, energy_guard, length_reason,
                                   library_attribute, state_ok)

#: Step budget when ``max_steps`` is not given: far above what any shipped run needs (a DOP853
#: reference at rtol 1e-12 takes ~5,000 steps per 10 s of a paper scene) and an end to a run
#: that would otherwise step for hours (scipy steps at ~1 ms each from Python).
DEFAULT_MAX_STEPS = 1_000_000


# ------------------------------------------------------------------------------------------
# The length-limit event in numpy (the checks of saved states are `integrators.lifecycle`'s)
# ------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=64)
def margin_function(model):
    """Deployed-length margin of an ODE state (None for a fixed-length scene): the same formula
    as `StringPendulum.deployed_length_margin` in numpy, because it runs after every step and a
    jitted call from numpy costs ~30 µs, as much as a right-hand side."""
    if not model.layout.has_reel:
        return None
    i_s = model.layout.y_x.start  # s_p is the first coordinate
    L, lo, hi = float(model.L), float(model.ell_min), float(model.L - model.b)

    def margin(y):
        ell = L - float(y[i_s])
        return min(ell - lo, hi - ell)
    return margin


def normalise_quaternion(model, y: np.ndarray) -> None:
    """In place: rescale the quaternion block of y to unit norm (projected variants only)."""
    sl = model.layout.y_quat
    if model.layout.has_attitude:
        y[sl] /= np.linalg.norm(y[sl])


class _Saver:
    """The saved points of a scipy run: dense output at the saved times, each checked against
    the energy bound (the guard at saved points)."""

    def __init__(self, run: Run, y0: np.ndarray):
        self.t_save = np.minimum(save_times(run.t_end, run.save_every), run.t_end)  # no t_end + 1 ulp
        self.error, self.bound = energy_guard(run.model)
        self.t, self.y, self.k = [0.0], [y0.copy()], 1
        self.reason = ""

    def save_until(self, solver, t_stop: float, inclusive: bool, dense=None) -> bool:
        """Save the points up to ``t_stop``; False when one fails the energy guard."""
        while self.k < len(self.t_save) and (self.t_save[self.k] <= t_stop if inclusive else self.t_save[self.k] < t_stop):
            tk = float(self.t_save[self.k])
            if tk == solver.t:
                yk = solver.y.copy()
            else:
                dense = dense or solver.dense_output()
                yk = np.asarray(dense(tk), dtype=float)
            err = self.error(yk)
            if not err <= self.bound:
                self.reason = energy_reason(err, self.bound, tk,
                                            f"; trajectory kept up to the previous saved point t = {self.t[-1]:.6g} s")
                return False
            self.t.append(tk)
            self.y.append(yk)
            self.k += 1
        return True


# ------------------------------------------------------------------------------------------
# The adapter
# ------------------------------------------------------------------------------------------
class ScipyIVP(LibraryAdapter):
    """One adapter for scipy's ``OdeSolver`` classes; subclasses pick the method."""

    implementation = "scipy-python"
    #: ``dense_output=True``: record every step's interpolant (`Trajectory.dense`, the pieces
    #: (t_old, t, interpolant) in order; the reference's evaluation at any saved time)
    option_names = ("dense_output",)
    solver_class: ClassVar[Any] = library_attribute("scipy.integrate", "RK45")
    uses_jacobian: ClassVar[bool] = False
    projected: ClassVar[bool] = False

    def check_option_values(self, options: dict, mode: str) -> None:
        if not isinstance(options.get("dense_output", False), bool):
            raise ValueError(f"dense_output = {options['dense_output']!r} is invalid (allowed: True or False)")

    def integrate(self, run: Run) -> Outcome:
        model = run.model
        y0 = np.asarray(model.initial_ode_state(), dtype=float)
        fun, jac = run.setup(self._compiled_functions, run, y0)
        solver_class = run.setup(self._library)
        kwargs: dict[str, Any] = {"rtol": run.rtol, "atol": run.atol}
        if run.dt is not None:
            kwargs["first_step"] = run.dt
        if jac is not None:
            kwargs["jac"] = jac
        solver = solver_class(fun, 0.0, y0.copy(), run.t_end, **kwargs)
        budget = run.max_steps if run.max_steps is not None else DEFAULT_MAX_STEPS
        dense = [] if run.options.get("dense_output", False) else None
        out = self._drive(run, solver, fun, _Saver(run, y0), budget, dense)
        out.dense = dense
        out.stats.update(rhs_evals=int(solver.nfev), jac_evals=int(solver.njev), lu_decompositions=int(solver.nlu))
        out.settings.update(max_steps=budget, method=solver_class.__name__, projected=self.projected)
        return out

    def _library(self):
        """The solver class, scipy imported on first use (setup, not run time)."""
        import scipy.optimize  # noqa: F401  (the length event's root find)

        return self.solver_class

    def _compiled_functions(self, run: Run, y0):
        """(f, Jacobian or None) as numpy functions, compiled and called once (setup)."""
        f_jit = _rhs.rhs_jit(run.model, run.rhs)
        np.asarray(f_jit(0.0, y0))
        jac = None
        if self.uses_jacobian:
            jac_jit = _rhs.jacobian_jit(run.model, run.rhs)
            np.asarray(jac_jit(0.0, y0))
            jac = lambda t, y: np.asarray(jac_jit(float(t), y))  # noqa: E731
        energy_guard(run.model)[0](y0)
        # float(t): scipy passes numpy scalars, which would trace a second (strongly typed) version
        return (lambda t, y: np.asarray(f_jit(float(t), y))), jac

    def _drive(self, run: Run, solver, fun, saver: _Saver, budget: int, dense: list | None = None) -> Outcome:
        """Step the solver to the end, a budget, a guard or a failure; save on the way (and
        append each accepted step's interpolant to ``dense`` when it is a list)."""
        from scipy import integrate

        steps, sizes, rejected = 0, [], 0
        # scipy's explicit Runge-Kutta solvers spend n_stages evaluations per attempted step, so
        # rejected steps follow from the evaluation count (Radau does not expose its rejections)
        counts_attempts = isinstance(solver, (integrate.RK23, integrate.RK45, integrate.DOP853))
        status, reason, event_time = Status.OK, "", None
        while solver.status == "running":
            if steps >= budget:
                status, reason = Status.MAX_STEPS, (f"max_steps = {budget} reached at t = {solver.t:.6g} "
                                                    f"(t_end = {run.t_end:g})")
                break
            if run.out_of_time():
                status, reason = Status.TIME_LIMIT, run.time_limit_reason(solver.t)
                break
            nfev = solver.nfev
            message = solver.step()
            if counts_attempts:
                rejected += max(0, (solver.nfev - nfev) // solver.n_stages - 1)
            if solver.status == "failed":
                status, reason = self._failure(solver, message)
                break
            steps += 1
            sizes.append(solver.t - solver.t_old)
            if dense is not None:
                dense.append(solver.dense_output())
            status, reason, event_time = self._after_step(run, solver, fun, saver)
            if status is not Status.OK:
                break
        stats = {"steps": steps}
        if sizes:
            stats.update(min_step=float(np.min(sizes)), median_step=float(np.median(sizes)), max_step=float(np.max(sizes)))
        if counts_attempts:  # Radau does not expose its rejections
            stats["rejected_steps"] = int(rejected)
        if event_time is not None:
            stats["event_time"] = float(event_time)
        return Outcome(t=np.array(saver.t), y=np.array(saver.y), status=status, reason=reason, stats=stats)

    @staticmethod
    def _failure(solver, message) -> tuple[Status, str]:
        msg = message or "solver failed"
        status = Status.STEP_SIZE_COLLAPSE if "step size" in msg.lower() else Status.FAILED
        return (status if state_ok(solver.y) else Status.DIVERGED), f"{msg} (t = {solver.t:.6g})"

    def _after_step(self, run: Run, solver, fun, saver: _Saver):
        """(status, reason, event time) after an accepted step: the state guards, the length
        event (root-found on the dense output), the saved points; the projection last."""
        t_old, t_new = solver.t_old, solver.t
        if not state_ok(solver.y, run.guards.blowup):
            return Status.DIVERGED, blowup_reason(f"the step ({t_old:.6g}, {t_new:.6g}]", run.guards.blowup), None
        margin = margin_function(run.model)
        if margin is not None and margin(solver.y) <= 0.0:
            from scipy.optimize import brentq  # imported in setup (`_library`)

            dense = solver.dense_output()
            g = lambda t: margin(dense(t))  # noqa: E731
            try:
                event_time = brentq(g, t_old, t_new, xtol=1e-13 * max(1.0, t_new)) if g(t_old) > 0 else t_old
            except ValueError:
                event_time = t_new
            if not saver.save_until(solver, event_time, inclusive=False, dense=dense):
                return Status.DIVERGED, saver.reason, None
            ell = float(run.model.L - dense(event_time)[0])
            return Status.LENGTH_LIMIT, length_reason(run.model, ell, f"at t = {event_time:.6g} s"), event_time
        if not saver.save_until(solver, t_new, inclusive=True):
            return Status.DIVERGED, saver.reason, None
        if self.projected and run.model.layout.has_attitude:
            normalise_quaternion(run.model, solver.y)
            if hasattr(solver, "f"):
                solver.f = fun(solver.t, solver.y)  # keep FSAL consistent with the projected state
        return Status.OK, "", None


class RK45(ScipyIVP):
    name = "rk45"
    solver_class = library_attribute("scipy.integrate", "RK45")
    capabilities = frozenset({Capability.ADAPTIVE})
    order = 5
    description = "scipy RK45 (Dormand–Prince 5(4)), quaternion attitude, not renormalised"


class Radau(ScipyIVP):
    name = "radau"
    solver_class = library_attribute("scipy.integrate", "Radau")
    uses_jacobian = True
    capabilities = frozenset({Capability.ADAPTIVE, Capability.IMPLICIT})
    order = 5
    #: Radau IIA (3 stages) has classical order 5 but stage order 3. While reeling, the element
    #: length changes in time and drives the string's stiff axial modes; there a stiff method's
    #: error falls at an order between its stage order and its classical one (order reduction,
    #: Hairer & Wanner, Solving ODEs II, IV.15). `verify` measures 3.67 while reeling (error
    #: against steps, rtol 1e-5..1e-9) and 4.35 at fixed length; 4 is declared for the reel.
    orders = {"reel": 4}
    description = "scipy Radau IIA (order 5, implicit), Jacobian by jacfwd of the RHS, quaternion attitude"
    #: its Jacobian (jacfwd of the closed-form right-hand side) compiles in seconds
    cost_hint = (15.0, 1.0)


class DOP853(ScipyIVP):
    name = "dop853"
    solver_class = library_attribute("scipy.integrate", "DOP853")
    capabilities = frozenset({Capability.ADAPTIVE})
    order = 8
    description = "scipy DOP853 (Dormand–Prince 8(5,3)), used for reference solutions"


class RK45Projected(RK45):
    name = "rk45_projected"
    projected = True
    description = "scipy RK45 with the quaternion rescaled to unit norm after every accepted step"
