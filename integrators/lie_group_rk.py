"""Lie group Runge–Kutta methods on SO(3) × ℝⁿ: a group-preserving method that is not symplectic.

The state is (R, v): the attitude R ∈ SO(3) as a rotation matrix and everything else
v = (x, w, W) ∈ ℝⁿ as a vector space (generalised coordinates, velocities, accumulated work).
A vector field gives, at (t, R, v), the body angular velocity Ω (Ṙ = R Ω̂) and v̇. The attitude
is only ever multiplied by exponentials of body-frame increments (Rodrigues' formula,
`so3_exp`), so R stays orthogonal to round-off; nothing else is preserved (energy is not: the
methods are not symplectic). The steps (`rkmk4_step`, `crouch_grossman3_step`) are generic over
the vector field, so the tests drive them with a free rigid body as well as with the pendulum.

Driving the pendulum (`pendulum_field`): Ω is the Ω slot of w, v̇ = (ẋ = w_x, ẇ = the closed-form
accelerations `models.closed_form.ClosedFormEOM.accelerations(t, x, R, w)` (O(N); the autodiff
model's with ``rhs="autodiff"``), Ẇ = Q·w), evaluated at a rotation matrix.

**RKMK4** (Munthe-Kaas 1999; Hairer–Lubich–Wanner, *Geometric Numerical Integration*, IV.8.2):
classical RK4 on the Lie algebra coordinates u of R = R_0 exp(û), with the dexp⁻¹ series
truncated at what order 4 needs and reduced to two commutators::

    k1 = h Ω(R0),                     l1 = h v̇(...)            (and likewise l2..l4 on ℝⁿ)
    k2 = h Ω(R0 exp(k1/2))
    k3 = h Ω(R0 exp(k2/2 + k1 × k2 / 8))
    k4 = h Ω(R0 exp(k3))
    R1 = R0 exp((k1 + 2k2 + 2k3 + k4)/6 + k1 × k4 / 12),   v1 = v0 + (l1 + 2l2 + 2l3 + l4)/6

(the commutators [a, b] of so(3) are cross products; their sign is that of the right action
Ṙ = R Ω̂). On ℝⁿ every commutator vanishes and the method is classical RK4.

Why RKMK4 rather than the commutator-free CF4 of Celledoni, Marthinsen & Owren (2003): both take
four field evaluations per step, which is where the cost is (each an O(N) closed-form solve).
CF4 avoids commutators at the price of composing exponentials: its fourth stage and its update
each need two, six in all; RKMK4 needs four exponentials and two commutators. Commutators are
what makes RKMK expensive on large matrix groups, but in so(3) a commutator is a cross product
(9 flops), cheaper than an exponential (a sine, a cosine and a 3 × 3 product), so RKMK4 is the
cheaper of the two here and no less accurate.

**Crouch–Grossman 3** (Crouch & Grossman 1993; coefficients of Owren & Marthinsen 1999): three
stages, each a product of exponentials of frozen fields (no commutators, no dexp⁻¹), six
exponentials and three field evaluations per step::

    c = (0, 3/4, 17/24),  a21 = 3/4,  a31 = 119/216,  a32 = 17/108,  b = (13/51, −2/3, 24/17)
    R_i = R0 exp(h a_i1 Ω1) ⋯ exp(h a_i,i−1 Ω_{i−1}),   R1 = R0 exp(h b1 Ω1) exp(h b2 Ω2) exp(h b3 Ω3)

The steps are pure functions of `integrators._lie_group_steps` (JAX), ``step(field, (R, v), t, h)
-> (R1, v1)``: explicit, so they report nothing but the new state (the lifecycle's guards judge it).
`LieRK4` / `CrouchGrossman3` are their `FixedStepMethod` wiring; this module imports no JAX.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from reelbench.integrators.base import Capability, Trajectory
from reelbench.integrators.fixed_step import FixedStepMethod
from reelbench.integrators.lifecycle import ODEProblem, Run

__all__ = ["CrouchGrossman3", "LieRK4"]


class _LieGroupMethod(FixedStepMethod):
    """The wiring of a Lie group step on the fixed-step lifecycle.

    The carry is (R, v), and it is what the lifecycle saves and guards: the saved attitude is the
    carried rotation matrix itself, so the orthogonality error in the results is the method's own
    (no conversion to a quaternion in between)."""

    capabilities = frozenset({Capability.FIXED_STEP, Capability.GROUP_PRESERVING})
    implementation: ClassVar[str] = "jax-compiled"
    #: the pure step's name in `integrators._lie_group_steps`, (field, (R, v), t, h) -> (R, v)
    lie_step: ClassVar[str]
    #: comparable to the LGVI's 5 ms in the long-horizon energy study (h ω_max ≈ 1.1 on
    #: fixed_length at N = 10, inside the explicit methods' stability intervals)
    cost_hint = (20.0, 1.0)

    def init(self, ode: ODEProblem, y0):
        from reelbench.integrators._lie_group_steps import split_ode_state
        from reelbench.models._jax import jnp

        return split_ode_state(ode.layout, jnp.asarray(y0))

    def step(self, ode: ODEProblem, carry, t, h):
        from reelbench.integrators import _lie_group_steps as steps

        field = steps.pendulum_field(ode.model, steps.equations_of(ode))
        return getattr(steps, self.lie_step)(field, carry, t, h)

    def state(self, ode: ODEProblem, carry):
        from reelbench.integrators._lie_group_steps import join_ode_state

        return join_ode_state(ode.layout, *carry)

    def saved(self, ode: ODEProblem, carry):
        return carry

    def coordinates(self, ode: ODEProblem, saved):
        return saved[1][:ode.layout.nx]

    def saved_energy_error(self, ode: ODEProblem, saved, E0):
        from reelbench.integrators.base import energy_error

        x, R, w, W = _split(ode.layout, *saved)
        return energy_error(ode.model, x, R, w, W, E0)

    def trajectory(self, run: Run, ode: ODEProblem, t: np.ndarray, saved, n: int) -> Trajectory:
        x, R, w, W = _split(ode.layout, *(np.asarray(a)[:n] for a in saved), axis=1)
        return Trajectory(t=t, x=x, attitude=R if ode.layout.has_attitude else None, velocity=w,
                          work=W if ode.layout.has_work else np.zeros(n), attitude_kind="matrix",
                          scene_name=run.scene.name)

    @staticmethod
    def attitude_matrix(ode: ODEProblem, carry):
        """The attitude a saved carry holds: the rotation matrix itself."""
        return carry[0]


def _split(lay, R, v, axis=0):
    """(x, R, w, W) of a carry (R, v = (x, w, W)); ``axis`` 1 for saved buffers (one row per save)."""
    nx, nw = lay.nx, lay.nw
    take = (lambda a, s: a[s]) if axis == 0 else (lambda a, s: a[:, s])
    W = take(v, nx + nw) if lay.has_work else 0.0
    return take(v, slice(0, nx)), R, take(v, slice(nx, nx + nw)), W


class LieRK4(_LieGroupMethod):
    """RKMK4 on SO(3) × ℝⁿ (module docstring): 4 closed-form evaluations per step."""

    name = "lie_rk4"
    order = 4
    evals_per_step = 4
    lie_step = "rkmk4_step"
    description = ("Runge-Kutta-Munthe-Kaas 4 on SO(3) x R^n: R by Rodrigues exponentials, RK4 on the rest; "
                   "group-preserving, not symplectic")


class CrouchGrossman3(_LieGroupMethod):
    """Crouch–Grossman order 3 on SO(3) × ℝⁿ (module docstring): 3 evaluations per step."""

    name = "crouch_grossman3"
    order = 3
    evals_per_step = 3
    lie_step = "crouch_grossman3_step"
    description = ("Crouch-Grossman order 3 on SO(3) x R^n: products of exponentials of frozen fields; "
                   "group-preserving, not symplectic")
