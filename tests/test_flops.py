"""The one-unit work column: flops from XLA's cost model times a run's counts."""

import math

import numpy as np
import pytest

from benchmark import flops
from models import build_model, load_scene


@pytest.fixture(scope="module")
def model():
    return build_model(load_scene("fixed_length", elements=3))


def test_rhs_flops_scale_with_the_evaluations(model):
    one, note = flops.run_flops("rk45", model, {"rhs_evals": 100, "steps": 16}, "closed_form")
    two, _ = flops.run_flops("rk45", model, {"rhs_evals": 200, "steps": 32}, "closed_form")
    assert one > 0 and two == pytest.approx(2 * one) and note == flops.FROM_RHS
    f_eval, f_jac = flops.rhs_flops(model, "closed_form"), flops.rhs_flops(model, "closed_form", True)
    assert one == pytest.approx(100 * f_eval) and f_jac > f_eval > 0
    ny = model.layout.ny
    with_jac, _ = flops.run_flops("radau", model, {"rhs_evals": 100, "jac_evals": 2, "lu_decompositions": 3},
                                  "closed_form")
    assert with_jac == pytest.approx(one + 2 * f_jac + 3 * (2 / 3) * ny ** 3)


def test_lgvi_flops_scale_with_steps_and_newton_iterations(model):
    one, note = flops.run_flops("lgvi", model, {"steps": 100, "newton_iterations": 200}, None)
    two, _ = flops.run_flops("lgvi", model, {"steps": 200, "newton_iterations": 400}, None)
    more_newton, _ = flops.run_flops("lgvi", model, {"steps": 100, "newton_iterations": 300}, None)
    assert one > 0 and two == pytest.approx(2 * one) and note == flops.FROM_STEP
    # one more Newton iteration per step costs one more pass through the loop body
    base, terms, uneven = flops.step_cost("lgvi", model)
    assert not uneven  # the fixed-length step has no branch taken only sometimes
    newton = [t for t in terms if t[0] == "while"]
    assert len(newton) == 1 and more_newton == pytest.approx(one + 100 * newton[0][2])


def test_loop_terms_multiply_a_scan_by_its_length():
    from models._jax import jax, jnp

    def f(x):
        return jax.lax.scan(lambda c, _: (c * 1.5 + 2.0, None), x, None, length=10)[0]

    closed = jax.make_jaxpr(f)(jnp.ones(100))
    terms = flops.loop_terms(closed)
    assert [(k, n) for k, n, _, _ in terms] == [("scan", 10)]
    total = flops._body_flops(closed) + flops.extra_flops(terms, 1.0)
    assert total == pytest.approx(10 * terms[0][2], rel=0.05)  # the body (200 flops) ten times


def test_an_uneven_cond_is_found_and_said(model):
    """A cond whose branches differ in cost (a fallback beside a no-op) is counted at its costlier
    branch on every step: found, and the note says that the count is an upper bound."""
    from models._jax import jax, jnp

    def f(pred, x):
        return jax.lax.cond(pred, lambda y: jnp.outer(y, y) @ (jnp.outer(y, y) @ y), lambda y: y, x)

    def g(pred, x):
        return jax.lax.cond(pred, lambda y: 2.0 * y, lambda y: 3.0 * y, x)

    assert flops.has_uneven_cond(jax.make_jaxpr(f)(True, jnp.ones(30)))
    assert not flops.has_uneven_cond(jax.make_jaxpr(g)(True, jnp.ones(30)))
    _, note = flops.run_flops("rattle", model, {"steps": 10, "newton_iterations": 30}, None)
    assert "upper bound" in note
    _, note = flops.run_flops("lgvi", model, {"steps": 10, "newton_iterations": 30}, None)
    assert "upper bound" not in note


def test_a_run_without_counts_gets_a_reason_not_a_zero(model):
    value, note = flops.run_flops("kvaerno5", model, {"steps": 10, "counts_unavailable": "diffrax hides them"},
                                  "closed_form")
    assert math.isnan(value) and "diffrax hides them" in note
    value, note = flops.run_flops("rk45", model, {"steps": 10}, "closed_form")
    assert math.isnan(value) and note.startswith("no flops")
    assert np.isnan(flops.run_flops("no_such_method", model, {"steps": 10}, None)[0])
