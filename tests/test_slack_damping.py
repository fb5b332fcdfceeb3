"""The optional effects `slack` (tension-only elasticity) and `axial_damping` (Kelvin–Voigt
strain-rate damping): scenes, model terms against autodiff, the continuous equations, the
baselines and the LGVI.

Targeted combinations only (the all-combination sweeps of test_model / test_closed_form are not
multiplied by the new effects). Scenes are small (N = 4) and each compiled model is reused.
"""

import numpy as np
import pytest

from reelbench.integrators import get_integrator
from reelbench.integrators._lgvi_core import DiscreteLagrangian, cayley
from reelbench.integrators.lgvi import LGVI
from reelbench.models import EFFECTS, build_model, load_scene, scene_from_dict
from reelbench.models._jax import jax, jnp
from reelbench.models.closed_form import ClosedFormEOM
from reelbench.models.diagnostics import evaluate, summary
from reelbench.models.model import hat

from _helpers import random_state, reference_solution, scene_with_effects
from test_closed_form import _check
from test_lgvi import autodiff_momenta
from test_scene import assert_refused, base_dict

LGVI_ = LGVI()
ALL = ["elasticity", "gravity", "rigid_body", "reel", "carnot", "reel_control", "slack", "axial_damping"]
C_DAMP = 0.5  # N s


def damped(effects, c=C_DAMP, **kw):
    """`scene_with_effects` with the damping coefficient when the effect is listed."""
    if "axial_damping" in effects:
        kw["axial_damping"] = c
    return scene_with_effects(effects, **kw)


# ------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------
def test_effects_declared_and_depend_on_elasticity():
    assert EFFECTS["slack"].needs == ("elasticity",) and EFFECTS["axial_damping"].needs == ("elasticity",)
    s = load_scene("fixed_length", effects=["axial_damping", "gravity", "slack", "elasticity", "rigid_body"],
                   axial_damping=0.25)
    assert s.effects == ("gravity", "elasticity", "rigid_body", "slack", "axial_damping")
    assert s.string.axial_damping == 0.25 and s.to_dict()["string"]["axial_damping"] == 0.25
    assert scene_from_dict(s.to_dict()) == s
    # absent: no key in the validated scene, so existing scenes keep their key (hash)
    plain = load_scene("fixed_length")
    assert "axial_damping" not in plain.to_dict()["string"] and plain.string.axial_damping is None
    assert s.with_(effects=list(plain.effects), axial_damping=None).key() == plain.key()
    assert load_scene("fixed_length", effects=["gravity", "elasticity", "rigid_body", "slack"]).key() != plain.key()


@pytest.mark.parametrize("mutate, fragments", [
    (lambda d: d["effects"].append("axial_damping"), ["string.axial_damping", "missing", "axial_damping", ">= 0"]),
    (lambda d: (d["effects"].append("axial_damping"), d["string"].update(axial_damping=-0.1)),
     ["string.axial_damping", "-0.1", ">= 0"]),
    (lambda d: (d["effects"].append("axial_damping"), d["string"].update(axial_damping=float("nan"))),
     ["string.axial_damping", "finite"]),
    (lambda d: (d["effects"].append("axial_damping"), d["string"].update(axial_damping="1")),
     ["string.axial_damping", "finite"]),
    (lambda d: d["string"].update(axial_damping=0.5), ["string.axial_damping", "only allowed with effect 'axial_damping'"]),
    (lambda d: d.update(effects=["gravity", "slack"]), ["effects", "elasticity"]),
    (lambda d: d["effects"].append("slak"), ["slak", "did you mean 'slack'"]),
])
def test_invalid_new_keys_are_refused(mutate, fragments):
    d = base_dict("retrieval")
    mutate(d)
    assert_refused(d, fragments)


def test_zero_damping_is_valid():
    assert load_scene("retrieval", effects=ALL, axial_damping=0).string.axial_damping == 0.0


# ------------------------------------------------------------------------------------------
# Model terms against autodiff
# ------------------------------------------------------------------------------------------
def test_slack_potential_gradient_and_tensions(rng):
    model = build_model(damped(ALL, elements=3))
    n_slack = n_taut = 0
    for _ in range(3):
        x, R, _ = random_state(model, rng, scale=0.6)
        x, R = jnp.asarray(x), jnp.asarray(R)
        closed = model.potential_gradient(x, R)
        auto = jax.grad(model.potential, argnums=0)(x, R)
        if model.layout.has_attitude:
            auto = jnp.concatenate([auto, jax.grad(lambda e: model.potential(x, R @ (jnp.eye(3) + hat(e))))(jnp.zeros(3))])
        np.testing.assert_allclose(closed, auto, rtol=1e-11, atol=1e-10)
        q, l = np.asarray(model.nodes(x)), float(model.element_length(x))
        stretch = np.linalg.norm(np.diff(q, axis=0), axis=1)
        tens = np.asarray(model.tensions(x))
        np.testing.assert_array_equal(tens[stretch <= l], 0.0)
        np.testing.assert_allclose(tens[stretch > l], model.EA * (stretch[stretch > l] / l - 1), rtol=1e-12)
        n_slack += int(np.sum(stretch < l))
        n_taut += int(np.sum(stretch > l))
    assert n_slack and n_taut  # both branches were exercised


def test_compressed_element_has_no_elastic_energy_or_force():
    """Element 2 of 3 shortened to half its length: no energy, no force from it with `slack`."""
    effects = ["elasticity", "reel"]
    two, one = (build_model(scene_with_effects(e, elements=3)) for e in (effects, effects + ["slack"]))
    x, R, _ = two.initial_state()
    l = float(two.element_length(jnp.asarray(x)))
    e = np.array([1.0, 0.0, 0.0])
    q = np.array([1.2 * l * e, 1.7 * l * e, 2.9 * l * e])  # elements: 1.2 l, 0.5 l, 1.2 l
    x = jnp.asarray(np.concatenate([x[:1], q.ravel()]))
    R = jnp.eye(3)
    V2, V1 = float(two.potential(x, R)), float(one.potential(x, R))
    per_element = two.EA / (2 * l) * (0.2 * l) ** 2
    assert V1 == pytest.approx(2 * per_element, rel=1e-12)
    assert V2 == pytest.approx(2 * per_element + two.EA / (2 * l) * (0.5 * l) ** 2, rel=1e-12)
    np.testing.assert_array_equal(np.asarray(one.tensions(x))[1], 0.0)
    g1 = np.asarray(one.potential_gradient(x, R))[1:].reshape(3, 3)
    # node 2 is pulled back by element 1 only, node 3 forward by element 3 only (elastic part)
    f = two.EA * 0.2
    np.testing.assert_allclose(g1[0], [f, 0, 0], rtol=1e-12)
    np.testing.assert_allclose(g1[1], [-f, 0, 0], rtol=1e-12)
    # and the closed-form continuous EOM sees the same (no force across the slack element)
    cf = ClosedFormEOM(one)
    w = jnp.zeros(one.layout.nw)
    F = np.asarray(cf.force(0.0, x, R, w))
    np.testing.assert_allclose(F[1:], -np.asarray(g1).ravel(), rtol=1e-12)


def _strain(model, x):
    q, l = model.nodes(x), model.element_length(x)
    return jnp.linalg.norm(q[1:] - q[:-1], axis=1) / l - 1.0


@pytest.mark.parametrize("effects", [["elasticity", "axial_damping"], ["elasticity", "rigid_body", "reel", "axial_damping"]],
                         ids="+".join)
def test_damping_force_is_minus_gradient_of_rayleigh_function(effects, rng):
    """Q = −∂D/∂w with D = Σ_a (c l/2) ε̇_a², ε̇ = (∂ε/∂x) ẋ by autodiff; power = −2D ≤ 0."""
    model = build_model(damped(effects, elements=4))
    nx = model.layout.nx
    for _ in range(3):
        x, _, w = random_state(model, rng, scale=0.5)
        x, w = jnp.asarray(x), jnp.asarray(w)

        def D(w_):
            _, rate = jax.jvp(lambda x_: _strain(model, x_), (x,), (w_[:nx],))
            return 0.5 * C_DAMP * model.element_length(x) * jnp.sum(rate**2)

        np.testing.assert_allclose(model.strain_rates(x, w), jax.jvp(lambda x_: _strain(model, x_), (x,), (w[:nx],))[1],
                                   rtol=1e-12)
        Q = model.generalized_force(0.1, x, w)
        np.testing.assert_allclose(Q, -jax.grad(D)(w), rtol=1e-12, atol=1e-14)
        assert float(model.power(0.1, x, w)) == pytest.approx(-2 * float(D(w)), rel=1e-12) and float(D(w)) > 0


@pytest.mark.parametrize("effects", [["elasticity", "gravity", "slack", "axial_damping"], ALL], ids="+".join)
def test_closed_form_eom_matches_autodiff(effects, rng):
    """The hand-derived EOM (models.closed_form) with the new effects = autodiff of the Lagrangian + Q."""
    model = build_model(damped(effects, elements=2))
    _check(model, [ClosedFormEOM(model)], rng)


# ------------------------------------------------------------------------------------------
# Slack in a run: all elements stretched -> identical to the two-sided law
# ------------------------------------------------------------------------------------------
TAUT = dict(elements=4, tip_velocity=[1.0, 0.5, 2.0], angular_velocity=[0.0, 0.0, 0.0], direction=[0.3, 0.0, 1.0],
            t_end=0.6)


@pytest.fixture(scope="module")
def taut_runs():
    """LGVI runs (h = 5 ms, 0.6 s) of a point-mass scene whose tip is thrown outwards."""
    runs = {}
    for extra in ([], ["slack"], ["axial_damping"]):
        scene = load_scene("fixed_length", effects=["gravity", "elasticity"] + extra, **TAUT,
                           **({"axial_damping": 0.0} if extra == ["axial_damping"] else {}))
        runs[tuple(extra)] = LGVI_.solve(scene, dt=0.005, save_every=0.005)
    return runs


def test_slack_scene_that_stays_taut_equals_two_sided(taut_runs):
    """Every element is stretched for t > 0 (checked), so `slack` changes nothing."""
    two, slack = taut_runs[()], taut_runs[("slack",)]
    assert two.ok and slack.ok
    n = len(two.t)
    q = np.concatenate([np.zeros((n, 1, 3)), two.x.reshape(n, 4, 3)], axis=1)
    extension = np.linalg.norm(np.diff(q, axis=1), axis=2) - 2.5
    assert extension[1:].min() > 1e-3  # taut at every step after the first (t = 0: straight, unstretched)
    np.testing.assert_allclose(slack.x, two.x, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(slack.momentum, two.momentum, rtol=1e-12, atol=1e-12)


def test_damping_zero_equals_no_damping(taut_runs, rng):
    """c = 0 with the effect listed: the same LGVI run (W = 0), the same ODE right-hand side (plus W' = 0)."""
    two, zero = taut_runs[()], taut_runs[("axial_damping",)]
    assert zero.ok
    np.testing.assert_allclose(zero.x, two.x, rtol=1e-13, atol=1e-14)
    # atol 1e-13 on momenta of order 1: the two runs are different compiled programs, and with the XLA
    # small-loop option (models/_jax.py) their fused loops may round differently (measured: 1.9e-14)
    np.testing.assert_allclose(zero.momentum, two.momentum, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(zero.work, 0.0)
    eff = ["gravity", "elasticity", "rigid_body", "reel", "carnot"]
    plain = build_model(scene_with_effects(eff, elements=3))
    damp0 = build_model(scene_with_effects(eff + ["axial_damping"], elements=3, axial_damping=0.0))
    assert plain.layout == damp0.layout  # W is already in the state (Carnot)
    y = jnp.asarray(plain.initial_ode_state() + 0.1 * rng.standard_normal(plain.layout.ny))
    np.testing.assert_array_equal(ClosedFormEOM(damp0).ode_rhs(0.3, y), ClosedFormEOM(plain).ode_rhs(0.3, y))


# ------------------------------------------------------------------------------------------
# Damping in a run: baselines through model.ode_rhs, E − W, monotone E
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fixed_damped():
    """fixed_length (rigid body, gravity) with axial damping, N = 4, 1 s."""
    return load_scene("fixed_length", elements=4, t_end=1.0, axial_damping=C_DAMP,
                      effects=["gravity", "elasticity", "rigid_body", "axial_damping"])


@pytest.fixture(scope="module")
def fixed_damped_dop853(fixed_damped):
    return get_integrator("dop853").solve(fixed_damped, rtol=1e-10, atol=1e-10, save_every=0.02)


def test_damped_dop853_conserves_energy_minus_work_and_dissipates(fixed_damped, fixed_damped_dop853):
    tr = fixed_damped_dop853
    assert tr.ok, tr.reason
    df = evaluate(fixed_damped, tr)
    s = summary(df, has_work=True)
    print("DOP853 rtol 1e-10: |Δ(E−W)|/max T", s["energy_error"], "W(1 s)", df.work.iloc[-1])
    assert s["energy_error"] < 1e-8  # measured 7.6e-12
    assert s["pi3_error"] < 1e-9  # measured 5e-12: the damping forces are internal and central
    assert df.work.iloc[-1] < -0.05  # measured -0.105 J
    # dissipation >= 0: W and E non-increasing (to the tolerance)
    tol = 1e-9 * abs(df.energy.iloc[0])
    assert np.all(np.diff(df.work) <= tol) and np.all(np.diff(df.energy) <= tol)
    assert df.energy.iloc[-1] < df.energy.iloc[0] - 0.05


# ------------------------------------------------------------------------------------------
# LGVI with damping
# ------------------------------------------------------------------------------------------
def _tip(scene, tr):
    return tr.x[-1][build_model(scene).layout.nodes][-3:]


def test_lgvi_damped_converges_second_order_and_conserves_energy_minus_work(fixed_damped):
    ref = reference_solution(fixed_damped, 1.0, rtol=1e-12, atol=1e-12, n_save=2)
    hs = [0.002, 0.001, 0.0005]
    errs, ew, dW = [], [], []
    for h in hs:
        tr = LGVI_.solve(fixed_damped, dt=h, save_every=0.05)
        assert tr.ok
        df = evaluate(fixed_damped, tr)
        errs.append(np.linalg.norm(_tip(fixed_damped, tr) - ref.x[-1][build_model(fixed_damped).layout.nodes][-3:]))
        s = summary(df, has_work=True)
        ew.append(s["energy_error"])
        dW.append(abs(df.work.iloc[-1] - ref.work[-1]))  # the dissipated work W(1 s) against DOP853's (-0.1054 J)
        # internal central forces: π3 is still conserved, to round-off (measured 7e-15 relative)
        assert s["pi3_error"] < 1e-12 and s["orthogonality_error"] < 1e-13
    errs, ew, dW = np.array(errs), np.array(ew), np.array(dW)
    orders, ew_orders, w_orders = (np.log2(e[:-1] / e[1:]) for e in (errs, ew, dW))
    print("LGVI damped fixed length: tip errors", errs, "orders", orders, "|Δ(E−W)|/max T", ew, "orders", ew_orders,
          "|W - W_ref|", dW, "orders", w_orders)
    # measured: tip errors 2.3e-5, 5.8e-6, 1.5e-6 (orders 2.00, 2.00); E−W 3.6e-6, 8.9e-7, 2.2e-7 (2.00, 2.00);
    # W(1 s) 3.6e-6, 8.9e-7, 2.2e-7 J (2.01, 2.00)
    assert np.all(np.abs(orders - 2.0) < 0.15) and np.all(np.abs(ew_orders - 2.0) < 0.2)
    assert np.all(np.abs(w_orders - 2.0) < 0.2)
    assert ew[0] < 1e-5


def test_lgvi_damped_reel_energy_minus_work(rng):
    """Deployment with slack and damping: E − W conserved to discretization error (first order)."""
    scene = load_scene("deployment", elements=4, effects=["gravity", "elasticity", "rigid_body", "reel", "carnot",
                                                          "slack", "axial_damping"], axial_damping=C_DAMP)
    ew = {}
    for h in (0.002, 0.001):
        tr = LGVI_.solve(scene, t_end=0.5, dt=h, save_every=0.05)
        assert tr.ok, tr.reason
        df = evaluate(scene, tr)
        ew[h] = summary(df, has_work=True)["energy_error"]
        assert df.work.iloc[-1] < 0 and np.all(np.diff(df.work) <= 0)
        assert np.abs(df.pi3).max() < 1e-10  # π3(0) = 0 (at rest), kept by the damping
    print("LGVI damped deployment |Δ(E−W)|/max T", ew)  # measured 5.2e-5 (2 ms), 2.2e-5 (1 ms)
    assert ew[0.002] < 1e-4 and ew[0.001] < 0.6 * ew[0.002]


@pytest.mark.parametrize("effects", [["elasticity", "gravity", "rigid_body", "slack", "axial_damping"], ALL],
                         ids=["fixed", "reel"])
def test_lgvi_closed_form_matches_autodiff_forced_discrete_lagrangian(effects, rng):
    """p_k, p_{k+1} of the closed form (with slack in V and the explicit damping forcing) = autodiff
    of L_d plus f⁻ = (h/2) Q(x_k, M_k⁻¹ p_k), f⁺ = (h/2) Q(x_{k+1}, 2Δx/h − ẋ_k); the reduced
    Newton residual vanishes at the step."""
    model = build_model(damped(effects, elements=3))
    lay, dl, h = model.layout, DiscreteLagrangian(model), 0.01
    nx = lay.nx
    x, R, w = random_state(model, rng, scale=0.6)
    x, R, w = jnp.asarray(x), jnp.asarray(R), jnp.asarray(w)
    assert np.min(np.asarray(model.tensions(x))) == 0.0  # some element slack
    dx = jnp.asarray(h * w[:nx] + 1e-3 * rng.standard_normal(nx))
    c = jnp.asarray(0.02 * rng.standard_normal(3))
    F = cayley(c)
    auto_k, auto_k1 = autodiff_momenta(model, h, 0.3, x, R, dx, F)  # conservative + reel forces
    # p_k = auto_k − (h/2) Q(x_k, w_k), p_k = M w_k, Q = K w linear in w: (M + (h/2) K) w_k = auto_k
    M = np.asarray(model.mass_matrix(x, R))
    K = np.asarray(jax.jacfwd(lambda w_: model.string_force(0.3, x, w_))(w))
    wk = jnp.asarray(np.linalg.solve(M + h / 2 * K, auto_k))
    p_k = jnp.asarray(M @ np.asarray(wk))
    np.testing.assert_allclose(p_k, auto_k - h / 2 * np.asarray(model.string_force(0.3, x, wk)), atol=1e-13)
    w1 = jnp.concatenate([2 * dx / h - wk[:nx], wk[nx:]])
    p_k1 = jnp.asarray(auto_k1) + h / 2 * model.string_force(0.3 + h, x + dx, w1)
    ctx = dl.context(0.3, x, R, model.potential_gradient(x, R), p_k)
    ds = dx[0] if lay.has_reel else 0.0
    dq = dx[lay.nodes].reshape(model.N, 3)
    cf_k = np.asarray(dl.hp_k_full(ctx, h, ds, dq, c)) / h
    cf_k1 = np.asarray(dl.hp_k1(ctx, h, ds, dq, c, model.potential_gradient(x + dx, R @ F))) / h
    scale = np.max(np.abs(auto_k)) + np.max(np.abs(auto_k1))
    assert np.max(np.abs(np.asarray(p_k) - auto_k)) > 1e-6 * scale  # the forcing is not negligible
    assert np.max(np.abs(cf_k - np.asarray(p_k))) < 1e-10 * scale
    assert np.max(np.abs(cf_k1 - np.asarray(p_k1))) < 1e-10 * scale
    z = dl.pack_z(ds, c)
    uv = None if lay.has_reel else dl.string_solve(ctx, p_k[lay.nodes].reshape(-1, 3), h, 0.0)
    r, _, dq_red = dl.reduced_system(ctx, p_k, h, z, uv)
    assert np.max(np.abs(np.asarray(r))) < 1e-12 * scale
    np.testing.assert_allclose(dq_red, dq, atol=1e-12)
    # work of the step: reel forcing Q_k Δs + ½ (Q⁻ + Q⁺)·Δx
    Qm, Qp = model.string_force(0.3, x, wk), model.string_force(0.3 + h, x + dx, w1)
    expect = float(dl.forcing(ctx, ds, h) * ds + 0.5 * (Qm + Qp)[:nx] @ dx)
    assert float(dl.work(ctx, h, ds, dq)) == pytest.approx(expect, rel=1e-12)


def test_lgvi_context_needs_momentum_with_damping():
    model = build_model(damped(["elasticity", "axial_damping"], elements=2))
    x, R, _ = model.initial_state()
    with pytest.raises(ValueError, match="p_k"):
        DiscreteLagrangian(model).context(0.0, jnp.asarray(x), jnp.asarray(R), model.potential_gradient(x, R))


def _damping_rate_max(model):
    """γ_max: largest eigenvalue of M⁻¹ K_d, K_d = −∂Q/∂w, at the initial state."""
    x, R, w = (jnp.asarray(a) for a in model.initial_state())
    M = np.asarray(model.mass_matrix(x, R))
    K = -np.asarray(jax.jacfwd(lambda w_: model.string_force(0.0, x, w_))(w))
    return float(np.max(np.real(np.linalg.eigvals(np.linalg.solve(M, K)))))


def test_lgvi_explicit_damping_stability_limit():
    """The explicit forcing is stable for h γ_max < 2 (documented limit), unstable above it."""
    h = 0.005
    base = dict(elements=4, effects=["gravity", "elasticity", "axial_damping"], angular_velocity=[0.0, 0.0, 0.0])
    gamma_per_c = _damping_rate_max(build_model(load_scene("fixed_length", axial_damping=1.0, **base)))
    assert gamma_per_c < 12 / (0.05 * 2.5**2)  # the consistent-mass bound 12 c/(μ l²)
    drift = {}
    for hg in (1.8, 2.2):
        scene = load_scene("fixed_length", axial_damping=hg / (h * gamma_per_c), **base)
        tr = LGVI_.solve(scene, t_end=1.5, dt=h, save_every=0.1)
        df = evaluate(scene, tr)
        ew = df.energy_minus_work.to_numpy()
        drift[hg] = (tr.status, float(np.nanmax(np.abs(ew - ew[0]))) if np.all(np.isfinite(ew)) else np.inf)
    # measured: 1.8 -> ok, 5e-4 J; 2.2 -> the energy guard stops it "diverged" (7.3 J in the kept prefix;
    # unguarded it reached 1e43 J)
    print("h γ_max -> (status, max |Δ(E−W)|)", drift)
    assert drift[1.8][0] == "ok" and drift[1.8][1] < 1e-2  # 1e-2 J: 20x the measured bounded oscillation
    assert drift[2.2][0] == "diverged"
