"""The RATTLE step on unit quaternions and the pendulum in quaternion coordinates (JAX).

What `integrators.rattle.Rattle` traces (that module's docstring gives the scheme, its solver and
its cost); kept apart so that the registry reads names and declarations without importing JAX.
Pure step function: ``rattle_step(system, state, t, h, tol, maxit) -> (state, code, iterations)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from reelbench.integrators.fixed_step import StepCode
from reelbench.integrators.rhs import closed_form_of
from reelbench.models._jax import jax, jnp
from reelbench.models.model import quat_rate, quat_to_rot

__all__ = ["QuaternionSystem", "RattleState", "body_rate", "extension_inertia", "initial_state", "ode_state",
           "pendulum_system", "quat_matrix", "rattle_step"]

#: step result codes of `rattle_step`: the lifecycle's shared table
STEP_OK, STEP_NEWTON_FAILED = StepCode.OK, StepCode.NEWTON_FAILED
#: the structured Newton matrix is replaced by the exact Jacobian when an iteration contracts
#: the update by less than this (it would need more than ~15 iterations to 1e-13)
SWITCH_CONTRACTION = 0.2


def quat_matrix(Q):
    """G(Q), 3 × 4: the body angular velocity is Ω = 2 G(Q) Q̇ (the vector part of 2 Q̄ ⊗ Q̇);
    G(Q) Q = 0 and G(Q) G(Q)ᵀ = |Q|² I for every Q."""
    w, x, y, z = Q
    return jnp.array([[-x, w, z, -y], [-y, -z, w, x], [-z, y, -x, w]])


def body_rate(Q, Qdot):
    """Ω = 2 G(Q) Q̇."""
    return 2.0 * quat_matrix(Q) @ Qdot


def legendre_of(model):
    """The model's closed-form equations (`integrators.rhs.closed_form_of`), built eagerly even
    when first asked for inside a traced function (their constants are numpy)."""
    with jax.ensure_compile_time_eval():
        return closed_form_of(model)


def extension_inertia(model) -> float:
    """J₀ of the quaternion kinetic energy's extension: the mean principal inertia about the
    attachment point, tr(J_o)/3 (the scale of the body's own rows, for the Newton matrix)."""
    if model.is_bound:  # a run-time value of the compiled program (`StringPendulum.bind`)
        return jnp.trace(model.J_o) / 3.0
    return float(np.trace(model.J_o) / 3.0)


@dataclass(frozen=True, eq=False)
class QuaternionSystem:
    """A Lagrangian system on q = (x ∈ ℝ^nx, Q ∈ ℝ⁴ if ``has_quaternion``), |Q| = 1.

    ``lagrangian(q, v)``: L at the configuration q and the velocity v = q̇ (any v, also off the
    constraint's tangent space), quadratic in v, of the form L_phys(x, Q, ẋ, Ω = 2 G(Q) Q̇)
    + 2 J₀ (Q·Q̇)² with J₀ = ``extension_inertia``; ``inverse_mass(q, r)``: M(q)⁻¹ r for the
    (regular) mass matrix M = ∂²L/∂v² at a configuration on the constraint; ``force(t, q, v)``:
    the generalised force over q's layout, or None for a conservative system.

    Because G(Q) Q = 0, M (0, Q) = (0, 4 J₀ Q) for unit Q: the constraint's normal needs no solve.
    """

    nx: int
    has_quaternion: bool
    lagrangian: Callable
    inverse_mass: Callable
    force: Callable | None = None
    extension_inertia: float = 0.0

    @property
    def nq(self) -> int:
        return self.nx + (4 if self.has_quaternion else 0)

    def constraint_normal(self, q):
        """∇g(q) = (0, Q) of g = (|Q|² − 1)/2."""
        return jnp.concatenate([jnp.zeros(self.nx), q[self.nx:]])


class RattleState(NamedTuple):
    """What a RATTLE step carries: configuration q, canonical momentum p, the secant velocities
    Δq/h of the last two steps (the predictor; q̇₀ at the start), the last multiplier λ (its
    first guess), the work W of the forces and the count of Newton iterations so far that
    needed the exact Jacobian (``exact_iterations``, see `rattle_step`)."""

    q: jnp.ndarray
    p: jnp.ndarray
    velocity: jnp.ndarray
    previous_velocity: jnp.ndarray
    multiplier: jnp.ndarray
    work: jnp.ndarray
    exact_iterations: jnp.ndarray

    @classmethod
    def start(cls, q, p, velocity, work) -> "RattleState":
        return cls(q=q, p=p, velocity=velocity, previous_velocity=velocity, multiplier=jnp.asarray(0.0),
                   work=jnp.asarray(work, float), exact_iterations=jnp.asarray(0, jnp.int32))


def _discrete_equations(system: QuaternionSystem, state: RattleState, t, h):
    """(D₂L_d, forcing, residual) of a step from ``state``: the discrete Lagrangian's derivative,
    the midpoint forces f(q_{k+1}) and the implicit equations r(z), z = (q_{k+1}, λ)."""
    nx, nq, quat = system.nx, system.nq, system.has_quaternion
    L, F = system.lagrangian, system.force
    q0, p0 = state.q, state.p

    def Ld(qa, qb):
        v = (qb - qa) / h
        return 0.5 * h * (L(qa, v) + L(qb, v))

    D1, D2 = jax.grad(Ld, argnums=0), jax.grad(Ld, argnums=1)

    def forcing(q1):
        if F is None:
            return jnp.zeros(nq)
        return 0.5 * h * F(t + 0.5 * h, 0.5 * (q0 + q1), (q1 - q0) / h)

    def residual(z):
        q1 = z[:nq]
        r = p0 + D1(q0, q1) + forcing(q1)
        if not quat:
            return r
        r = r - 0.5 * h * z[nq] * system.constraint_normal(q0)
        Q1 = q1[nx:]
        return jnp.concatenate([r, jnp.atleast_1d(0.5 * (Q1 @ Q1 - 1.0))])

    return D2, forcing, residual


def _structured_update(system: QuaternionSystem, q0, h, residual):
    """z ↦ the update −J̃⁻¹ r(z) with J̃ the structured matrix of `rattle_step`: ∂r_q/∂q_{k+1}
    = −(M(q_k) + M(q_{k+1}))/(2h) + O(|q̇| ∂M/∂q) holds no stiffness (the potential enters
    D₁L_d at q_k only), so −M(q_k)/h makes Newton contract by O(h |q̇| |∂M/∂q| / |M|)."""
    nq = system.nq

    def solve_mass(r):
        return -h * system.inverse_mass(q0, r)  # ≈ (∂r_q/∂q_{k+1})⁻¹

    if not system.has_quaternion:
        return lambda z: -solve_mass(residual(z))
    a_n0 = -h * system.constraint_normal(q0) / (4.0 * system.extension_inertia)  # = solve_mass(∇g(q_k))

    def update(z):
        r = residual(z)
        a_r = solve_mass(r[:nq])
        n1 = system.constraint_normal(z[:nq])
        d_lam = (n1 @ a_r - r[nq]) / (0.5 * h * (n1 @ a_n0))
        return jnp.concatenate([-a_r + 0.5 * h * d_lam * a_n0, jnp.atleast_1d(d_lam)])

    return update


def _newton_loop(update, nq, tol, maxit, slow_allowed):
    """(cond, body) of a Newton while loop over (z, |dz| before, θ, iterations, converged, bad):
    it stops on convergence, a non-finite iterate, ``maxit`` iterations or, unless
    ``slow_allowed``, a contraction θ above `SWITCH_CONTRACTION`."""
    def cond(c):
        _, _, theta, it, conv, bad = c
        return (~conv) & (~bad) & (it < maxit) & (slow_allowed | (theta <= SWITCH_CONTRACTION))

    def body(c):
        z, size_prev, _, it, _, _ = c
        dz = update(z)
        z_new = z + dz
        bad = ~jnp.all(jnp.isfinite(z_new))
        size = jnp.max(jnp.abs(dz[:nq]))
        # the error left after this update: θ/(1 − θ) |dz| for the observed contraction θ
        # (Hairer & Wanner's stopping rule); on the first iteration, |dz| itself
        first = ~jnp.isfinite(size_prev)
        theta = jnp.where(first, 0.0, size / size_prev)
        left = jnp.where(first | (theta >= 0.5), size, theta / (1.0 - theta) * size)
        scale = jnp.maximum(1.0, jnp.max(jnp.abs(z_new[:nq])))  # relative to |q| beyond 1 m
        return jnp.where(bad, z, z_new), size, theta, it + 1, left <= tol * scale, bad

    return cond, body


def _newton(structured, nq, tol, maxit):
    """The solve of `jax.lax.custom_root`: (res, z_start) -> (z, (iterations, converged, exact
    iterations)): the structured iteration, then, where it contracts too slowly (a fast spin: the
    terms it neglects are O(h |Ω|)), Newton with the exact Jacobian (dense, re-assembled every
    iteration) in a separate loop behind a cond, so that the steps that never need it never pay
    for it (a loop that runs no iteration still cost 15 µs per step at N = 10, measured)."""
    def newton(res, z_start):
        def exact(z):
            return -jnp.linalg.solve(jax.jacfwd(res)(z), res(z))

        false = jnp.asarray(False)
        start = (z_start, jnp.asarray(jnp.inf), jnp.asarray(0.0), jnp.asarray(0, jnp.int32), false, false)
        z, size, _, it, conv, bad = jax.lax.while_loop(*_newton_loop(structured, nq, tol, maxit, False), start)
        need = (~conv) & (~bad) & (it < maxit)
        z, _, _, it_all, conv, bad = jax.lax.cond(
            need, lambda c: jax.lax.while_loop(*_newton_loop(exact, nq, tol, maxit, True), c), lambda c: c,
            (z, size, jnp.asarray(0.0), it, conv, bad))
        # custom_root differentiates its aux output as floats (integer aux breaks its JVP rule)
        return z, jnp.stack([it_all, (conv & ~bad).astype(jnp.int32), it_all - it]).astype(float)

    return newton


def rattle_step(system: QuaternionSystem, state: RattleState, t, h, tol, maxit):
    """One RATTLE step (`integrators.rattle`) of ``system`` from ``state`` at time t.

    Simplified Newton with the structured matrix [−M(q_k)/h, −(h/2)∇g(q_k); ∇g(z)ᵀ, 0]: one
    `QuaternionSystem.inverse_mass` solve per iteration, a scalar Schur complement for λ; where
    an iteration contracts by less than `SWITCH_CONTRACTION`, Newton with the exact (dense,
    autodiff) Jacobian takes over for the rest of the step. It stops when the error left in q,
    estimated from the contraction of the updates, is at most ``tol`` · max(1, |q|_∞) (q in m and
    quaternion units: a few ulps of the largest coordinate) and fails after ``maxit`` iterations
    or on a non-finite iterate. The converged Q_{k+1} is rescaled to |Q| = 1 (a change far below
    ``tol``, along the constraint's normal). Returns (new state, `StepCode`, Newton iterations);
    on failure the state returned is not meaningful (the lifecycle keeps the previous one). The
    step's derivative is the exact discrete map's (implicit function theorem), not the iterates'.
    """
    nx, nq, quat = system.nx, system.nq, system.has_quaternion
    q0 = state.q
    D2, forcing, residual = _discrete_equations(system, state, t, h)
    newton = _newton(_structured_update(system, q0, h, residual), nq, tol, maxit)

    def tangent_solve(g, y):
        return jnp.linalg.solve(jax.jacfwd(g)(y), y)

    # quadratic extrapolation of the last three positions (error O(h³))
    z_start = q0 + h * (2.0 * state.velocity - state.previous_velocity)
    if quat:
        z_start = jnp.concatenate([z_start, jnp.atleast_1d(state.multiplier)])
    z, counts = jax.lax.custom_root(residual, z_start, newton, tangent_solve, has_aux=True)
    counts = jax.lax.stop_gradient(counts).astype(jnp.int32)
    iterations, converged, exact = counts[0], counts[1] == 1, counts[2]
    q1 = z[:nq]
    if quat:
        Q1 = q1[nx:]
        q1 = q1.at[nx:].set(Q1 / jnp.sqrt(Q1 @ Q1))
    f = forcing(q1)
    p1 = D2(q0, q1) + f
    if quat:
        Q1, pQ = q1[nx:], p1[nx:]
        p1 = p1.at[nx:].set(pQ - (Q1 @ pQ) * Q1)  # onto Q·p_Q = 0 (the μ term), |Q1| = 1
    dq = q1 - q0
    work = state.work + (2.0 / h) * (f @ dq)
    new = RattleState(q=q1, p=p1, velocity=dq / h, previous_velocity=state.velocity,
                      multiplier=z[nq] if quat else state.multiplier, work=work,
                      exact_iterations=state.exact_iterations + exact)
    ok = converged & jnp.all(jnp.isfinite(q1)) & jnp.all(jnp.isfinite(p1)) & jnp.isfinite(work)
    code = jnp.where(ok, STEP_OK, STEP_NEWTON_FAILED).astype(jnp.int32)
    return new, code, iterations


# ------------------------------------------------------------------------------------------
# The pendulum in quaternion coordinates
# ------------------------------------------------------------------------------------------
def pendulum_system(model) -> QuaternionSystem:
    """The model's Lagrangian and forces in q = (x, Q) (module docstring)."""
    lay = model.layout
    nx, quat = lay.nx, lay.has_attitude
    J0 = extension_inertia(model) if quat else 0.0

    def to_model(q, v):
        """(x, R, w) of the model at (q, q̇)."""
        if not quat:
            return q, jnp.eye(3), v
        Q, Qdot = q[nx:], v[nx:]
        return q[:nx], quat_to_rot(Q), jnp.concatenate([v[:nx], body_rate(Q, Qdot)])

    def lagrangian(q, v):
        x, R, w = to_model(q, v)
        L = model.lagrangian(x, R, w)
        if quat:
            L = L + 2.0 * J0 * (q[nx:] @ v[nx:]) ** 2
        return L

    def inverse_mass(q, r):
        """M(q)⁻¹ r in O(N): with |Q| = 1 the rows of [Qᵀ; G(Q)] are orthonormal, and
        p_Q = 2 G(Q)ᵀ Π + 4 J₀ (Q·Q̇) Q splits into the model's Π = G(Q) p_Q / 2 and Q·Q̇ =
        Q·p_Q / (4 J₀); (ẋ, Ω) = M_model⁻¹ (p_x, Π) by the closed form, Q̇ = G(Q)ᵀ Ω/2 + (Q·Q̇) Q."""
        if not quat:
            return legendre_of(model).velocity_from_momentum(q, jnp.eye(3), r)
        Q = q[nx:]
        G = quat_matrix(Q)
        w = legendre_of(model).velocity_from_momentum(q[:nx], quat_to_rot(Q), jnp.concatenate([r[:nx], 0.5 * G @ r[nx:]]))
        along = (Q @ r[nx:]) / (4.0 * J0)
        return jnp.concatenate([w[:nx], 0.5 * G.T @ w[lay.omega] + along * Q])

    force = None
    if model.reel_forces or model.string_forces or model.body_loads:
        def force(t, q, v):
            x, R, w = to_model(q, v)
            Fw = model.generalized_force(t, x, w, R)
            if not quat:
                return Fw
            return jnp.concatenate([Fw[:nx], 2.0 * quat_matrix(q[nx:]).T @ Fw[lay.omega]])

    return QuaternionSystem(nx=nx, has_quaternion=quat, lagrangian=lagrangian, inverse_mass=inverse_mass, force=force,
                            extension_inertia=J0)


def initial_state(model, y0) -> RattleState:
    """The RATTLE state of an ODE state y0 = (x, quat, w, W): p from the model's Legendre map."""
    lay = model.layout
    x, w = y0[lay.y_x], y0[lay.y_w]
    W = y0[lay.y_work][0] if lay.has_work else jnp.asarray(0.0)
    if not lay.has_attitude:
        p = legendre_of(model).momentum(x, jnp.eye(3), w)
        return RattleState.start(x, p, w, W)
    Q = y0[lay.y_quat]
    pm = legendre_of(model).momentum(x, quat_to_rot(Q), w)
    p = jnp.concatenate([pm[:lay.nx], 2.0 * quat_matrix(Q).T @ pm[lay.omega]])
    velocity = jnp.concatenate([w[:lay.nx], quat_rate(Q, w[lay.omega])])
    return RattleState.start(jnp.concatenate([x, Q]), p, velocity, W)


def ode_state(model, state: RattleState):
    """The ODE state (x, Q, w, W) of a RATTLE state: w = M(x, R(Q))⁻¹ (p_x, Π) by the O(N)
    closed-form Legendre map, Π = G(Q) p_Q / (2|Q|²) (p_Q = 2 G(Q)ᵀ Π on the constraint)."""
    lay = model.layout
    nx = lay.nx
    x = state.q[:nx]
    if lay.has_attitude:
        Q = state.q[nx:]
        Pi = quat_matrix(Q) @ state.p[nx:] / (2.0 * (Q @ Q))
        w = legendre_of(model).velocity_from_momentum(x, quat_to_rot(Q), jnp.concatenate([state.p[:nx], Pi]))
        parts = [x, Q, w]
    else:
        parts = [x, legendre_of(model).velocity_from_momentum(x, jnp.eye(3), state.p)]
    if lay.has_work:
        parts.append(jnp.atleast_1d(state.work))
    return jnp.concatenate(parts)
