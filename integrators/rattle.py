"""RATTLE on unit quaternions: a symplectic method that is not a Lie group method.

Coordinates q = (x, Q): the model's generalised coordinates x (s_p with a reel, then q_2..q_{N+1})
and the body's attitude as a quaternion Q = (w, x, y, z) ∈ ℝ⁴, held on the sphere
g(Q) = (|Q|² − 1)/2 = 0 by a Lagrange multiplier. The Lagrangian is the model's, composed with
R(Q) (`models.model.quat_to_rot`) and the body angular velocity Ω = 2 G(Q) Q̇ (= 2 vec(Q̄ ⊗ Q̇)):

    L(q, q̇) = L_model(x, R(Q), (ẋ, Ω(Q, Q̇))) + 2 J₀ (Q·Q̇)²

No physics is derived again: T and V are the model's (string, reel, rigid body). The last term
is the usual extension: the body's kinetic energy in the quaternion velocity is the 4 × 4 form
2 Q̇ᵀ E(Q)ᵀ diag(J₀, J) E(Q) Q̇ (E(Q) Q̇ = Q̄ ⊗ Q̇), whose first row, J₀, is absent from the
physics because Q·Q̇ = 0 on the constraint's tangent space; it makes ∂²L/∂q̇² regular off that
space, so the momenta p = ∂L/∂q̇ are canonical coordinates on all of ℝ^{nx+4}. J₀ is the mean
principal inertia about the attachment point (`extension_inertia`); any J₀ > 0 gives the same
continuous motion. Since G(Q) Q = 0, p_Q = 2 G(Q)ᵀ Π + 4 J₀ (Q·Q̇) Q, and the hidden
(velocity-level) constraint Q·Q̇ = 0 is the linear condition Q·p_Q = 0.

**The scheme.** The trapezoidal discrete Lagrangian
L_d(q₀, q₁) = (h/2) [L(q₀, (q₁ − q₀)/h) + L(q₁, (q₁ − q₀)/h)], symmetric in time, gives with
the constraint the RATTLE equations (Hairer, Lubich & Wanner, *Geometric Numerical Integration*,
VII.1.4; Marsden & West 2001, §3.5), with forces f = (h/2) F(t_k + h/2, q_{k+½}, Δq/h) at both
ends (discrete Lagrange–d'Alembert; the force at the midpoint with the secant velocity, as the
symmetric LGVI does, so the forced map stays self-adjoint):

    p_k + D₁L_d(q_k, q_{k+1}) + f − (h/2) λ ∇g(q_k) = 0,    g(Q_{k+1}) = 0      (implicit: Newton)
    p_{k+1} = D₂L_d(q_k, q_{k+1}) + f − (h/2) μ ∇g(q_{k+1}),  Q_{k+1}·p_{Q,k+1} = 0  (explicit)

∇g = (0, Q). The second line is a projection of the Q momentum onto the tangent space. The
work of step k is F·Δq. Second order (symmetric and consistent); symplectic on the constraint
manifold {g = 0, Q·p_Q = 0} without forces. The reel needs nothing special: the s_p-dependent
masses are in L, and the Carnot loss and the control moment are forces on s_p (F over q's
layout: the model's generalised force, with its Ω part, if any, mapped by 2 G(Q)ᵀ).

**Solving and cost.** The mass matrix depends on the configuration (R in the body coupling,
s_p with a reel), so the first line is solved by Newton in z = (q_{k+1}, λ), n_z = nx + 5
unknowns, from the quadratic extrapolation of the last three positions. Its Jacobian holds no
stiffness: the potential enters D₁L_d at q_k only, so ∂r/∂q_{k+1} = −(M(q_k) + M(q_{k+1}))/(2h)
+ O(|q̇| ∂M/∂q). Simplified Newton with the structured matrix [−M(q_k)/h, −(h/2)∇g(q_k);
∇g(z)ᵀ, 0] therefore contracts by O(h |q̇| |∂M/∂q| / |M|) per iteration (measured on
fixed_length, N = 10, h = 5 ms: 0.007, 4-5 iterations per step), and each iteration is one
residual (reverse-mode autodiff of the O(N) energies) and one M⁻¹ solve, O(N) by the model's
closed-form Legendre map (`QuaternionSystem.inverse_mass`): the normal direction needs no solve
(M(0, Q) = (0, 4J₀Q)), λ is a scalar Schur complement. So a step costs O(N) (the Newton
iterations times an O(N) residual and solve); no dense matrix is formed or factored. Only where
the neglected O(h|Ω|) terms make it contract slowly (a fast tumble at a large step: measured on
a tumbling N = 3 body at h = 10 ms, |Ω| up to 22 rad/s, where the structured iteration needed
up to 19 iterations) does Newton go on with the exact Jacobian (autodiff, dense solve: O(N³)). The
velocities for the guards and the saved states come from the momenta by the same O(N) map.
The step's derivative is that of the exact discrete map (implicit function theorem,
`jax.lax.custom_root`, a dense solve used only under differentiation), not of the Newton
iterates, so autodiff of a step sees the scheme itself (tests/test_rattle.py checks its
symplecticity that way).

The step is the pure function ``rattle_step(system, state, t, h, tol, maxit) -> (state, code,
iterations)`` of `integrators._rattle_step` (JAX); `Rattle` is its `FixedStepMethod` wiring, and
this module imports no JAX.
"""

from __future__ import annotations

from typing import ClassVar

from reelbench.integrators.base import Capability
from reelbench.integrators.fixed_step import FixedStepMethod, StepResult
from reelbench.integrators.lifecycle import ODEProblem

__all__ = ["Rattle"]


class Rattle(FixedStepMethod):
    """RATTLE on the pendulum (module docstring) on the fixed-step lifecycle: the step reports
    its Newton code and iterations (`StepResult`), so a failed solve ends the run as
    ``newton_failed`` and the iterations reach the run's stats."""

    name = "rattle"
    capabilities = frozenset({Capability.FIXED_STEP, Capability.IMPLICIT, Capability.VARIATIONAL})
    implementation: ClassVar[str] = "jax-compiled"
    order = 2  # at fixed length and while reeling alike (symmetric scheme, midpoint forces)
    #: no fixed count: Newton iterations (each one residual and one O(N) mass solve) per step
    evals_per_step = None
    description = ("RATTLE on unit quaternions: trapezoidal discrete Lagrangian, |Q| = 1 by a multiplier, "
                   "Newton per step; symplectic, not a Lie group method")
    cost_hint = (20.0, 3.0)
    #: its own discrete Euler-Lagrange equations, with the closed form's Legendre map
    uses_rhs = False
    rhs_label = "closed_form"
    #: Newton: the error left in q, relative to max(1, |q|) (`rattle_step`), and the iteration cap
    newton_tol: ClassVar[float] = 1e-14
    newton_max_iter: ClassVar[int] = 20

    def init(self, ode: ODEProblem, y0):
        from reelbench.integrators._rattle_step import initial_state
        from reelbench.models._jax import jnp

        return initial_state(ode.model, jnp.asarray(y0))

    def step(self, ode: ODEProblem, carry, t, h):
        from reelbench.integrators._rattle_step import pendulum_system, rattle_step

        new, code, iterations = rattle_step(pendulum_system(ode.model), carry, t, h, self.newton_tol,
                                            self.newton_max_iter)
        return new, StepResult.of(code, iterations)

    def state(self, ode: ODEProblem, carry):
        from reelbench.integrators._rattle_step import ode_state

        return ode_state(ode.model, carry)
