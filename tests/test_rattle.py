"""RATTLE on unit quaternions (integrators/rattle.py): the quaternion Lagrangian is the model's,
the constraints hold at round-off, the production steps satisfy the discrete equations of an
independently written discrete Lagrangian, the step map is symplectic on the constraint manifold
(and the Lie group RK's is not), the energy error has no trend (and the Lie group RK's drifts),
π₃ is conserved (discrete Noether), and a failed step is a status. Orders: tests/test_orders.py.
"""

import functools

import numpy as np
import pytest

from reelbench.integrators import Capability, Status, get_integrator
from reelbench.integrators._lie_group_steps import pendulum_field, rkmk4_step
from reelbench.integrators._rattle_step import (RattleState, extension_inertia, initial_state, pendulum_system, quat_matrix,
                                rattle_step)
from reelbench.integrators.rhs import closed_form_of
from reelbench.models import build_model
from reelbench.models._jax import jax, jnp
from reelbench.models.diagnostics import evaluate
from reelbench.models.model import quat_rate, quat_to_rot, vee

from _helpers import random_state, scene_with_effects

FIXED = ["elasticity", "gravity", "rigid_body"]
VARIANTS = {
    "fixed_length": (FIXED, {}),
    "reel": (FIXED + ["reel", "carnot", "reel_control"], {}),
    "reel_point_mass": (["elasticity", "gravity", "reel", "carnot", "reel_control"], {}),
    "axial_damping": (FIXED + ["axial_damping"], {"axial_damping": 0.5}),
}
TOL, MAXIT = 1e-14, 20  # the method's Newton settings (`Rattle.newton_tol`, `newton_max_iter`)
H = 0.005


def model_of(variant, elements=3):
    effects, kw = VARIANTS[variant]
    return build_model(scene_with_effects(effects, elements=elements, **kw))


def qmul(a, b):
    """Quaternion product a ⊗ b, (w, x, y, z)."""
    return jnp.concatenate([jnp.atleast_1d(a[0] * b[0] - a[1:] @ b[1:]), a[0] * b[1:] + b[0] * a[1:] + jnp.cross(a[1:], b[1:])])


def conj(a):
    return a * jnp.array([1.0, -1.0, -1.0, -1.0])


def direction_rotation(Q):
    """R(Q/|Q|): the rotation of Q's direction (homogeneous of degree 0 in Q)."""
    return quat_to_rot(Q / jnp.sqrt(Q @ Q))


def independent_lagrangian(model):
    """L(q, q̇) written apart from the production code: Ω = (R̂ᵀ dR̂[Q̇])^∨ with R̂(Q) = R(Q/|Q|)
    (autodiff), which is 2 G(Q) Q̇ for unit Q and every Q̇ (a velocity along Q turns nothing); T
    and V the model's; the extension 2 J₀ (Q·Q̇)² with the method's J₀. (R(Q) itself is not
    homogeneous in Q: with it a velocity along Q would turn the body.)"""
    lay = model.layout
    nx = lay.nx
    J0 = extension_inertia(model)

    def L(q, v):
        if not lay.has_attitude:
            return model.lagrangian(q, jnp.eye(3), v)
        Q, Qdot = q[nx:], v[nx:]
        R, Rdot = jax.jvp(direction_rotation, (Q,), (Qdot,))
        w = jnp.concatenate([v[:nx], vee(R.T @ Rdot)])
        return model.lagrangian(q[:nx], R, w) + 2.0 * J0 * (Q @ Qdot) ** 2

    return L


def independent_force(model):
    """F(t, q, q̇) over q's layout: the model's generalised force at w = (ẋ, Ω = 2 vec(Q̄ ⊗ Q̇)),
    its torque part mapped to Q by virtual work (δθ = 2 vec(Q̄ ⊗ δQ))."""
    lay = model.layout
    nx = lay.nx

    def F(t, q, v):
        if not lay.has_attitude:
            return model.generalized_force(t, q, v)
        Q = q[nx:]
        omega = 2.0 * qmul(conj(Q), v[nx:])[1:]
        Fw = model.generalized_force(t, q[:nx], jnp.concatenate([v[:nx], omega]))
        return jnp.concatenate([Fw[:nx], jax.jacfwd(lambda Qd: 2.0 * qmul(conj(Q), Qd)[1:])(jnp.zeros(4)).T @ Fw[lay.omega]])

    return F


@functools.lru_cache(maxsize=None)
def runner(model, h, n):
    """Jitted: state -> (state after n production steps of size h, per step: the state after it,
    its code and Newton iterations, ||Q| − 1| and |Q·Q̇| with Q̇ = M⁻¹p = ∂H/∂p_Q)."""
    system = pendulum_system(model)
    nx = model.layout.nx

    def body(s, _):
        s1, code, it = rattle_step(system, s, 0.0, h, TOL, MAXIT)
        out = {"state": s1, "code": code, "iterations": it}
        if model.layout.has_attitude:
            Q = s1.q[nx:]
            out["norm_error"] = jnp.abs(jnp.sqrt(Q @ Q) - 1.0)
            out["velocity_constraint"] = jnp.abs(Q @ system.inverse_mass(s1.q, s1.p)[nx:])
        return s1, out

    return jax.jit(lambda s: jax.lax.scan(body, s, None, length=n))


def start_state(model):
    return initial_state(model, jnp.asarray(model.initial_ode_state()))


@pytest.fixture(scope="module")
def fixed_run():
    """2000 steps of 5 ms on the small fixed-length scene (N = 3, a tumbling body)."""
    model = model_of("fixed_length")
    final, out = runner(model, 0.005, 2000)(start_state(model))
    return model, final, jax.tree_util.tree_map(np.asarray, out)


# ------------------------------------------------------------------------------------------
# The Lagrangian in quaternion coordinates is the model's
# ------------------------------------------------------------------------------------------
def test_quaternion_lagrangian_momenta_and_mass_are_the_models(rng):
    """On the constraint (|Q| = 1, Q̇ = ½ Q ⊗ (0, Ω)), with a reel and a rigid body: L(q, q̇) =
    L_model(x, R, w), p_x is the model's, p_Q = 2 G(Q)ᵀ Π, the hidden constraint Q·p_Q = 0
    holds; the structured M⁻¹ equals the inverse of ∂²L/∂q̇² (autodiff) for any right-hand side."""
    from reelbench.models.model import rot_to_quat

    model = model_of("reel")
    lay = model.layout
    nx = lay.nx
    system = pendulum_system(model)
    x, R, w = random_state(model, rng)
    Q = jnp.asarray(rot_to_quat(R))
    r = jnp.asarray(rng.standard_normal(system.nq))

    @jax.jit
    def pieces(x, R, w, Q, r):
        q = jnp.concatenate([x, Q])
        v = jnp.concatenate([w[:nx], quat_rate(Q, w[lay.omega])])
        p = jax.grad(system.lagrangian, argnums=1)(q, v)
        M = jax.jacfwd(jax.grad(system.lagrangian, argnums=1), argnums=1)(q, v)
        return (system.lagrangian(q, v), model.lagrangian(x, R, w), p, model.momentum(x, R, w),
                system.inverse_mass(q, r), jnp.linalg.solve(M, r))

    L, L_model, p, p_model, inv_r, solved = (np.asarray(a) for a in pieces(x, R, w, Q, r))
    assert abs(L - L_model) < 1e-12 * abs(L_model)
    assert np.abs(p[:nx] - p_model[:nx]).max() < 1e-12
    assert np.abs(p[nx:] - np.asarray(2.0 * quat_matrix(Q).T @ p_model[lay.omega])).max() < 1e-12
    assert abs(float(np.asarray(Q) @ p[nx:])) < 1e-12
    assert np.abs(inv_r - solved).max() < 1e-11 * np.abs(solved).max()


# ------------------------------------------------------------------------------------------
# Constraints and discrete equations
# ------------------------------------------------------------------------------------------
def test_constraints_stay_at_round_off(fixed_run):
    """2000 steps of 5 ms: ||Q| − 1| and the velocity constraint Q·Q̇ (Q̇ = ∂H/∂p_Q = M⁻¹p, the
    same as Q·p_Q = 0) stay at round-off in every step (measured 2.2e-16 and 1.3e-15)."""
    _, _, out = fixed_run
    assert out["code"].max() == 0
    print("max ||Q| - 1|", out["norm_error"].max(), "max |Q.Qdot|", out["velocity_constraint"].max())
    assert out["norm_error"].max() < 1e-15
    assert out["velocity_constraint"].max() < 1e-14


@functools.lru_cache(maxsize=None)
def residuals_of(model):
    """Jitted (q_k, p_k, q_{k+1}, p_{k+1}, t_k) -> (p_k + D₁L_d + f, p_{k+1} − D₂L_d − f, f) for the
    trapezoidal L_d of `independent_lagrangian` and f = (h/2) F(t_k + h/2, q_{k+½}, Δq/h) of
    `independent_force`."""
    L, F = independent_lagrangian(model), independent_force(model)

    def Ld(q0, q1):
        v = (q1 - q0) / H
        return 0.5 * H * (L(q0, v) + L(q1, v))

    def residuals(q0, p0, q1, p1, t):
        f = 0.5 * H * F(t + 0.5 * H, 0.5 * (q0 + q1), (q1 - q0) / H)
        return p0 + jax.grad(Ld, argnums=0)(q0, q1) + f, p1 - jax.grad(Ld, argnums=1)(q0, q1) - f, f

    return jax.jit(residuals)


SLOW_VARIANT = pytest.mark.slow  # their own scenes: one more compiled loop each (~15 s)


@pytest.mark.parametrize("variant", ["fixed_length", "reel", pytest.param("reel_point_mass", marks=SLOW_VARIANT),
                                     pytest.param("axial_damping", marks=SLOW_VARIANT)])
def test_production_steps_satisfy_the_discrete_equations(variant):
    """The production run (`Rattle.solve`, saving every step) satisfies RATTLE's equations step
    by step for the trapezoidal L_d of `independent_lagrangian`, with the midpoint forces
    f = (h/2) F(t + h/2, q_{k+½}, Δq/h) of `independent_force` (autodiff, none of the production
    functions): p_k + D₁L_d + f and p_{k+1} − D₂L_d − f have no component tangent to the sphere
    (they are the multiplier terms, along (0, Q)), |Q_{k+1}| = 1, Q_{k+1}·p_{Q,k+1} = 0, and the
    work of each step is F·Δq. The momenta are read back from the saved velocities by the
    model's Legendre map (p = M w, p_Q = 2 G(Q)ᵀ Π)."""
    effects, kw = VARIANTS[variant]
    scene = scene_with_effects(effects, elements=3, **kw)
    model = build_model(scene)
    lay = model.layout
    nx = lay.nx
    tr = get_integrator("rattle").solve(scene, t_end=0.2, dt=H, save_every=H)
    assert tr.ok and len(tr.t) == 41, tr.reason
    Y = np.concatenate([tr.x] + ([tr.attitude] if lay.has_attitude else []) + [tr.velocity]
                       + ([tr.work[:, None]] if lay.has_work else []), axis=1)
    states = [initial_state(model, jnp.asarray(y)) for y in Y[-3:]]
    residuals = residuals_of(model)
    for k, (before, after) in enumerate(zip(states[:-1], states[1:])):
        r0, r1, f = residuals(before.q, before.p, after.q, after.p, tr.t[-3 + k])

        def tangential(r, q):
            if not lay.has_attitude:
                return r
            Q = q[nx:]
            return r.at[nx:].add(-(Q @ r[nx:]) * Q)

        scale = float(jnp.max(jnp.abs(before.p)))
        t0, t1 = (float(jnp.max(jnp.abs(tangential(r, q)))) / scale for r, q in ((r0, before.q), (r1, after.q)))
        print(variant, "tangential residuals (relative to max |p|)", t0, t1)
        assert t0 < 1e-11 and t1 < 1e-11
        if lay.has_attitude:
            Q1 = after.q[nx:]
            assert abs(float(Q1 @ Q1) - 1.0) < 1e-15 and abs(float(Q1 @ after.p[nx:])) < 1e-14 * scale
            # the multiplier term is not zero: the constraint force is in the equations
            assert abs(float(before.q[nx:] @ r0[nx:])) > 1e-6 * scale
        if model.reel_forces or model.string_forces:
            dW = float(after.work - before.work)
            assert dW != 0.0
            assert abs(dW - float((2.0 / H) * f @ (after.q - before.q))) < 1e-10 * abs(dW)


# ------------------------------------------------------------------------------------------
# Symplecticity on the constraint manifold (canonical coordinates (q, p) of the quaternion L)
# ------------------------------------------------------------------------------------------
def manifold_constraints(nx, nq):
    """(|Q|² − 1)/2 and Q·p_Q: the constraint manifold of the canonical phase space."""
    def c(z):
        Q, pQ = z[nx:nq], z[nq + nx:]
        return jnp.array([0.5 * (Q @ Q - 1.0), Q @ pQ])

    return c


def symplectic_defect(phi, z, nx, nq):
    """max |(DΦ V)ᵀ 𝕁 (DΦ V) − Vᵀ 𝕁 V| / max |(DΦ V)ᵀ 𝕁 (DΦ V)| for an orthonormal basis V of the
    tangent space of the constraint manifold at z; also the largest constraint derivative of the
    image vectors at Φ(z) (DΦ maps tangent vectors to tangent vectors)."""
    c = manifold_constraints(nx, nq)
    C = np.asarray(jax.jacfwd(c)(z))
    V = np.linalg.svd(C)[2][2:].T
    image, D = (np.asarray(a) for a in jax.jit(lambda z: (phi(z), jax.jacfwd(phi)(z)))(z))
    A = D @ V
    n = nq
    Jc = np.block([[np.zeros((n, n)), np.eye(n)], [-np.eye(n), np.zeros((n, n))]])
    S1, S0 = A.T @ Jc @ A, V.T @ Jc @ V
    off = np.abs(np.asarray(jax.jacfwd(c)(jnp.asarray(image))) @ A).max() / np.abs(A).max()
    return np.abs(S1 - S0).max() / np.abs(S1).max(), off


@pytest.fixture(scope="module")
def small_system():
    """N = 2 at fixed length (conservative), h = 10 ms, at a state off the straight initial line:
    nodes and velocities perturbed, a random attitude (on the constraint manifold)."""
    model = model_of("fixed_length", elements=2)
    rng = np.random.default_rng(7)
    lay = model.layout
    y = np.asarray(model.initial_ode_state()).copy()
    y[lay.y_x] += 0.3 * rng.standard_normal(lay.nx)
    y[lay.y_w] += rng.standard_normal(lay.nw)
    Q = rng.standard_normal(4)
    y[lay.y_quat] = Q / np.linalg.norm(Q)
    return model, initial_state(model, jnp.asarray(y)), 0.01


def test_rattle_step_is_symplectic_on_the_constraint_manifold(small_system):
    """DΦ of the production step (autodiff: the implicit function theorem through Newton's
    solution) preserves ω = dq ∧ dp on tangent vectors of {|Q| = 1, Q·p_Q = 0} to round-off
    (measured relative defect 1.1e-14) and maps them to tangent vectors."""
    model, state, h = small_system
    system = pendulum_system(model)
    nx, nq = system.nx, system.nq

    def phi(z):
        s = state._replace(q=z[:nq], p=z[nq:])
        new, _, _ = rattle_step(system, s, 0.0, h, TOL, MAXIT)
        return jnp.concatenate([new.q, new.p])

    defect, off = symplectic_defect(phi, jnp.concatenate([state.q, state.p]), nx, nq)
    print("rattle: symplectic defect", defect, "constraint derivative of image vectors", off)
    assert defect < 1e-13 and off < 1e-13


def test_lie_rk4_step_is_not_symplectic(small_system):
    """The same test on RKMK4, read in the same canonical coordinates (q = (x, Q), p = ∂L/∂q̇;
    its attitude R(Q) advanced by R exp(u) is Q ⊗ q(exp(u))): a defect far above round-off (measured
    5.6e-7 at h = 10 ms, 5·10⁷ times RATTLE's), though it also keeps the manifold."""
    model, state, h = small_system
    lay = model.layout
    nx, nq = lay.nx, lay.nx + 4
    cf = closed_form_of(model)
    field = pendulum_field(model, cf)

    def phi(z):
        x, Q, px, pQ = z[:nx], z[nx:nq], z[nq:nq + nx], z[nq + nx:]
        R = quat_to_rot(Q)
        Pi = quat_matrix(Q) @ pQ / (2.0 * (Q @ Q))
        w = cf.velocity_from_momentum(x, R, jnp.concatenate([px, Pi]))
        R1, v1 = rkmk4_step(field, (R, jnp.concatenate([x, w])), 0.0, h)
        x1, w1 = v1[:nx], v1[nx:]
        step = R.T @ R1  # exp(u), near the identity: its quaternion from the trace formula
        s = 0.5 * jnp.sqrt(1.0 + jnp.trace(step))
        dq = jnp.concatenate([jnp.atleast_1d(s), vee(step) / (2.0 * s)])
        Q1 = qmul(Q, dq)
        pm = cf.momentum(x1, R1, w1)
        return jnp.concatenate([x1, Q1, pm[:nx], 2.0 * quat_matrix(Q1).T @ pm[lay.omega]])

    z = jnp.concatenate([state.q, state.p])
    defect, off = symplectic_defect(phi, z, nx, nq)
    print("lie_rk4: symplectic defect", defect, "constraint derivative of image vectors", off)
    assert defect > 1e-9
    assert off < 1e-12


# ------------------------------------------------------------------------------------------
# Long runs: energy without trend, π₃ conserved
# ------------------------------------------------------------------------------------------
LONG_T, LONG_DT = 200.0, 0.005


@pytest.fixture(scope="module")
def long_runs():
    """rattle and lie_rk4 on the small fixed-length scene of tests/test_orders.py (N = 3, a
    tumbling body), 200 s at 5 ms (40000 steps), saved every second."""
    scene = scene_with_effects(FIXED, elements=3)
    out = {}
    for name in ("rattle", "lie_rk4"):
        tr = get_integrator(name).solve(scene, t_end=LONG_T, dt=LONG_DT, save_every=1.0)
        assert tr.ok, tr.reason
        out[name] = evaluate(scene, tr)
    return out


def energy_trend(df):
    """(drift = fitted slope × duration, its size over the scatter about the fit, max |E − E₀|)."""
    t, e = df["t"].to_numpy(), (df["energy"] - df["energy"].iloc[0]).to_numpy()
    slope, intercept = np.polyfit(t, e, 1)
    drift = slope * (t[-1] - t[0])
    return drift, abs(drift) / np.std(e - intercept - slope * t), np.abs(e).max()


def test_energy_error_is_bounded_without_trend_and_lie_rk4_drifts(long_runs):
    """Fit E(t) − E₀ = a + b t over 200 s. RATTLE: the drift b·T is a fraction of the scatter
    about the fit (measured 0.16; max |E − E₀| = 8.7e-3 J, 2.4e-4 of max T); RKMK4 at the same
    step: a steady loss, 25 times the scatter (drift −4.2e-3 J)."""
    drift_r, t_r, max_r = energy_trend(long_runs["rattle"])
    drift_k, t_k, max_k = energy_trend(long_runs["lie_rk4"])
    print(f"rattle: drift {drift_r:.3g} J ({t_r:.3g} x scatter), max |dE| {max_r:.3g} J; "
          f"lie_rk4: drift {drift_k:.3g} J ({t_k:.3g} x scatter), max |dE| {max_k:.3g} J")
    assert t_r < 2.0
    assert max_r < 1e-3 * long_runs["rattle"]["kinetic"].max()
    assert t_k > 10.0 and drift_k < 0


def test_angular_momentum_about_the_vertical_is_conserved(long_runs):
    """π₃ (rotations about e₃ are a symmetry of L_d and of the constraint): RATTLE keeps it to
    the Newton tolerance over 40000 steps (measured 2.3e-9 relative), RKMK4 only to its
    truncation error (2.1e-6)."""
    rel = {k: float(np.abs(df["pi3"] - df["pi3"].iloc[0]).max() / abs(df["pi3"].iloc[0])) for k, df in long_runs.items()}
    print("relative pi3 errors", rel)
    assert rel["rattle"] < 1e-7
    assert rel["lie_rk4"] > 100 * rel["rattle"]


# ------------------------------------------------------------------------------------------
# Work balance with forces, failures, declarations
# ------------------------------------------------------------------------------------------
def test_energy_minus_work_converges_at_second_order_with_forces():
    """Reel with Carnot loss and control moment: the balance E − W − E₀ at t = 0.32 s shrinks by
    4 when h halves (the forces' work is accounted with the same midpoint force as the step;
    measured ratio 4.0)."""
    scene = scene_with_effects(VARIANTS["reel"][0], elements=3)
    errs = []
    for h in (0.004, 0.002):
        df = evaluate(scene, get_integrator("rattle").solve(scene, t_end=0.32, dt=h, save_every=0.08))
        errs.append(float(np.abs(df["energy_minus_work"] - df["energy_minus_work"].iloc[0]).max()))
    print("max |E - W - E0|", errs, "ratio", errs[0] / errs[1])
    assert 3.5 < errs[0] / errs[1] < 4.5


def test_newton_failure_is_a_status_not_a_crash():
    """A step far too large for the string (h ω_max ≫ 2): the run stops with a status and a
    reason, the trajectory up to the last good saved point, no NaN."""
    scene = scene_with_effects(FIXED, elements=3)
    tr = get_integrator("rattle").solve(scene, t_end=4.0, dt=0.2, save_every=0.4)
    print(tr.status, tr.reason)
    assert tr.status == Status.DIVERGED.value and tr.reason
    assert np.all(np.isfinite(tr.x)) and np.all(np.isfinite(tr.velocity)) and tr.t[-1] < 4.0


def test_newton_iterations_per_step(fixed_run):
    """The structured simplified Newton contracts by ~0.005 per iteration: 4-5 iterations per step
    to the error estimate 1e-13 m, and the exact Jacobian takes over in few steps (measured mean
    4.4, max 6, 32 exact-Jacobian iterations in 2000 steps, where the body spins fastest)."""
    _, final, out = fixed_run
    iterations = out["iterations"]
    print("iterations: mean", iterations.mean(), "max", iterations.max(), "exact Jacobian", int(final.exact_iterations))
    assert iterations.mean() < 5.5 and iterations.max() <= 10
    assert int(final.exact_iterations) < 0.05 * len(iterations)


def test_declarations_and_refused_options():
    integ = get_integrator("rattle")
    assert integ.capabilities == frozenset({Capability.FIXED_STEP, Capability.IMPLICIT, Capability.VARIATIONAL})
    assert integ.order == 2 and integ.orders is None and integ.implementation == "jax-compiled"
    from reelbench.benchmark.studies import horizon

    assert horizon.declared("rattle").settings == {"dt": 0.005}  # the energy study's setting
    scene = scene_with_effects(FIXED, elements=3)
    with pytest.raises(ValueError, match="rhs"):
        integ.solve(scene, t_end=0.1, dt=0.01, rhs="autodiff")
    with pytest.raises(ValueError, match="dt"):
        integ.solve(scene, t_end=0.1, dt=-0.01)


def test_rattle_state_starts_on_the_constraint():
    model = model_of("reel")
    s = start_state(model)
    assert isinstance(s, RattleState)
    Q, pQ = s.q[model.layout.nx:], s.p[model.layout.nx:]
    assert abs(float(Q @ Q) - 1.0) < 1e-15 and abs(float(Q @ pQ)) < 1e-14


def test_a_failed_newton_solve_ends_the_run_as_newton_failed_with_its_iterations():
    """The step reports its code and iterations to the lifecycle (`StepResult`): a normal run sums
    the Newton iterations into the stats; a cap of one iteration cannot converge (the stopping
    rule needs two updates to estimate the contraction), so the run stops at its first step as
    ``newton_failed``, keeping the initial state."""
    from reelbench.integrators.rattle import Rattle

    scene = scene_with_effects(VARIANTS["fixed_length"][0], elements=2)
    ok = get_integrator("rattle").solve(scene, t_end=0.05, dt=0.005, save_every=0.05)
    assert ok.ok and ok.stats["steps"] == 10
    assert 10 * 2 <= ok.stats["newton_iterations"] <= 10 * 20

    class OneIteration(Rattle):
        newton_max_iter = 1

    failed = OneIteration().solve(scene, t_end=0.05, dt=0.005, save_every=0.05)
    assert failed.status == Status.NEWTON_FAILED.value, (failed.status, failed.reason)
    assert failed.stats["steps"] == 0 and len(failed.t) == 1
