"""The lumped-mass string (`string.mass_model = "lumped"`, docs/equations.md, "Lumped-mass string"): scene key, energy,
closed form vs autodiff, the LGVI's discrete equations, order and energy, and the consistent
and lumped models converging to each other as N grows."""

import numpy as np
import pytest

from reelbench.integrators._lgvi_core import DiscreteLagrangian, cayley
from reelbench.integrators.lgvi import LGVI
from reelbench.models import SceneError, build_model, load_scene
from reelbench.models._jax import jax, jnp
from reelbench.models.closed_form import ClosedFormEOM
from reelbench.models.diagnostics import evaluate, summary
from reelbench.models.model import STRING_MASS

from _helpers import reference_solution
from test_lgvi import autodiff_momenta

POINT = dict(effects=["elasticity", "gravity"], angular_velocity=[0.0, 0.0, 0.0])
BODY = dict(effects=["elasticity", "gravity", "rigid_body"])


def lumped(elements=4, body=True, **kw):
    return load_scene("fixed_length", elements=elements, mass_model="lumped", **(BODY if body else POINT), **kw)


# ------------------------------------------------------------------------------------------
# Scene key
# ------------------------------------------------------------------------------------------
def test_mass_model_key_default_validation_and_hash():
    base = load_scene("fixed_length")
    assert base.string.mass_model == "consistent"
    # the default is left out of the physics hash: existing results keep their keys
    assert load_scene("fixed_length", mass_model="consistent").key() == base.key()
    lump = load_scene("fixed_length", mass_model="lumped")
    assert lump.string.mass_model == "lumped" and lump.key() != base.key()
    for bad in ("lumpy", 1, "Lumped"):
        with pytest.raises(SceneError, match=r"string\.mass_model.*'consistent', 'lumped'"):
            load_scene("fixed_length", mass_model=bad)
    # the lumped string's axial-flow terms are not derived: refused with a reel
    with pytest.raises(SceneError, match=r"string\.mass_model' = 'lumped' is not available with effect 'reel'"):
        load_scene("deployment", mass_model="lumped")
    assert load_scene("deployment", mass_model="consistent").key() == load_scene("deployment").key()


# ------------------------------------------------------------------------------------------
# Continuous model
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("body", [False, True], ids=["point_mass", "rigid_body"])
def test_lumped_kinetic_energy_and_mass_matrix(body, rng):
    """T_str = Σ_a (μl/4)(|q̇_a|² + |q̇_{a+1}|²): M's string block is diag(μl, …, μl, μl/2 + m_b)."""
    model = build_model(lumped(body=body))
    N, mu = model.N, model.mu
    l = model.scene.initial.deployed_length / N
    x, R, w = model.initial_state()
    w = w + rng.standard_normal(w.shape)
    v = np.concatenate([np.zeros((1, 3)), w[model.layout.nodes].reshape(N, 3)])
    expected = np.sum(mu * l / 4 * (np.sum(v[:-1] ** 2, 1) + np.sum(v[1:] ** 2, 1)))
    assert float(model._T_string(jnp.asarray(x), jnp.asarray(R), jnp.asarray(w))) == pytest.approx(expected, rel=1e-14)
    M = np.asarray(model.mass_matrix(jnp.asarray(x), jnp.asarray(R)))
    diag = np.repeat(np.r_[np.full(N - 1, mu * l), mu * l / 2 + model.m_b], 3)
    nod = model.layout.nodes
    np.testing.assert_allclose(M[nod, nod], np.diag(diag), rtol=1e-14, atol=1e-15)
    # consistent stays the consistent linear element
    assert STRING_MASS["consistent"].o / STRING_MASS["consistent"].den == 1.0 / 6.0


@pytest.mark.parametrize("body", [False, True], ids=["point_mass", "rigid_body"])
def test_lumped_closed_form_matches_autodiff(body, rng):
    """Closed-form M, p and ẏ (structured and dense solves) = the autodiff path, lumped mass."""
    model = build_model(lumped(body=body))
    cf = ClosedFormEOM(model)
    lay = model.layout
    ref = jax.jit(lambda t, y: (model.mass_matrix(*model.split_state(y)[:2]),
                                model.momentum(*model.split_state(y)[:3]), model.ode_rhs(t, y)))
    for k in range(2):
        y = model.initial_ode_state().copy()
        y[lay.y_x] += 0.2 * rng.standard_normal(lay.nx)
        y[lay.y_w] += rng.standard_normal(lay.nw)
        if lay.has_attitude:  # a drifted quaternion too (the baselines do not renormalise)
            quat = rng.standard_normal(4)
            y[lay.y_quat] = quat / np.linalg.norm(quat) * (1.03 if k else 1.0)
        y = jnp.asarray(y)
        M_a, p_a, rhs_a = (np.asarray(a) for a in ref(0.4, y))
        x, R, w, _ = model.split_state(y)
        for a, c in ((M_a, cf.mass_matrix(x, R)), (p_a, cf.momentum(x, R, w)), (rhs_a, cf.ode_rhs(0.4, y)),
                     (rhs_a[-lay.nw:], cf.accelerations_dense(0.4, x, R, w))):
            assert np.abs(a - np.asarray(c)).max() <= 1e-11 * np.abs(a).max()


# ------------------------------------------------------------------------------------------
# LGVI
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("body", [False, True], ids=["point_mass", "rigid_body"])
def test_lgvi_lumped_discrete_equations_match_autodiff(body, rng):
    model = build_model(lumped(body=body))
    lay, dl, h = model.layout, DiscreteLagrangian(model), 0.01
    x, R, w = model.initial_state()
    x = jnp.asarray(x + 0.2 * rng.standard_normal(x.shape))
    R = jnp.asarray(R)
    dx = jnp.asarray(h * w[: lay.nx] + 1e-3 * rng.standard_normal(lay.nx))
    c = jnp.asarray(0.02 * rng.standard_normal(3)) if body else jnp.zeros(3)
    F = cayley(c) if body else jnp.eye(3)
    auto_k, auto_k1 = autodiff_momenta(model, h, 0.0, x, R, dx, F)  # the model's own T_string (lumped)
    ctx = dl.context(0.3, x, R, model.potential_gradient(x, R))
    dq = dx.reshape(model.N, 3)
    cf_k = np.asarray(dl.hp_k_full(ctx, h, 0.0, dq, c)) / h
    cf_k1 = np.asarray(dl.hp_k1(ctx, h, 0.0, dq, c, model.potential_gradient(x + dx, R @ F))) / h
    scale = np.abs(auto_k).max() + np.abs(auto_k1).max()
    assert np.abs(cf_k - auto_k).max() < 1e-10 * scale
    assert np.abs(cf_k1 - auto_k1).max() < 1e-10 * scale


@pytest.fixture(scope="module")
def lumped_body():
    return lumped(elements=5, body=True)


def test_lgvi_lumped_second_order_and_energy(lumped_body):
    """Fixed length, rigid body, lumped mass: order 2 on the body position against DOP853, and
    bounded energy error that scales as h² (as for the consistent mass)."""
    scene = lumped_body
    ref = reference_solution(scene, 1.0, rtol=1e-12, atol=1e-12, n_save=2)
    nod = build_model(scene).layout.nodes
    errs, energy = [], []
    for h in (0.002, 0.001, 0.0005):
        tr = LGVI().solve(scene, t_end=1.0, dt=h, save_every=0.05)
        assert tr.ok
        errs.append(np.linalg.norm(tr.x[-1][nod][-3:] - ref.x[-1][nod][-3:]))
        energy.append(summary(evaluate(scene, tr), has_work=False)["energy_error"])
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    e_orders = np.log2(np.array(energy[:-1]) / np.array(energy[1:]))
    print("lumped LGVI errors", errs, "orders", orders, "energy", energy, "orders", e_orders)
    assert np.all(np.abs(orders - 2.0) < 0.15)
    assert np.all(np.abs(e_orders - 2.0) < 0.3) and energy[0] < 1e-4


# ------------------------------------------------------------------------------------------
# Consistent and lumped converge to the same continuum solution
# ------------------------------------------------------------------------------------------
@pytest.mark.slow  # the same convergence is measured by `python -m benchmark xval`
def test_consistent_and_lumped_converge_to_each_other():
    """Tip position at t = 1 s: the gap between the two mass models falls ≈ 4× per doubling of N
    (measured 0.062, 0.019, 0.0035 m at N = 4, 8, 16; 9 s)."""
    gaps = []
    for N in (4, 8, 16):
        tips = []
        for mm in ("consistent", "lumped"):
            scene = load_scene("fixed_length", elements=N, mass_model=mm, t_end=1.0)
            ref = reference_solution(scene, 1.0, rtol=1e-11, atol=1e-12, n_save=2)
            tips.append(ref.x[-1][-3:])
        gaps.append(np.linalg.norm(tips[0] - tips[1]))
    ratios = np.array(gaps[:-1]) / np.array(gaps[1:])
    print("consistent - lumped gap", gaps, "ratios", ratios)
    assert np.all(ratios > 2.5) and gaps[0] / gaps[-1] > 10.0


def test_baselines_follow_the_lumped_mass():
    """The baselines integrate the model's RHS: DOP853 (the plugin) on the lumped scene equals
    solve_ivp on the lumped model, and differs from the consistent one."""
    from reelbench.integrators import get_integrator

    scene = lumped(elements=3, body=False, t_end=0.3)
    tr = get_integrator("dop853").solve(scene, t_end=0.3, rtol=1e-11, atol=1e-12, save_every=0.3)
    assert tr.ok
    ref = reference_solution(scene, 0.3, rtol=1e-11, atol=1e-12, n_save=2)
    cons = reference_solution(scene.with_(mass_model="consistent"), 0.3, rtol=1e-11, atol=1e-12, n_save=2)
    assert np.abs(tr.x[-1] - ref.x[-1]).max() < 1e-8
    assert np.abs(cons.x[-1] - ref.x[-1]).max() > 1e-3
