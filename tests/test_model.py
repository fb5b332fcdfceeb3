"""The continuous model: closed-form pieces vs autodiff, conservation laws, analytic cases."""

import numpy as np
import pytest

from reelbench.models import build_model, load_scene
from reelbench.models._jax import jax, jnp
from reelbench.models.diagnostics import evaluate, summary
from reelbench.models.model import hat, quat_to_rot, rot_to_quat
from reelbench.integrators.base import Trajectory

from _helpers import effect_combinations, random_state, reference_solution, scene_with_effects


@pytest.mark.parametrize("effects", effect_combinations(), ids=lambda e: "+".join(e))
def test_closed_form_potential_gradient_matches_autodiff(effects, rng):
    model = build_model(scene_with_effects(effects))
    for _ in range(3):
        x, R, w = random_state(model, rng)
        x, R = jnp.asarray(x), jnp.asarray(R)
        closed = model.potential_gradient(x, R)
        auto = jax.grad(model.potential, argnums=0)(x, R)
        if model.layout.has_attitude:
            d_eta = jax.grad(lambda e: model.potential(x, R @ (jnp.eye(3) + hat(e))))(jnp.zeros(3))
            auto = jnp.concatenate([auto, d_eta])
        np.testing.assert_allclose(closed, auto, rtol=1e-11, atol=1e-10)


@pytest.mark.parametrize("effects", effect_combinations(), ids=lambda e: "+".join(e))
def test_state_layout_follows_effects(effects):
    model = build_model(scene_with_effects(effects, elements=4))
    lay = model.layout
    assert lay.nx == ("reel" in effects) + 12
    assert lay.nw == lay.nx + 3 * ("rigid_body" in effects)
    assert lay.ny == lay.nx + lay.nw + 4 * ("rigid_body" in effects) + (("carnot" in effects) or ("reel_control" in effects))
    assert ("V_reel" in model.potential_terms) == ("reel" in effects and "gravity" in effects)
    assert ("V_body_gravity" in model.potential_terms) == ("gravity" in effects)
    assert model.initial_ode_state().shape == (lay.ny,)
    # mass matrix symmetric positive definite
    x, R, w = model.initial_state()
    M = np.asarray(model.mass_matrix(jnp.asarray(x), jnp.asarray(R)))
    np.testing.assert_allclose(M, M.T, atol=1e-14)
    assert np.linalg.eigvalsh(M).min() > 0


def test_initial_state_is_straight_and_unstretched():
    scene = load_scene("fixed_length")
    model = build_model(scene)
    x, R, w = model.initial_state()
    q = np.asarray(model.nodes(jnp.asarray(x)))
    np.testing.assert_allclose(np.linalg.norm(q[-1]), 10.0)
    np.testing.assert_allclose(np.linalg.norm(np.diff(q, axis=0), axis=1), 1.0)
    assert float(model.potential_terms["V_elastic"](jnp.asarray(x), jnp.asarray(R))) < 1e-20
    # the fixed-length scene's initial energy, E ≈ -85.54 J (paper's scene, N = 10)
    assert abs(float(model.energy(jnp.asarray(x), jnp.asarray(R), jnp.asarray(w))) + 85.54) < 0.01


def test_quaternion_round_trip(rng):
    for _ in range(5):
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        R = np.asarray(quat_to_rot(q))
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(np.asarray(quat_to_rot(rot_to_quat(R))), R, atol=1e-14)


@pytest.fixture(scope="module")
def fixed_reference():
    scene = load_scene("fixed_length", elements=4, t_end=1.0)
    return scene, reference_solution(scene, 1.0, rtol=1e-11, atol=1e-12)


def test_energy_and_pi3_conserved_by_continuous_eom(fixed_reference):
    scene, traj = fixed_reference
    df = evaluate(scene, traj)
    m = summary(df, has_work=False)
    assert m["energy_error"] < 1e-8, m
    assert m["pi3_error"] < 1e-8, m
    assert np.all(np.isfinite(df.to_numpy()))
    # something actually happens: the body swings and the string stretches
    assert df["kinetic"].max() > 1.0 and df["stretched_length"].max() > 10.05


@pytest.mark.parametrize("name", ["deployment", "retrieval"])
def test_energy_minus_work_conserved_with_reel(name):
    scene = load_scene(name, elements=4)
    traj = reference_solution(scene, 0.6, rtol=1e-11, atol=1e-12)
    df = evaluate(scene, traj)
    m = summary(df, has_work=True)
    assert m["energy_error"] < 1e-8, m
    assert m["pi3_error"] < 1e-8 or abs(df["pi3"].iloc[0]) < 1e-12, m
    assert abs(df["work"].iloc[-1]) > 1e-6  # the forces did work
    assert abs(df["deployed_length"].iloc[-1] - df["deployed_length"].iloc[0]) > 0.05  # the reel moved
    if name == "deployment":
        assert df["work"].iloc[-1] < 0  # Carnot loss only dissipates


def test_diagnostics_same_from_momenta_and_matrices(fixed_reference):
    scene, traj = fixed_reference
    model = build_model(scene)
    quat = traj.attitude / np.linalg.norm(traj.attitude, axis=1, keepdims=True)
    Rs = np.stack([np.asarray(quat_to_rot(q)) for q in quat])
    p = np.stack([np.asarray(model.momentum(jnp.asarray(x), jnp.asarray(R), jnp.asarray(w)))
                  for x, R, w in zip(traj.x, Rs, traj.velocity)])
    other = Trajectory(t=traj.t, x=traj.x, attitude=Rs, attitude_kind="matrix", velocity=None, momentum=p, work=traj.work)
    a, b = evaluate(scene, traj), evaluate(scene, other)
    for col in ["energy", "pi3", "body_x", "omega_2", "stretched_length"]:
        np.testing.assert_allclose(a[col], b[col], rtol=1e-7, atol=1e-9)


def _crossing_times(t, z):
    """Times of upward zero crossings of a sampled signal (linear interpolation)."""
    i = np.nonzero((z[:-1] < 0) & (z[1:] >= 0))[0]
    return t[i] - z[i] * (t[i + 1] - t[i]) / (z[i + 1] - z[i])


def test_single_element_spring_frequency():
    """N = 1, point mass, no gravity, vertical: ω² = EA / (l (m_b + μ l / 3))."""
    EA, l, mb, mu = 200.0, 2.0, 1.0, 0.05
    scene = load_scene("fixed_length", effects=["elasticity"], elements=1, deployed_length=l,
                       direction=[0, 0, 1], tip_velocity=[0, 0, 0.01], angular_velocity=[0, 0, 0])
    omega = np.sqrt(EA / (l * (mb + mu * l / 3)))
    period = 2 * np.pi / omega
    traj = reference_solution(scene, 3.2 * period, n_save=4001, rtol=1e-12, atol=1e-14)
    z = traj.x[:, 2] - l
    crossings = _crossing_times(traj.t, z)
    measured = np.mean(np.diff(crossings))
    assert abs(measured / period - 1) < 1e-6, (measured, period)


def test_stiff_light_string_is_a_simple_pendulum():
    """Small swing of a point mass on a stiff, light string: period → 2π √(ℓ/g)."""
    ell, g, theta = 2.0, 9.81, 0.02
    # N = 1: no light interior node, whose axial mode would make the ODE needlessly stiff
    scene = load_scene("fixed_length", effects=["gravity", "elasticity"], elements=1, deployed_length=ell,
                       axial_stiffness=4e4, mass_per_length=1e-4, direction=[np.sin(theta), 0, np.cos(theta)],
                       tip_velocity=[0, 0, 0], angular_velocity=[0, 0, 0])
    period = 2 * np.pi * np.sqrt(ell / g)
    traj = reference_solution(scene, 2.6 * period, n_save=3001, rtol=1e-10, atol=1e-12)
    crossings = _crossing_times(traj.t, traj.x[:, -3])
    measured = np.mean(np.diff(crossings))
    assert abs(measured / period - 1) < 1e-3, (measured, period)


def test_quat_to_rot_many_is_quat_to_rot_bit_for_bit():
    """The host's batched twin (the metrics' attitude matrices) equals the JAX formula exactly,
    unit and non-unit quaternions (the baselines' are not renormalised)."""
    from reelbench.models.model import quat_to_rot_many

    q = np.random.default_rng(3).normal(size=(50, 4))
    q[:25] /= np.linalg.norm(q[:25], axis=1, keepdims=True)
    expected = np.stack([np.asarray(quat_to_rot(row)) for row in q])
    assert np.array_equal(quat_to_rot_many(q), expected)
    assert quat_to_rot_many(np.zeros((0, 4))).shape == (0, 3, 3)
