"""Baselines from `scipy.integrate`: RK45, Radau (Jacobian by forward-mode autodiff) and DOP853 (references).

They integrate the model's continuous equations (models/README.md) on the quaternion ODE state
``y = (x, quat, w, W)`` of `models.layout`, with a jitted right-hand side returning numpy:
the O(N) closed form by default, the autodiff one with ``rhs="autodiff"`` (`integrators.rhs`). The quaternion is *not* renormalised (the drift is part of what is measured), except by
the clearly named ``rk45_projected`` variant, which rescales it to unit norm after every
accepted step.

The adapter drives scipy's ``OdeSolver`` step by step (what ``solve_ivp`` does internally) so
that it can count accepted steps, enforce ``max_steps``, stop on the deployed-length limit
(a root of `StringPendulum.deployed_length_margin` located on the dense output) and stop on a
non-finite or blown-up state, always returning the trajectory up to the last good point.

These classes are registered through the ``reelbench.integrators`` entry-point group (see
pyproject.toml), exactly as an outside plugin is: no ``@register`` here.
"""

from __future__ import annotations

import functools
import time
from typing import Any, ClassVar

import numpy as np
from scipy import integrate as _si
from scipy.optimize import brentq

from integrators import rhs as _rhs
from integrators.base import (Capability, Integrator, Status, Trajectory, check_positive, energy_reason, save_times,
                              stamp_wall_time, build_model_timed)
from integrators.lifecycle import (blowup_reason, check_max_steps, check_options, check_tolerances, energy_guard,
                                   finite_prefix, length_reason, ode_trajectory, resolve_scene, state_ok)



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


# ------------------------------------------------------------------------------------------
# The adapter
# ------------------------------------------------------------------------------------------
#: scipy's public explicit Runge-Kutta solvers: each attempted step costs ``n_stages`` evaluations,
#: so rejected steps follow from the evaluation count (Radau does not expose its rejections).
EXPLICIT_RK = (_si.RK23, _si.RK45, _si.DOP853)


class ScipyIVP(Integrator):
    """One adapter for scipy's ``OdeSolver`` classes; subclasses pick the method."""

    solver_class: ClassVar[type] = _si.RK45
    uses_jacobian: ClassVar[bool] = False
    projected: ClassVar[bool] = False

    def solve(self, scene, t_end=None, *, dt=None, rtol=None, atol=None, save_every=None, max_steps=None,
              rhs=_rhs.DEFAULT_RHS, **options) -> Trajectory:
        """``rhs``: "closed_form" (default, O(N)) or "autodiff" (see `integrators.rhs`)."""
        started = time.perf_counter()  # run time = the whole call minus compilation (issue #11)
        # ---- arguments, all checked before any work ----
        check_options(self.name, options)
        _rhs.check_rhs(rhs)
        scene = resolve_scene(scene)
        t_end = scene.t_end if t_end is None else t_end
        check_positive("t_end", t_end)
        check_tolerances(rtol, atol)
        check_positive("dt", dt, allow_none=True)  # initial step, optional
        check_positive("save_every", save_every, allow_none=True)
        check_max_steps(max_steps)
        t_end = float(t_end)
        settings = {"rtol": rtol, "atol": atol, "dt": dt, "save_every": save_every, "max_steps": max_steps,
                    "t_end": t_end, "method": self.solver_class.__name__, "projected": self.projected, "rhs": rhs}

        model, setup_time = build_model_timed(scene)  # a first build is setup: booked with compile time
        lay = model.layout
        y0 = np.asarray(model.initial_ode_state(), dtype=float)
        t_save = np.minimum(save_times(t_end, save_every), t_end)  # the last one may be t_end + 1 ulp

        # ---- compile (the jitted functions are cached on the model) ----
        tc = time.perf_counter()
        f_jit = _rhs.rhs_jit(model, rhs)
        np.asarray(f_jit(0.0, y0))
        jac = None
        if self.uses_jacobian:
            jac_jit = _rhs.jacobian_jit(model, rhs)
            np.asarray(jac_jit(0.0, y0))
            jac = lambda t, y: np.asarray(jac_jit(float(t), y))  # noqa: E731
        margin = margin_function(model)
        if margin is not None:
            margin(y0)
        e_err, e_bound = energy_guard(model)
        e_err(y0)
        compile_time = time.perf_counter() - tc + setup_time

        # float(t): scipy passes numpy scalars, which would trace a second (strongly typed) version
        fun = lambda t, y: np.asarray(f_jit(float(t), y))  # noqa: E731
        kwargs: dict[str, Any] = {"rtol": rtol, "atol": atol}
        if dt is not None:
            kwargs["first_step"] = min(float(dt), t_end)
        if jac is not None:
            kwargs["jac"] = jac

        # ---- integrate ----
        solver = self.solver_class(fun, 0.0, y0.copy(), t_end, **kwargs)
        out_t, out_y = [0.0], [y0.copy()]
        k = 1  # next saved time
        steps = 0
        status, reason = Status.OK, ""
        event_time = None
        step_sizes = []
        rejected = 0
        counts_attempts = isinstance(solver, EXPLICIT_RK)  # explicit RK: n_stages evals per attempt
        while solver.status == "running":
            if max_steps is not None and steps >= max_steps:
                status, reason = Status.MAX_STEPS, f"max_steps = {max_steps} reached at t = {solver.t:.6g} (t_end = {t_end:g})"
                break
            nfev_before = solver.nfev
            message = solver.step()
            if counts_attempts:
                rejected += max(0, (solver.nfev - nfev_before) // solver.n_stages - 1)
            if solver.status == "failed":
                msg = message or "solver failed"
                status = Status.STEP_SIZE_COLLAPSE if "step size" in msg.lower() else Status.FAILED
                reason = f"{msg} (t = {solver.t:.6g})"
                if not state_ok(solver.y):
                    status = Status.DIVERGED
                break
            steps += 1
            t_old, t_new = solver.t_old, solver.t
            step_sizes.append(t_new - t_old)
            if not state_ok(solver.y):
                status = Status.DIVERGED
                reason = blowup_reason(f"the step ({t_old:.6g}, {t_new:.6g}]")
                break
            t_stop = t_new
            dense = None
            if margin is not None and margin(solver.y) <= 0.0:
                dense = solver.dense_output()
                g = lambda t: margin(dense(t))  # noqa: E731
                try:
                    event_time = brentq(g, t_old, t_new, xtol=1e-13 * max(1.0, t_new)) if g(t_old) > 0 else t_old
                except ValueError:
                    event_time = t_new
                t_stop = event_time
                status = Status.LENGTH_LIMIT
                ell = float(model.L - dense(event_time)[0])
                reason = length_reason(model, ell, f"at t = {event_time:.6g} s")
            while k < len(t_save) and (t_save[k] < t_stop if event_time is not None else t_save[k] <= t_new):
                if t_save[k] == t_new:
                    yk = solver.y.copy()
                else:
                    dense = dense or solver.dense_output()
                    yk = np.asarray(dense(t_save[k]), dtype=float)
                err = e_err(yk)  # energy guard at saved points (issue #7)
                if not err <= e_bound:
                    status = Status.DIVERGED
                    reason = energy_reason(err, e_bound, float(t_save[k]),
                                           f"; trajectory kept up to the previous saved point t = {out_t[-1]:.6g} s")
                    break
                out_t.append(float(t_save[k]))
                out_y.append(yk)
                k += 1
            if event_time is not None or status is Status.DIVERGED:
                break
            if self.projected and lay.has_attitude:
                normalise_quaternion(model, solver.y)
                if hasattr(solver, "f"):
                    solver.f = fun(solver.t, solver.y)  # keep FSAL consistent with the projected state
        y_arr = np.array(out_y)
        n = finite_prefix(y_arr)
        if n < len(y_arr):
            status = Status.DIVERGED
            reason = reason or "non-finite saved state"
        stats = {
            "steps": steps,
            "rhs_evals": int(solver.nfev),
            "jac_evals": int(solver.njev),
            "lu_decompositions": int(solver.nlu),
            "compile_time": compile_time,
            "rhs": rhs,
        }
        if step_sizes:
            stats.update(min_step=float(np.min(step_sizes)), median_step=float(np.median(step_sizes)),
                         max_step=float(np.max(step_sizes)))
        if counts_attempts:  # Radau does not expose its rejections
            stats["rejected_steps"] = int(rejected)
        if event_time is not None:
            stats["event_time"] = float(event_time)
        traj = ode_trajectory(model, scene, np.array(out_t)[:n], y_arr[:n], status=status, reason=reason,
                               stats=stats, integrator=self.name, settings=settings)
        return stamp_wall_time(traj, started)


class RK45(ScipyIVP):
    name = "rk45"
    solver_class = _si.RK45
    capabilities = frozenset({Capability.ADAPTIVE})
    order = 5
    description = "scipy RK45 (Dormand–Prince 5(4)), quaternion attitude, not renormalised"
    horizon_settings = {"rtol": 1e-6, "atol": 1e-8}


class Radau(ScipyIVP):
    name = "radau"
    solver_class = _si.Radau
    uses_jacobian = True
    capabilities = frozenset({Capability.ADAPTIVE, Capability.IMPLICIT})
    order = 5
    description = "scipy Radau IIA (order 5, implicit), Jacobian by jacfwd of the RHS, quaternion attitude"
    #: measured on the shared 2-core machine: 100-115 s of compilation per scene
    cost_hint = (15.0, 1.0)  # its Jacobian (jacfwd of the closed form) compiles in seconds


class DOP853(ScipyIVP):
    name = "dop853"
    solver_class = _si.DOP853
    capabilities = frozenset({Capability.ADAPTIVE})
    order = 8
    description = "scipy DOP853 (Dormand–Prince 8(5,3)), used for reference solutions"
    horizon_settings = {"rtol": 1e-8, "atol": 1e-10}


class RK45Projected(RK45):
    name = "rk45_projected"
    projected = True
    horizon_settings = None
    description = "scipy RK45 with the quaternion rescaled to unit norm after every accepted step"
