"""The Lie group steps on SO(3) × ℝⁿ and the pendulum as their vector field (JAX).

What the methods of `integrators.lie_group_rk` trace (its docstring gives the schemes); kept apart
so that the registry reads names and declarations without importing JAX. Pure step functions:
``step(field, (R, v), t, h) -> (R1, v1)``, generic over the vector field (the tests drive them with
a free rigid body as well as with the pendulum).
"""

from __future__ import annotations

from typing import Callable

from reelbench.integrators.lifecycle import ODEProblem
from reelbench.integrators.rhs import closed_form_of
from reelbench.models._jax import jax, jnp
from reelbench.models.model import hat, quat_to_rot

__all__ = ["CG3_A", "CG3_B", "CG3_C", "crouch_grossman3_step", "equations_of", "join_ode_state", "pendulum_field",
           "rkmk4_step", "rotation_to_quat", "so3_exp", "split_ode_state"]

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
    return R @ so3_exp(u), v1


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
    return R, v


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
            parts.append(jnp.atleast_1d(model.power(t, x, w, R)))
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
