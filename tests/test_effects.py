"""Generic checks over the effect registry (models/effects.py): whatever effect is registered,
its closed-form potential gradients equal autodiff of its energies, its forces deliver the power
it claims (≤ 0 when it says it is dissipative), and its declarations are consistent.

`check_effect` is also run on the effects that tests/test_effect_plugin.py registers.
"""

import numpy as np
import pytest

from reelbench.models import EFFECTS, build_model, load_scene
from reelbench.models._jax import jax, jnp
from reelbench.models.model import hat

from _helpers import random_state, scene_with_effects


def closure(names):
    """``names`` with everything they need, plus elasticity, in canonical order."""
    out, todo = set(), list(names) + [n for n, e in EFFECTS.items() if e.required]
    while todo:
        n = todo.pop()
        if n not in out:
            out.add(n)
            todo.extend(EFFECTS[n].needs)
    return [n for n in EFFECTS if n in out]


BUILTIN_FULL = ["gravity", "elasticity", "rigid_body", "reel", "carnot", "reel_control", "slack", "axial_damping",
                "buoyancy", "drag"]


def scenes_for(name, **extra):
    """A minimal scene with effect ``name`` and a full one (every built-in effect, body and reel)."""
    out = []
    for names in (closure([name]), closure(BUILTIN_FULL + [name])):
        kw = {"axial_damping": 0.3} if "axial_damping" in names else {}
        kw.update(extra)
        out.append(scene_with_effects(names, elements=3, **kw))
    if name in ("buoyancy", "drag"):  # the lumped string takes the fluid forces per node (MoorDyn's)
        out.append(scene_with_effects(closure([name]), elements=3, mass_model="lumped", **extra))
    if name == "buoyancy":  # a rigid body with an offset centre of mass (and of buoyancy): a moment, −∂V/∂η
        out.append(scene_with_effects(closure(["rigid_body", name]), elements=3, attachment_to_com=[0.2, -0.1, 0.3],
                                      **extra))
    if name == "drag":  # a rigid body with an offset centre of mass: the body's drag is a body load
        out.append(scene_with_effects(closure(["rigid_body", name]), elements=3, attachment_to_com=[0.2, -0.1, 0.3],
                                      **extra))
    return out


def autodiff_gradient(model, V, x, R):
    """∂V over w's layout by autodiff; the Ω slot is the derivative along R(I + η^)."""
    g = jax.grad(V, argnums=0)(x, R)
    if model.layout.has_attitude:
        g = jnp.concatenate([g, jax.grad(lambda e: V(x, R @ (jnp.eye(3) + hat(e))))(jnp.zeros(3))])
    return g


def check_effect(model, name, rng, n=3):
    """The effect's own terms in ``model``: closed-form gradient = autodiff, forces' power as claimed."""
    effect = EFFECTS[name]
    own = set(model.terms_of(name))
    checked = 0
    for _ in range(n):
        x, R, w = (jnp.asarray(a) for a in random_state(model, rng))
        for term in own & set(model.potential_terms):
            V, dV = model.potential_terms[term], model.potential_gradients[term]
            closed, auto = dV(x, R), autodiff_gradient(model, V, x, R)
            assert closed.shape == (model.layout.nw,), term
            np.testing.assert_allclose(closed, auto, rtol=1e-11, atol=1e-10 * (1 + float(jnp.abs(auto).max())),
                                       err_msg=f"{name}: {term}")
            checked += 1
        reel = [model.reel_forces[k] for k in own & set(model.reel_forces)]
        string = [model.string_forces[k] for k in own & set(model.string_forces)]
        if reel or string:
            t = float(rng.uniform(0, 2))
            P = sum(float(f(t, x, w)) * float(w[0]) for f in reel) + sum(float(f(t, x, w) @ w) for f in string)
            claimed = effect.power(model, t, x, w)
            assert claimed is not None, f"{name} has forces but claims no power"
            assert P == pytest.approx(float(claimed), rel=1e-11, abs=1e-12), name
            if effect.dissipative:
                assert P <= 1e-14 * (1 + abs(P))
            for f in string:  # string forces act on (s_p, q), never on Ω
                assert np.all(np.asarray(f(t, x, w))[model.layout.omega] == 0.0)
            checked += 1
        body = [model.body_loads[k] for k in own & set(model.body_loads)]
        if body:  # body loads: Q·w (the moment's Ω·M included) is the claimed body power
            assert effect.forcing, f"{name} has body loads but forcing = False"
            t = float(rng.uniform(0, 2))
            P = sum(float(f(t, x, R, w) @ w) for f in body)
            claimed = effect.body_power(model, t, x, R, w)
            assert claimed is not None, f"{name} has body loads but claims no body power"
            assert P == pytest.approx(float(claimed), rel=1e-11, abs=1e-12), name
            if effect.dissipative:
                assert P <= 1e-14 * (1 + abs(P))
            checked += 1
    return checked


@pytest.mark.parametrize("name", list(EFFECTS))
def test_effect_terms_match_autodiff_and_claimed_power(name, rng):
    for scene in scenes_for(name):
        model = build_model(scene)
        check_effect(model, name, rng)
        # the composed totals are the sums of the terms (what every integrator reads)
        x, R, w = (jnp.asarray(a) for a in random_state(model, rng))
        total = sum(np.asarray(g(x, R)) for g in model.potential_gradients.values())
        np.testing.assert_array_equal(np.asarray(model.potential_gradient(x, R)), total)


def test_registry_declarations_are_consistent():
    from reelbench.models.scene import BASE_SCHEMA

    for name, effect in EFFECTS.items():
        assert effect.name == name and all(n in EFFECTS and n != name for n in effect.needs)
        assert effect.dissipative <= effect.forcing  # a dissipative effect has forces
        for section, keys in effect.keys.items():
            for key, spec in keys.items():
                assert not (isinstance(BASE_SCHEMA.get(section), dict) and key in BASE_SCHEMA[section])
                if spec.only_with_effect:  # required by its effect, or an optional key of it (a default)
                    assert (spec.required_by and name in spec.required_by) or spec.default is not None
        for key in effect.plausible:
            section, k = key.split(".")
            assert k in effect.keys.get(section, {}), f"{name} bounds a key it does not own: {key}"


def test_layout_and_terms_follow_the_effects():
    """Forcing effects put W in the state; reel and rigid_body add their coordinates and kinetic terms."""
    full = build_model(scene_with_effects(BUILTIN_FULL, elements=3, axial_damping=0.3))
    plain = build_model(load_scene("fixed_length", elements=3, effects=["elasticity"], angular_velocity=[0, 0, 0]))
    assert full.layout.has_work and full.layout.has_reel and full.layout.has_attitude
    assert not (plain.layout.has_work or plain.layout.has_reel or plain.layout.has_attitude)
    assert set(full.kinetic_terms) == {"T_string", "T_body", "T_reel"} and set(plain.kinetic_terms) == {"T_string", "T_body"}
    assert full.kinetic_terms["T_body"] == full._T_rigid_body and plain.kinetic_terms["T_body"] == plain._T_point_mass
    assert full.terms_of("gravity") == ("V_string_gravity", "V_body_gravity", "V_reel")
    assert full.terms_of("carnot") == ("Q_carnot",) and full.terms_of("axial_damping") == ("Q_axial_damping",)
    assert plain.terms_of("gravity") == ()


def test_energy_scale_is_the_sum_of_its_parts():
    model = build_model(load_scene("retrieval"))
    x, R, w = (jnp.asarray(a) for a in model.initial_state())
    parts = float(model.kinetic(x, R, w)) + sum(abs(float(f(x, R))) for f in model.potential_terms.values())
    gravity = model.g * (model.m_b + model.mu * model.L) * (model.L + np.linalg.norm(model.rho_c)
                                                           + np.linalg.norm(model.r_d) + model.d)
    assert model.energy_scale() == pytest.approx(parts + gravity + abs(model.u) * model.L / model.d, rel=1e-14)
