"""The Lie group Runge–Kutta methods (integrators/lie_group_rk.py): the exponential, the order of
the rotation on a torque-free axisymmetric body (closed-form solution), orthogonality over long
runs, and the wiring. Their orders on the pendulum are measured by tests/test_orders.py; that
they are not symplectic (and RATTLE is), by tests/test_rattle.py.
"""

import numpy as np
import pytest
import scipy.linalg

from reelbench.integrators import Capability, get_integrator
from reelbench.integrators._lie_group_steps import (crouch_grossman3_step, pendulum_field, rkmk4_step, rotation_to_quat,
                                      so3_exp, split_ode_state)
from reelbench.integrators.rhs import closed_form_of
from reelbench.models import build_model
from reelbench.models._jax import jax, jnp
from reelbench.models.model import hat, quat_to_rot

from _helpers import scene_with_effects

FIXED = ["elasticity", "gravity", "rigid_body"]


def test_so3_exp_is_the_matrix_exponential_and_smooth_at_zero():
    for theta in ([0.3, -1.2, 0.7], [2.9, 0.1, -0.4], [1e-5, -2e-5, 3e-6], [1e-9, 0.0, 0.0], [0.0, 0.0, 0.0]):
        theta = np.array(theta)
        R = np.asarray(so3_exp(jnp.asarray(theta)))
        assert np.abs(R - scipy.linalg.expm(np.asarray(hat(theta)))).max() < 2e-15
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-15
    # the derivative at θ = 0 is the hat map's basis (no 0/0 in the closed-form coefficients)
    D = np.asarray(jax.jacfwd(so3_exp)(jnp.zeros(3)))
    assert np.abs(D - np.stack([np.asarray(hat(e)) for e in np.eye(3)], axis=-1)).max() < 1e-15


def test_rotation_to_quat_inverts_quat_to_rot_on_every_branch(rng):
    quats = [rng.standard_normal(4) for _ in range(20)]
    # near half-turns about each axis: the trace is near −1, so each of the other three pivots is taken
    quats += [np.array([1e-3, 1.0, 0.2, -0.1]), np.array([1e-3, 0.1, 1.0, 0.3]), np.array([-1e-3, 0.2, 0.1, 1.0])]
    for q in quats:
        q = q / np.linalg.norm(q)
        R = np.asarray(quat_to_rot(jnp.asarray(q)))
        q2 = np.asarray(rotation_to_quat(jnp.asarray(R)))
        assert abs(np.linalg.norm(q2) - 1.0) < 5e-16
        assert q2[0] >= 0.0
        assert np.abs(np.asarray(quat_to_rot(jnp.asarray(q2))) - R).max() < 1e-15


# ------------------------------------------------------------------------------------------
# A torque-free axisymmetric body: the closed-form solution
# ------------------------------------------------------------------------------------------
I_AXIAL, I_TRANSVERSE = 2.5, 1.0
INERTIA = np.array([I_TRANSVERSE, I_TRANSVERSE, I_AXIAL])
OMEGA0 = np.array([0.7, -0.4, 1.3])
R0 = np.asarray(scipy.linalg.expm(np.asarray(hat(np.array([0.3, 0.2, -0.5])))))


def free_body_field(t, R, omega):
    """Euler's equations on SO(3) × ℝ³: Ṙ = R Ω̂, J Ω̇ = J Ω × Ω (body frame)."""
    J = jnp.asarray(INERTIA)
    return omega, jnp.cross(J * omega, omega) / J


def free_body_attitude(t):
    """R(t) = exp(t |π|/I₁ π̂/|π|) R₀ exp(−λ t ê₃), π = R₀ J Ω₀ (space angular momentum),
    λ = (I₃ − I₁) Ω₃ / I₁: the space-fixed precession about π and the body-fixed spin about e₃."""
    pi = R0 @ (INERTIA * OMEGA0)
    lam = (I_AXIAL - I_TRANSVERSE) / I_TRANSVERSE * OMEGA0[2]
    precession = scipy.linalg.expm(t * np.linalg.norm(pi) / I_TRANSVERSE * np.asarray(hat(pi / np.linalg.norm(pi))))
    return precession @ R0 @ scipy.linalg.expm(-lam * t * np.asarray(hat(np.array([0.0, 0.0, 1.0]))))


def integrate(step, field, state, h, n):
    def body(s, _):
        return step(field, s, 0.0, h), None

    return jax.jit(lambda s: jax.lax.scan(body, s, None, length=n)[0])(state)


def test_free_body_closed_form_solves_euler_equations():
    """The reference: its body angular velocity R(t)ᵀṘ(t) is Ω(t) = exp(λ t ê₃) Ω₀ (Euler's equations)."""
    lam = (I_AXIAL - I_TRANSVERSE) / I_TRANSVERSE * OMEGA0[2]
    for t in (0.0, 0.8, 2.0):
        eps = 1e-6
        Rdot = (free_body_attitude(t + eps) - free_body_attitude(t - eps)) / (2 * eps)
        W = free_body_attitude(t).T @ Rdot
        omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
        expected = scipy.linalg.expm(lam * t * np.asarray(hat(np.array([0.0, 0.0, 1.0])))) @ OMEGA0
        assert np.abs(omega - expected).max() < 1e-8


def rkmk4_without_commutators(field, state, t, h):
    """RKMK4 with the dexp⁻¹ correction left out (classical RK4 on u): not a test subject, the
    check that the order test can tell a method that is not of order 4."""
    R, v = state
    om1, f1 = field(t, R, v)
    om2, f2 = field(t + h / 2, R @ so3_exp(h * om1 / 2), v + h * f1 / 2)
    om3, f3 = field(t + h / 2, R @ so3_exp(h * om2 / 2), v + h * f2 / 2)
    om4, f4 = field(t + h, R @ so3_exp(h * om3), v + h * f3)
    u = h * (om1 + 2 * om2 + 2 * om3 + om4) / 6
    return R @ so3_exp(u), v + h * (f1 + 2 * f2 + 2 * f3 + f4) / 6


@pytest.mark.parametrize("step, order", [(rkmk4_step, 4), (crouch_grossman3_step, 3), (rkmk4_without_commutators, 2)],
                         ids=["rkmk4", "crouch_grossman3", "rk4_on_u_without_commutators"])
def test_free_body_rotation_converges_at_the_order(step, order):
    T = 2.0
    exact = free_body_attitude(T)
    errors = []
    for n in (20, 40, 80, 160):
        R, _ = integrate(step, free_body_field, (jnp.asarray(R0), jnp.asarray(OMEGA0)), T / n, n)
        errors.append(np.abs(np.asarray(R) - exact).max())
    slopes = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    print(step.__name__, "errors", errors, "slopes (log2 of the ratios)", slopes)
    assert errors[-1] > 1e-12  # above round-off
    assert np.all(np.abs(slopes[1:] - order) < 0.1), slopes


def test_attitude_stays_orthogonal_to_round_off():
    """A fast free body (|Ω| = 15.6 rad/s, h = 10 ms) for 10⁵ steps and the pendulum (N = 2) for
    2·10⁴ steps: ‖RᵀR − I‖ grows only as the round-off of the products R exp(u), a random walk
    ~ √n ε (measured 6.3e-14 and 2.6e-14 with RKMK4, 5.2e-13 and 3.3e-14 with CG3, whose update is
    three products: 0.9, 0.8, 7.5 and 1.1 × √n ε)."""
    fast = (jnp.asarray(R0), jnp.asarray(10.0 * OMEGA0))
    model = build_model(scene_with_effects(FIXED, elements=2))
    field = pendulum_field(model, closed_form_of(model))
    pendulum = split_ode_state(model.layout, jnp.asarray(model.initial_ode_state()))
    eps = np.finfo(float).eps
    for step in (rkmk4_step, crouch_grossman3_step):
        for f, state, h, n in ((free_body_field, fast, 0.01, 100_000), (field, pendulum, 0.002, 20_000)):
            R, _ = integrate(step, f, state, h, n)
            R = np.asarray(R)
            err = np.linalg.norm(R.T @ R - np.eye(3))
            print(step.__name__, n, "steps: |R^T R - I| =", err, "=", err / (np.sqrt(n) * eps), "x sqrt(n) eps")
            assert err < 20.0 * np.sqrt(n) * eps


# ------------------------------------------------------------------------------------------
# The wiring
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, order, evals", [("lie_rk4", 4, 4), ("crouch_grossman3", 3, 3)])
def test_declarations(name, order, evals):
    integ = get_integrator(name)
    assert integ.capabilities == frozenset({Capability.FIXED_STEP, Capability.GROUP_PRESERVING})
    assert integ.order == order and integ.orders is None and integ.evals_per_step == evals
    assert integ.implementation == "jax-compiled"


def test_solve_counts_evaluations_and_saves_the_carried_rotation():
    """The saved attitude is the carried R itself (no quaternion in between), orthogonal to
    round-off, and its energy and states agree with the ODE-state view of the same carry."""
    scene = scene_with_effects(FIXED, elements=3)
    tr = get_integrator("lie_rk4").solve(scene, t_end=0.32, dt=0.004, save_every=0.08)
    assert tr.ok, tr.reason
    assert tr.stats["steps"] == 80 and tr.stats["rhs_evals"] == 320
    assert tr.attitude_kind == "matrix" and tr.attitude.shape == (5, 3, 3)
    ortho = np.abs(np.einsum("nji,njk->nik", tr.attitude, tr.attitude) - np.eye(3)).max()
    assert 0.0 <= ortho < 1e-14
    ode = get_integrator("tsit5").solve(scene, t_end=0.32, dt=0.004, save_every=0.08)
    assert np.abs(tr.x - ode.x).max() < 1e-6  # same motion as a 5th-order method at the same step


def test_the_run_s_right_hand_side_drives_the_field(rng):
    """``rhs="autodiff"`` (``ode.f`` is the model's own ``ode_rhs``) drives the step with the
    autodiff model's accelerations, the default with the closed form: the two fields agree to
    round-off (the closed form is checked against autodiff in tests/test_closed_form.py)."""
    from reelbench.integrators import ODEProblem
    from reelbench.integrators._lie_group_steps import equations_of
    from reelbench.integrators.rhs import ode_rhs

    model = build_model(scene_with_effects(["elasticity", "gravity", "rigid_body", "reel", "carnot", "reel_control"],
                                           elements=2))
    fields = {}
    for rhs in ("closed_form", "autodiff"):
        equations = equations_of(ODEProblem(model=model, f=ode_rhs(model, rhs), layout=model.layout))
        assert equations is (model if rhs == "autodiff" else closed_form_of(model))
        fields[rhs] = jax.jit(pendulum_field(model, equations))
    y = np.asarray(model.initial_ode_state()) + 0.05 * rng.standard_normal(model.layout.ny)
    y[model.layout.y_quat] /= np.linalg.norm(y[model.layout.y_quat])
    R, v = split_ode_state(model.layout, jnp.asarray(y))
    (om_c, f_c), (om_a, f_a) = fields["closed_form"](0.1, R, v), fields["autodiff"](0.1, R, v)
    assert np.array_equal(np.asarray(om_c), np.asarray(om_a))
    assert np.abs(np.asarray(f_c) - np.asarray(f_a)).max() < 1e-11 * np.abs(np.asarray(f_a)).max()


@pytest.mark.parametrize("kw, match", [({"dt": 0.0}, "dt"), ({"dt": 1.0}, "larger than t_end"),
                                        ({"dt": 0.01, "newton_tol": 1e-9}, "unknown option")])
def test_bad_arguments_are_refused_before_any_work(kw, match):
    with pytest.raises(ValueError, match=match):
        get_integrator("lie_rk4").solve(scene_with_effects(FIXED, elements=3), t_end=0.5, **kw)
