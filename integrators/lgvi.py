"""Lie group variational integrator (Lee, Leok & McClamroch 2011), on the fixed-step lifecycle.

Discrete state (s_p, q, R ∈ SO(3) as a matrix, discrete momenta p = (p_s, p_q, Π)). Each
step solves the implicit p_k equations for X = (Δs, Δq, c), F = cay(c), R_{k+1} = R_k F,
then evaluates p_{k+1} explicitly (docs/equations.md, "The LGVI step"). The closed-form
equations and the structured solver (tridiagonal string rows + ≤4-unknown Newton in (Δs, c))
live in `integrators._lgvi_core`; the step (Newton, the symmetric scheme's forcing fixed point,
the composition of substeps, the Cayley guard) in `integrators._lgvi_step`. Everything else —
the compiled loop over save slots, the guards, statuses, stats and timing — is the fixed-step
lifecycle's (`integrators.fixed_step`), the same as for every fixed-step method.

The same step runs the symmetric LGVI and its compositions (`integrators.lgvi_sym`): a
`Scheme` selects the discrete Lagrangian (`DiscreteLagrangian(symmetric=...)`) and the substep
coefficients γ_i. With the symmetric scheme and string forces (axial damping) the midpoint
string force is found by a fixed point around the structured solve (see
`DiscreteLagrangian.with_forcing`): it costs more Newton iterations per step (measured N = 4,
c = 0.5 N s: 5.3 vs 1.0 per step at fixed length, 9.2 vs 2.5 on retrieval, at h = 4 ms).

Forcing: (h/2) Q_k at both ends of the step, Q_k = Q_u(t_k) + Q_c(s_k, Δs/h, q_{k,2}); the work
of step k is Q_k Δs and is accumulated in ``Trajectory.work``. The string forces (axial
damping) are explicit (Heun: (h/2) Q at g_k from w_k = M⁻¹ p_k, (h/2) Q at g_{k+1} from the
predicted velocity 2Δx/h − ẋ_k), see `integrators._lgvi_core`; their work ½ (Q⁻ + Q⁺)·Δx is
added to W.

The LGVI saves (x, R, p, W) and turns its saved momenta into velocities with the compiled O(N)
Legendre map (`ClosedFormEOM.velocity_from_momentum`) when it assembles the `Trajectory`.
No JAX at import: the traced parts are imported where they trace.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from reelbench.integrators.base import Capability, Status, Trajectory, check_positive
from reelbench.integrators.fixed_step import FixedStepMethod, StepCode
from reelbench.integrators.lifecycle import CompileCache, ODEProblem, Run
from reelbench.integrators.registry import register

#: Cayley guard: a step whose Cayley parameter has |c| = tan(θ/2) > CAYLEY_BOUND, i.e. rotates
#: the body by θ > 90° in one step, does not resolve the rotation: the run stops there (status
#: "diverged", reason naming the Cayley parameter) instead of going on with a step that Newton
#: may have solved on the wrong branch (|c| → ∞ is a half-turn). A run-time value of the
#: compiled loop (read at every solve), not a constant compiled into it.
CAYLEY_BOUND = 1.0
CAYLEY_CODE = StepCode.define("cayley_bound", Status.DIVERGED, "Cayley parameter blow-up")

#: the compiled Legendre maps w = M⁻¹ p over a save buffer, per (model structure, buffer length)
_VELOCITY = CompileCache(maxsize=32)


@dataclass(frozen=True)
class Scheme:
    """Which LGVI: the discrete Lagrangian (the paper's or the symmetric one) and the composition.

    ``gammas``: substep fractions γ_i of a composition Φ_{γ_m h} ∘ … ∘ Φ_{γ_1 h} of the
    (symmetric) step (Σ γ_i = 1), or None for one step per step.
    """

    symmetric: bool = False
    gammas: tuple | None = None

    @property
    def substeps(self) -> int:
        """Symmetric steps per step (the work of one step is this many LGVI steps)."""
        return len(self.gammas) if self.gammas else 1


SECTION6 = Scheme()


def _momentum_fn(model):
    """Jitted p = M(x, R) w by the O(N) closed form (the initial momentum), the model's numbers
    an argument (one program per model structure)."""
    from reelbench.integrators.rhs import closed_form_of
    from reelbench.models._jax import jax

    return jax.jit(lambda values, x, R, w: closed_form_of(model.bind(values)).momentum(x, R, w))


_MOMENTUM = CompileCache(maxsize=32)


@register
class LGVI(FixedStepMethod):
    name = "lgvi"
    capabilities = frozenset({Capability.FIXED_STEP, Capability.IMPLICIT, Capability.VARIATIONAL,
                              Capability.GROUP_PRESERVING})
    order = 2
    #: measured (tests/test_orders.py): second order at fixed length, first while the length changes
    orders = {"fixed_length": 2, "reel": 1}
    description = "Lie group variational integrator (Lee-Leok-McClamroch 2011): Cayley SO(3), structured Newton"
    cost_hint = (30.0, 0.3)
    uses_rhs = False
    rhs_label = "closed_form"
    #: ``newton_tol``: max |Newton update| of the reduced unknowns (Δs [m], c) to stop;
    #: ``newton_max_iter``: the iteration cap of each solve
    option_defaults = {"newton_tol": 1e-12, "newton_max_iter": 20}
    #: the discrete Lagrangian and composition (subclasses: integrators.lgvi_sym)
    scheme: ClassVar[Scheme] = SECTION6

    def check_options(self, options: dict) -> dict:
        opts = {**self.option_defaults, **options}
        check_positive("newton_tol", opts["newton_tol"])
        it = opts["newton_max_iter"]
        if isinstance(it, bool) or not isinstance(it, (int, np.integer)) or it < 1:
            raise ValueError(f"newton_max_iter = {it!r} is invalid (allowed: an integer >= 1)")
        return {"newton_tol": float(opts["newton_tol"]), "newton_max_iter": int(it)}

    def run_parameters(self, options: dict) -> dict:
        return {"newton_tol": np.float64(options["newton_tol"]), "newton_max_iter": np.int32(options["newton_max_iter"]),
                "cayley_bound": np.float64(CAYLEY_BOUND)}

    def loop_key(self):
        return super().loop_key() + (self.scheme,)

    # -- the step ----------------------------------------------------------------------------
    def initial_state(self, run: Run, ode: ODEProblem):
        """(x0, R0, p0 = M(g0) w0): the initial momentum by the compiled closed form (setup)."""
        x0, R0, w0 = (np.asarray(a, dtype=float) for a in ode.model.initial_state())
        from reelbench.integrators import rhs as _rhs

        momentum = run.compiled(_MOMENTUM, _rhs.structure_of(ode.model), lambda: _momentum_fn(ode.model))
        p0 = run.setup(lambda: np.asarray(momentum(_rhs.device_values(ode.model), x0, R0, w0)))
        return x0, R0, p0

    def init(self, ode: ODEProblem, y0):
        from reelbench.integrators._lgvi_step import lgvi_step

        return lgvi_step(ode.model, self.scheme, CAYLEY_CODE).initial(*y0)

    def step(self, ode: ODEProblem, carry, t, h):
        from reelbench.integrators._lgvi_step import lgvi_step

        return lgvi_step(ode.model, self.scheme, CAYLEY_CODE).step(carry, t, h, ode.params)

    # -- what is saved and how it becomes a Trajectory ---------------------------------------
    def saved(self, ode: ODEProblem, carry):
        x, R, p, _, W, _ = carry
        return x, R, p, W

    def coordinates(self, ode: ODEProblem, saved):
        return saved[0]

    def saved_energy_error(self, ode: ODEProblem, saved, E0):
        from reelbench.integrators._lgvi_step import lgvi_step
        from reelbench.integrators.base import energy_error

        x, R, p, W = saved
        return energy_error(ode.model, x, R, lgvi_step(ode.model, self.scheme, CAYLEY_CODE).dl.legendre(x, R, p), W, E0)

    def trajectory(self, run: Run, ode: ODEProblem, t, saved, n: int) -> Trajectory:
        """Velocities from the saved momenta by the compiled Legendre map (over the whole
        bucketed buffer, so that one compiled map serves every run of that length)."""
        X, Rs, P, Ws = (np.asarray(a) for a in saved)
        n_buf = len(X)
        from reelbench.integrators import rhs as _rhs

        values = _rhs.device_values(ode.model)
        velocity = run.compiled(_VELOCITY, (_rhs.structure_of(ode.model), n_buf),
                                lambda: _velocity_map(ode.model, values, X, Rs, P))
        V = np.asarray(velocity(values, X, Rs, P, np.int32(n)))
        has_attitude = ode.layout.has_attitude
        return Trajectory(t=t, x=X[:n], attitude=Rs[:n] if has_attitude else None, velocity=V[:n], work=Ws[:n],
                          momentum=P[:n], attitude_kind="matrix", scene_name=run.scene.name)

    def failure_reason(self, run: Run, code: int, traj: Trajectory) -> str:
        opts = run.options
        if code == CAYLEY_CODE:
            return (f"Cayley parameter blow-up: |c| > {CAYLEY_BOUND:g}, i.e. the body would rotate by more than "
                    f"{np.degrees(2 * np.arctan(CAYLEY_BOUND)):.0f} degrees in one step (step too large for the spin)")
        if code != StepCode.NEWTON_FAILED:
            return super().failure_reason(run, code, traj)
        words = (f"Newton did not converge within {opts['newton_max_iter']} iterations (tol {opts['newton_tol']:g}) "
                 "or produced a non-finite iterate")
        lay = run.model.layout
        turn = float(run.dt * np.linalg.norm(traj.velocity[-1][lay.omega])) if lay.has_attitude else 0.0
        if turn > 0.5:  # the usual cause with a fast-spinning body, said plainly
            words += (f"; h|Omega| = {turn:.3g} rad at the last kept state: the Cayley step (2 J c/(1+|c|^2) ~ h Pi) "
                      "has no solution beyond about 1 rad per step (a fast spin, or a body spun up by a diverging "
                      "string) - reduce dt")
        return words


def _velocity_map(model, values, X, Rs, P):
    """AOT-compiled w = M⁻¹ p of the first n slots of a save buffer of this length (n a run-time
    argument: one compiled map serves every run of that length, and a run pays only for the slots
    it filled; a vmap over the whole buffer cost ~25 ms per run at N = 640, 256 slots)."""
    from reelbench.integrators.rhs import closed_form_of
    from reelbench.models._jax import jax, jnp

    def velocities(values, X, Rs, P, n):
        velocity = closed_form_of(model.bind(values)).velocity_from_momentum
        V = jnp.zeros((X.shape[0], model.layout.nw), X.dtype)
        return jax.lax.fori_loop(0, n, lambda i, V: V.at[i].set(velocity(X[i], Rs[i], P[i])), V)

    return jax.jit(velocities).lower(values, X, Rs, P, np.int32(0)).compile()
