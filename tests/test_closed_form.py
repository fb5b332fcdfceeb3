"""Closed-form equations of motion (models.closed_form) vs the model's autodiff path.

Runtime (< 60 s on 2 cores): XLA compile time dominates (≈1.5 s per function even at small
N), so each case compiles only the autodiff reference, once (one jit returning M, p and the
ODE right-hand side, at XLA optimisation level 0, without the CPU fusion emitters), and the closed form runs eagerly (a
warm-up per state layout only). The closed form's own `ode_rhs_jit` is compiled once.
(Compiling the references ahead in a background thread was tried: no overlap was gained.)
"""

import io
import tokenize

import numpy as np
import pytest

from reelbench.models import build_model
from reelbench.models._jax import jax, jnp
from reelbench.models.closed_form import ClosedFormEOM
import reelbench.models.closed_form as closed_form_module

from _helpers import effect_combinations, fluid_combinations, scene_with_effects

RTOL = 1e-10
FULL = ["elasticity", "gravity", "rigid_body", "reel", "carnot", "reel_control"]


SWEEP_ELEMENTS = 2


def _reference(model):
    """Autodiff (M, p, ẏ) at an ODE state y, compiled once per model."""

    def f(t, y):
        x, R, w, _ = model.split_state(y)
        return model.mass_matrix(x, R), model.momentum(x, R, w), model.ode_rhs(t, y)

    # both options only cut compile time (≈2×); the outputs are bit-identical at N = 2
    return jax.jit(f, compiler_options={"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False})


def _random_states(model, rng, n=3, scale=0.2):
    """ODE states near the initial one: random x, w, quaternion (one of norm ≠ 1), work."""
    lay = model.layout
    y0 = model.initial_ode_state()
    out = []
    for k in range(n):
        y = y0.copy()
        y[lay.y_x] += scale * rng.standard_normal(lay.nx)
        y[lay.y_w] += rng.standard_normal(lay.nw)
        if lay.has_attitude:
            quat = rng.standard_normal(4)
            # R(quat) is not renormalised by the baselines: include a drifted quaternion
            y[lay.y_quat] = quat / np.linalg.norm(quat) * (1.03 if k == n - 1 else 1.0)
        if lay.has_work:
            y[lay.y_work] = rng.standard_normal()
        out.append((float(rng.uniform(0.0, 2.0)), jnp.asarray(y)))
    return out


def _rel_err(auto, closed):
    auto, closed = np.asarray(auto), np.asarray(closed)
    return np.abs(auto - closed).max() / max(np.abs(auto).max(), 1e-300)


def _closed_form_values(model, c, t, y, dense):
    x, R, w, _ = model.split_state(y)
    out = dict(M=c.mass_matrix(x, R), p=c.momentum(x, R, w), rhs=c.ode_rhs(t, y))
    if dense:  # dense solve of the closed-form M (cross-checks the structured solve)
        out["acc_dense"] = c.accelerations_dense(t, x, R, w)
    return out


def _check(model, variants, rng, n=2, dense=False):
    """Closed form (eager) vs the autodiff reference, on n random states."""
    lay = model.layout
    states = _random_states(model, rng, n=n)
    closed = [[_closed_form_values(model, c, t, y, dense) for t, y in states] for c in variants]
    ref = _reference(model)
    for (t, y), *per_variant in zip(states, *closed):
        M_a, p_a, rhs_a = ref(t, y)
        x, R, w, _ = model.split_state(y)
        acc_a = rhs_a[lay.y_w]
        for c, v in zip(variants, per_variant):
            errs = {
                "mass_matrix": _rel_err(M_a, v["M"]),
                "momentum": _rel_err(p_a, v["p"]),
                "accelerations": _rel_err(acc_a, v["rhs"][lay.y_w]),  # = c.accelerations(t, x, R, w)
                "ode_rhs": _rel_err(rhs_a, v["rhs"]),
                "velocity_from_momentum": _rel_err(w, c.velocity_from_momentum(x, R, p_a)),
            }
            if dense:
                errs["accelerations_dense"] = _rel_err(acc_a, v["acc_dense"])
            bad = {k: f"{e:.1e}" for k, e in errs.items() if not e < RTOL}
            assert not bad, f"tri_solve={c.tri_solve}: {bad}"
    return ref


@pytest.mark.parametrize("effects", effect_combinations() + fluid_combinations(), ids=lambda e: "+".join(e))
def test_closed_form_matches_autodiff(effects, rng):
    model = build_model(scene_with_effects(effects, elements=SWEEP_ELEMENTS))
    cf = ClosedFormEOM(model)
    ref = _check(model, [cf], rng)
    x, R, w = (jnp.asarray(v) for v in model.initial_state())
    M = np.asarray(cf.mass_matrix(x, R))
    np.testing.assert_allclose(M, M.T, atol=1e-14)
    if effects == FULL:  # the compiled entry point, once
        assert cf.ode_rhs_jit is cf.ode_rhs_jit
        for t, y in _random_states(model, rng, n=2):
            assert _rel_err(ref(t, y)[2], cf.ode_rhs_jit(t, y)) < RTOL


@pytest.mark.parametrize("mass_model", ["consistent", "lumped"])
def test_closed_form_matches_autodiff_with_an_off_centre_drag(mass_model, rng):
    """The body's drag at an offset centre of mass is a body load (a force and its moment on the
    rotation, depending on R and Ω): the closed form takes it as the autodiff path does."""
    effects = ["elasticity", "gravity", "rigid_body", "buoyancy", "drag"]
    model = build_model(scene_with_effects(effects, elements=SWEEP_ELEMENTS, attachment_to_com=[0.2, -0.1, 0.3],
                                           mass_model=mass_model))
    assert model.body_loads
    _check(model, [ClosedFormEOM(model)], rng)


@pytest.mark.parametrize("elements", [1, 4])
def test_structured_solve_sizes_and_variants(elements, rng):
    """N = 1 (no interior nodes) and 5 (N = 2 is the sweep above); both interior solvers."""
    model = build_model(scene_with_effects(FULL, elements=elements))
    variants = [ClosedFormEOM(model, tri_solve=s) for s in ("dense", "doubling")]
    _check(model, variants, rng, dense=True)


def test_closed_form_uses_no_autodiff():
    """No jax.grad / jacfwd / jvp … in the module's code (docstrings and comments aside)."""
    src = open(closed_form_module.__file__, encoding="utf-8").read()
    names = {tok.string for tok in tokenize.generate_tokens(io.StringIO(src).readline) if tok.type == tokenize.NAME}
    assert not names & {"grad", "value_and_grad", "jacfwd", "jacrev", "jacobian", "hessian", "jvp", "vjp", "linearize"}


def test_bad_tri_solve_option_is_rejected():
    model = build_model(scene_with_effects(["elasticity"], elements=2))
    with pytest.raises(ValueError, match="tri_solve"):
        ClosedFormEOM(model, tri_solve="banded")


#: compile options that only cut compile time (as in _reference)
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}


@pytest.mark.parametrize("diag, off", [(4.0, 1.0), (2.0, 0.0), (3.0, -1.0)], ids=["consistent", "lumped", "negative_off"])
def test_toeplitz_interior_solve_matches_dense_solve(diag, off, rng):
    """scale·T⁻¹B by Sherman–Morrison and recursive doubling = numpy's dense solve, to round-off,
    for sizes below and past the 2^J = 32 where doubling stops adding terms (tri(1, 4, 1))."""
    for n, k in ((1, 3), (7, 6), (33, 3), (200, 3)):
        solver = closed_form_module.ToeplitzTridiagonal(diag, off, n)
        T = diag * np.eye(n) + off * (np.eye(n, k=1) + np.eye(n, k=-1))
        B = rng.standard_normal((n, k))
        solve = jax.jit(lambda b: solver.solve(b, k, 0.37), compiler_options=FAST_COMPILE)
        X = np.asarray(solve(jnp.asarray(B.ravel()))).reshape(n, k)
        expected = 0.37 * np.linalg.solve(T, B)
        assert np.abs(X - expected).max() <= 1e-15 * np.abs(expected).max(), (n, k)
        np.testing.assert_allclose(solver.solve_numpy(B[:, 0]), np.linalg.solve(T, B[:, 0]), rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="diagonal dominance"):
        closed_form_module.ToeplitzTridiagonal(2.0, 1.0, 5)


@pytest.mark.parametrize("effects", [["elasticity", "gravity", "rigid_body"], FULL], ids="+".join)
def test_structured_solve_matches_dense_solve_at_many_elements(effects, rng):
    """At N = 80 (79 interior nodes, past the doubling's cut-off) the O(N) solve = a dense solve of
    the closed-form M (itself equal to autodiff's, tests above), and so does the Legendre map."""
    model = build_model(scene_with_effects(effects, elements=80))
    cf = ClosedFormEOM(model)

    def both(t, y):
        x, R, w, _ = model.split_state(y)
        return (cf.accelerations_dense(t, x, R, w), cf.accelerations(t, x, R, w),
                cf.velocity_from_momentum(x, R, cf.momentum(x, R, w)))

    (t, y), = _random_states(model, rng, n=1)
    dense, structured, w_back = jax.jit(both, compiler_options=FAST_COMPILE)(t, y)
    assert _rel_err(dense, structured) < 1e-12
    assert _rel_err(model.split_state(y)[2], w_back) < 1e-12


def test_right_hand_side_in_a_loop_calls_no_library():
    """The closed form inside a compiled loop holds no custom call (LAPACK): XLA's CPU backend
    then compiles the whole loop as one function (models._jax, this module's docstring); with
    the project's XLA option on, the loop is hoisted so ("xla_cpu_small_call")."""
    import os

    model = build_model(scene_with_effects(FULL, elements=4))
    f = ClosedFormEOM(model).ode_rhs
    y0 = jnp.asarray(model.initial_ode_state())
    hlo = jax.jit(lambda y: jax.lax.fori_loop(0, 3, lambda i, y: y + 1e-9 * f(0.0, y), y)).lower(y0).compile().as_text()
    assert "custom-call" not in hlo
    if os.environ.get("REELBENCH_XLA_DEFAULTS", "1") != "0":
        assert "xla_cpu_small_call" in hlo
