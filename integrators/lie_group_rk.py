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

Pure step functions: ``step(field, (R, v), t, h) -> ((R1, v1), code, iterations)``, code 0 and no
iterations (explicit steps; the lifecycle's guards judge the state). `LieRK4` / `CrouchGrossman3`
are the thin `FixedStepMethod` wiring that runs them now (see the class docstrings).
"""

from __future__ import annotations

from typing import Callable, ClassVar

from integrators.base import Capability
from integrators.fixed_step import FixedStepMethod
from integrators.lifecycle import ODEProblem
from integrators.rhs import closed_form_of
from models._lazy import jax, jnp, lazy_function  # JAX on first use: the registry lists this module
hat = lazy_function("models.model", "hat")
quat_to_rot = lazy_function("models.model", "quat_to_rot")

__all__ = ["CrouchGrossman3", "LieRK4", "crouch_grossman3_step", "pendulum_field", "rkmk4_step", "rotation_to_quat",
           "so3_exp"]

#: below this |θ|² the exponential's coefficients are taken from their Taylor series (their
#: closed forms lose digits and their derivatives are 0/0 at θ = 0)
_SMALL_ANGLE2 = 1e-8


def so3_exp(theta):
    """exp(θ̂) by Rodrigues' formula, I + (sin|θ|/|θ|) θ̂ + (2 sin²(|θ|/2)/|θ|²) θ̂² (smooth at θ = 0)."""
    t2 = theta @ theta
    small = t2 < _SMALL_ANGLE2
    safe = jnp.where(small, 1.0, t2)
    n = jnp.sqrt(safe)
    a = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, jnp.sin(n) / n)
    half = jnp.sin(0.5 * n)
    b = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 2.0 * half * half / safe)
    K = hat(theta)
    return jnp.eye(3) + a * K + b * (K @ K)


def rotation_to_quat(R):
    """The unit quaternion (w, x, y, z) of a rotation matrix, in JAX and without branches on
    values (Shepperd's method: of the four formulas the one with the largest pivot is taken)."""
    tr = jnp.trace(R)
    d = jnp.diag(R)
    pivots = jnp.stack([tr, d[0], d[1], d[2]])
    s = 2.0 * jnp.sqrt(jnp.maximum(1.0 + jnp.stack([tr, 2 * d[0] - tr, 2 * d[1] - tr, 2 * d[2] - tr]), 1e-300))
    r21, r12, r02, r20, r10, r01 = R[2, 1], R[1, 2], R[0, 2], R[2, 0], R[1, 0], R[0, 1]
    candidates = jnp.stack([
        jnp.stack([0.25 * s[0], (r21 - r12) / s[0], (r02 - r20) / s[0], (r10 - r01) / s[0]]),
        jnp.stack([(r21 - r12) / s[1], 0.25 * s[1], (r01 + r10) / s[1], (r02 + r20) / s[1]]),
        jnp.stack([(r02 - r20) / s[2], (r01 + r10) / s[2], 0.25 * s[2], (r12 + r21) / s[2]]),
        jnp.stack([(r10 - r01) / s[3], (r02 + r20) / s[3], (r12 + r21) / s[3], 0.25 * s[3]]),
    ])
    q = candidates[jnp.argmax(pivots)]
    return jnp.where(q[0] < 0, -q, q)


# ------------------------------------------------------------------------------------------
# The steps, generic over a vector field (t, R, v) -> (Ω, v̇) on SO(3) × ℝⁿ
# ------------------------------------------------------------------------------------------
def rkmk4_step(field: Callable, state, t, h):
    """One RKMK4 step (module docstring) of ``field`` from state = (R, v) at time t."""
    R, v = state
    om1, f1 = field(t, R, v)
    k1, l1 = h * om1, h * f1
    om2, f2 = field(t + 0.5 * h, R @ so3_exp(0.5 * k1), v + 0.5 * l1)
    k2, l2 = h * om2, h * f2
    om3, f3 = field(t + 0.5 * h, R @ so3_exp(0.5 * k2 + jnp.cross(k1, k2) / 8.0), v + 0.5 * l2)
    k3, l3 = h * om3, h * f3
    om4, f4 = field(t + h, R @ so3_exp(k3), v + l3)
    k4, l4 = h * om4, h * f4
    u = (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0 + jnp.cross(k1, k4) / 12.0
    v1 = v + (l1 + 2.0 * l2 + 2.0 * l3 + l4) / 6.0
    return (R @ so3_exp(u), v1), jnp.asarray(0, jnp.int32), jnp.asarray(0, jnp.int32)


#: Crouch–Grossman order 3 (module docstring)
CG3_C = (0.0, 3.0 / 4.0, 17.0 / 24.0)
CG3_A = ((), (3.0 / 4.0,), (119.0 / 216.0, 17.0 / 108.0))
CG3_B = (13.0 / 51.0, -2.0 / 3.0, 24.0 / 17.0)


def crouch_grossman3_step(field: Callable, state, t, h):
    """One Crouch–Grossman step of order 3 (module docstring) of ``field`` from state = (R, v)."""
    R0, v0 = state
    oms, fs = [], []
    for c, a in zip(CG3_C, CG3_A):
        R, v = R0, v0
        for a_j, om_j, f_j in zip(a, oms, fs):
            R = R @ so3_exp(h * a_j * om_j)
            v = v + h * a_j * f_j
        om, f = field(t + c * h, R, v)
        oms.append(om)
        fs.append(f)
    R, v = R0, v0
    for b_j, om_j, f_j in zip(CG3_B, oms, fs):
        R = R @ so3_exp(h * b_j * om_j)
        v = v + h * b_j * f_j
    return (R, v), jnp.asarray(0, jnp.int32), jnp.asarray(0, jnp.int32)


# ------------------------------------------------------------------------------------------
# The pendulum as a vector field on SO(3) × ℝⁿ
# ------------------------------------------------------------------------------------------
def equations_of(ode: ODEProblem):
    """What gives a(t, x, R, w) for the run's right-hand side (`integrators.rhs`): the autodiff
    model when ``rhs="autodiff"`` selected its ``ode_rhs``, else the closed form."""
    model = ode.model
    if ode.f == model.ode_rhs:
        return model
    with jax.ensure_compile_time_eval():  # built eagerly even if first asked for while tracing
        return closed_form_of(model)


def pendulum_field(model, equations):
    """(t, R, v) -> (Ω, v̇) of the pendulum, v = (x, w, W) (the ODE state without its quaternion;
    without a rigid body R is the identity and Ω = 0)."""
    lay = model.layout
    nx, nw = lay.nx, lay.nw

    def field(t, R, v):
        x, w = v[:nx], v[nx:nx + nw]
        parts = [w[:nx], equations.accelerations(t, x, R, w)]
        if lay.has_work:
            parts.append(jnp.atleast_1d(model.power(t, x, w)))
        om = w[lay.omega] if lay.has_attitude else jnp.zeros(3)
        return om, jnp.concatenate(parts)

    return field


def split_ode_state(lay, y):
    """The ODE state y = (x, quat, w, W) as (R, v = (x, w, W))."""
    R = quat_to_rot(y[lay.y_quat]) if lay.has_attitude else jnp.eye(3)
    v = jnp.concatenate([y[lay.y_x], y[lay.y_w], y[lay.y_work]])
    return R, v


def join_ode_state(lay, R, v):
    """(R, v) back to the ODE state y = (x, quat(R), w, W)."""
    nx = lay.nx
    parts = [v[:nx]] + ([rotation_to_quat(R)] if lay.has_attitude else []) + [v[nx:]]
    return jnp.concatenate(parts)


class _LieGroupMethod(FixedStepMethod):
    """The wiring of a Lie group step on today's fixed-step contract.

    The carry is (R, v). The lifecycle guards and saves the ODE state (`state`), so for now the
    saved attitude is the quaternion of the carried R (Shepperd's formula; unit to round-off).
    Once a method defines its saved form, `attitude_matrix` is what it saves instead.
    """

    capabilities = frozenset({Capability.FIXED_STEP, Capability.GROUP_PRESERVING})
    implementation: ClassVar[str] = "jax-compiled"
    #: the pure step, (field, (R, v), t, h) -> ((R, v), code, iterations)
    lie_step: ClassVar[Callable]
    #: comparable to the LGVI's 5 ms in the long-horizon energy study (h ω_max ≈ 1.1 on
    #: fixed_length at N = 10, inside the explicit methods' stability intervals)
    horizon_settings = {"dt": 0.005}
    cost_hint = (20.0, 1.0)

    def init(self, ode: ODEProblem, y0):
        return split_ode_state(ode.layout, jnp.asarray(y0))

    def step(self, ode: ODEProblem, carry, t, h):
        field = pendulum_field(ode.model, equations_of(ode))
        carry, _, _ = type(self).lie_step(field, carry, t, h)
        return carry

    def state(self, ode: ODEProblem, carry):
        return join_ode_state(ode.layout, *carry)

    @staticmethod
    def attitude_matrix(ode: ODEProblem, carry):
        """The attitude a saved carry holds: the rotation matrix itself."""
        return carry[0]


class LieRK4(_LieGroupMethod):
    """RKMK4 on SO(3) × ℝⁿ (module docstring): 4 closed-form evaluations per step."""

    name = "lie_rk4"
    order = 4
    evals_per_step = 4
    lie_step = staticmethod(rkmk4_step)
    description = ("Runge-Kutta-Munthe-Kaas 4 on SO(3) x R^n: R by Rodrigues exponentials, RK4 on the rest; "
                   "group-preserving, not symplectic")


class CrouchGrossman3(_LieGroupMethod):
    """Crouch–Grossman order 3 on SO(3) × ℝⁿ (module docstring): 3 evaluations per step."""

    name = "crouch_grossman3"
    order = 3
    evals_per_step = 3
    lie_step = staticmethod(crouch_grossman3_step)
    description = ("Crouch-Grossman order 3 on SO(3) x R^n: products of exponentials of frozen fields; "
                   "group-preserving, not symplectic")
    horizon_settings = None  # lie_rk4 represents the Lie group methods in the energy study
