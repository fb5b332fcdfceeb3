"""The one-unit work column: flops from XLA's cost model times a run's counts."""

import math

import numpy as np
import pytest

from reelbench.benchmark.work import flops
from reelbench.models import build_model, load_scene


@pytest.fixture(scope="module")
def model():
    return build_model(load_scene("fixed_length", elements=3))


# ---- the rule on hand-countable methods -----------------------------------------------------
# XLA's convention: a matrix-vector product of n × n by n is 2n² flops (a multiply and an add per
# entry), an elementwise vector operation n, a scalar one 1.
def _linear_methods(n):
    """Explicit Euler, classical RK4 and a 3-iteration fixed-point implicit Euler on y' = A y
    (A a fixed n × n matrix), as fixed-step methods with their own equations."""
    from reelbench.integrators import FixedStepMethod
    from reelbench.models._jax import jax, jnp

    A = jnp.asarray(np.random.default_rng(0).normal(size=(n, n)))

    class Base(FixedStepMethod):
        order, uses_rhs, rhs_label, description = 1, False, "linear", "a linear test field"

    class Euler(Base):
        name = "test_linear_euler"

        def step(self, ode, y, t, h):
            return y + h * (A @ y)

    class RK4(Base):
        name = "test_linear_rk4"

        def step(self, ode, y, t, h):
            k1 = A @ y
            k2 = A @ (y + 0.5 * h * k1)
            k3 = A @ (y + 0.5 * h * k2)
            k4 = A @ (y + h * k3)
            return y + (h / 6) * (k1 + 2 * k2 + 2 * k3 + k4)

    class FixedPoint(Base):
        name = "test_linear_fixed_point"

        def step(self, ode, y, t, h):  # z <- y + h A z, a Newton-like loop of 3 trips
            return jax.lax.while_loop(lambda c: c[0] < 3, lambda c: (c[0] + 1, y + h * (A @ c[1])), (0, y))[1]

    return Euler, RK4, FixedPoint


def test_the_flop_rule_equals_the_hand_count_of_euler_rk4_and_a_newton_like_loop(model):
    from reelbench.integrators import registry

    n = model.layout.ny
    classes = _linear_methods(n)
    for cls in classes:
        registry.register(cls)
    try:
        euler, _ = flops.run_flops("test_linear_euler", model, {"steps": 100}, None)
        assert euler == 100 * (2 * n * n + 2 * n)  # A y; h × it; y + it
        # 4 products A(.), 3 stage inputs (scale, add), the combination (2k2, 2k3, 3 adds,
        # scale, add), and the scalars 0.5 h (twice) and h / 6
        rk4, _ = flops.run_flops("test_linear_rk4", model, {"steps": 100}, None)
        assert rk4 == 100 * (4 * 2 * n * n + 3 * 2 * n + 7 * n + 3)
        # a while loop at its measured trips (3 per step from the run's iteration count): each
        # trip a product, a scale, an add and the counter's increment; the loop's condition
        # (one comparison) counted once, as XLA does
        loop, note = flops.run_flops("test_linear_fixed_point", model, {"steps": 10, "newton_iterations": 30}, None)
        assert loop == 10 * (3 * (2 * n * n + 2 * n + 1) + 1) and note == flops.FROM_STEP
    finally:
        for cls in classes:
            registry.unregister(cls.name)


@pytest.mark.slow  # compiles a diffrax step twice and scipy's twin: over a minute on a loaded machine
def test_every_rhs_method_is_charged_its_whole_step_not_its_evaluations(model):
    """lie_rk4: its whole compiled step is charged (at N = 10 14,993 flops by XLA), not 4 × one
    isolated right-hand side (the old rule's 5,520); the diffrax and scipy pairs likewise per
    attempted step, Tsit5's controller included when adaptive."""
    m = model
    rk4, note = flops.run_flops("lie_rk4", m, {"steps": 10, "rhs_evals": 40}, "closed_form")
    assert note == flops.FROM_STEP and rk4 / 10 == flops.step_cost("lie_rk4", m, "closed_form")[0]
    assert rk4 / 10 > 4 * flops.rhs_flops(m, "closed_form")
    fixed, note = flops.run_flops("tsit5", m, {"steps": 10, "attempted_steps": 10, "rhs_evals": 61}, "closed_form")
    adaptive, _ = flops.run_flops("tsit5", m, {"steps": 10, "attempted_steps": 10, "rhs_evals": 63}, "closed_form")
    assert note == flops.FROM_DIFFRAX and adaptive - 2 * flops.rhs_flops(m, "closed_form") > fixed  # + controller
    twin, note = flops.run_flops("rk45", m, {"steps": 8, "rejected_steps": 2, "rhs_evals": 63}, "closed_form")
    assert note == flops.FROM_TWIN
    assert twin == pytest.approx(10 * flops.scipy_twin_step("rk45", m, "closed_form")
                                 + 3 * flops.rhs_flops(m, "closed_form"))


def test_rhs_flops_scale_with_the_evaluations(model):
    one, note = flops.run_flops("radau", model, {"rhs_evals": 100, "steps": 16}, "closed_form")
    two, _ = flops.run_flops("radau", model, {"rhs_evals": 200, "steps": 32}, "closed_form")
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
    from reelbench.models._jax import jax, jnp

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
    from reelbench.models._jax import jax, jnp

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


def test_a_count_kept_on_disk_is_the_traced_count(model, tmp_path, monkeypatch):
    """Counts are kept beside the compiled programs: one read back equals one traced, a plugin's
    step (code outside the hashed source) is never kept, and the compile cache's switch turns
    the keeping off."""
    from reelbench.integrators import registry

    monkeypatch.setenv("REELBENCH_CACHE", str(tmp_path))
    monkeypatch.delenv("REELBENCH_COMPILE_CACHE", raising=False)
    fresh = [flops._tupled(f.__wrapped__.__wrapped__(*args)) for f, args in ((flops.step_cost, ("lgvi", model, None)),
                                                   (flops.rhs_flops, (model, "closed_form")))]
    for f, args in ((flops.step_cost, ("lgvi", model, None)), (flops.rhs_flops, (model, "closed_form"))):
        f.cache_clear()
        written = f(*args)
        f.cache_clear()
        assert f(*args) == written
    assert [flops.step_cost("lgvi", model, None), flops.rhs_flops(model, "closed_form")] == fresh
    assert len(list((tmp_path / "flops").glob("*.json"))) == 2
    _, rk4, _ = _linear_methods(model.layout.ny)
    registry.register(rk4)
    try:
        assert flops._count_path("step_cost", (rk4.name, model, None)) is None
    finally:
        registry.unregister(rk4.name)
    monkeypatch.setenv("REELBENCH_COMPILE_CACHE", "0")
    assert flops._count_path("rhs_flops", (model, "closed_form")) is None
    for f in (flops.step_cost, flops.rhs_flops):
        f.cache_clear()
