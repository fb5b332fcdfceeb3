"""The integrator API keeps the command line's rules: refusals before any work, budgets that
end in statuses, compile caches keyed by what the code depends on and bounded, metadata without
JAX, and the code shape the lifecycle promises (short functions)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from reelbench.integrators import (IMPLEMENTATIONS, FixedStepMethod, Status, available, get_integrator)
from reelbench.integrators import fixed_step, lifecycle
from reelbench.models import load_scene

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def small():
    return load_scene("fixed_length", elements=2)


# ------------------------------------------------------------------------------------------
# Refusals, each before any work
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, kwargs, match", [
    ("lgvi", dict(dt=1e-3, rtol=1e-6), r"fixed-step method: rtol/atol do not apply"),
    ("lgvi_suzuki4", dict(dt=1e-3, atol=1e-8), r"rtol/atol do not apply"),
    ("lgvi", dict(dt=1e-3, rhs="autodiff"), r"rhs = 'autodiff' does not apply"),
    ("tsit5", dict(dt=1e-3, rtol=1e-6, atol=1e-8), r"tsit5 takes dt \(constant step\) or rtol and atol .* not both"),
    ("dopri8", dict(dt=1e-3, rtol=1e-6, atol=1e-8), r"not both"),
    ("dop853", dict(t_end=0.1, dt=5.0, rtol=1e-6, atol=1e-8), r"the first step dt = 5.0 is larger than t_end = 0.1"),
    ("lgvi", dict(t_end=0.1, dt=5.0), r"dt = 5.0 is larger than t_end = 0.1"),
    ("rk45", dict(t_end=0.1, save_every=0.5, rtol=1e-6, atol=1e-8), r"save_every = 0.5 is larger than t_end = 0.1"),
    ("lgvi", dict(t_end=0.1, save_every=0.5, dt=1e-3), r"save_every = 0.5 is larger than t_end"),
    ("tsit5", dict(t_end=1e12, dt=1e-3), r"t_end = 1e\+12 is implausible \(allowed: 0 < t_end <= 1e\+06 s"),
    ("dop853", dict(t_end=1e12, rtol=1e-6, atol=1e-8), r"t_end = 1e\+12 is implausible"),
    ("lgvi", dict(t_end=1e5, dt=1e-5), r"would take 1e\+10 steps \(allowed: at most 1e\+09\)"),
    ("rk45", dict(t_end=1e5, save_every=1e-5, rtol=1e-6, atol=1e-8), r"GiB; allowed: at most 8 GiB"),
    ("lgvi", dict(dt=1e-3, time_limit=-1.0), r"time_limit = -1.0 is invalid"),
    ("rk45", dict(rtol=1e-6, atol=1e-8, time_limit=0), r"time_limit = 0 is invalid"),
    ("tsit5", dict(dt=1e-3, max_steps=2.5), r"max_steps = 2.5 is invalid"),
])
def test_solve_refuses_what_the_command_line_refuses(small, name, kwargs, match, monkeypatch):
    kwargs.setdefault("t_end", 0.1)
    # "before any work": the model is never built
    monkeypatch.setattr(lifecycle, "build_model_timed", lambda scene: pytest.fail("work was done"))
    with pytest.raises(ValueError, match=match):
        get_integrator(name).solve(small, **kwargs)


def test_a_class_says_what_the_method_is_and_the_studies_choose_where_it_runs():
    """Study settings live in each study's table keyed by method name, not on the class; every
    name a table lists is one of the project's methods, and every method of the energy study's
    plan has its setting there."""
    from reelbench.benchmark.runs import sweep
    from reelbench.benchmark.studies import horizon, stability
    from reelbench.integrators import registry

    for name in available():
        for attr in ("horizon_settings", "paper_settings", "sweep_rtols", "default_sweep", "expensive"):
            assert not hasattr(get_integrator(name), attr), (name, attr)
    planned = {name for _, name, _, _ in horizon.PLAN}
    assert planned <= set(horizon.SETTINGS)
    listed = {*sweep.EXTENDED_METHODS, *sweep.SWEEP_RTOLS, sweep.PAPER_METHOD.name, *horizon.SETTINGS, *planned,
              *stability.EXPENSIVE}
    assert listed <= set(registry.own())


def test_the_horizon_bound_is_the_scene_files():
    from reelbench.models.scene import PLAUSIBLE

    assert lifecycle.T_END_MAX == PLAUSIBLE["t_end"][1]


@pytest.mark.parametrize("name", [None, 123, 1.5, ["lgvi"]])
def test_get_integrator_refuses_a_name_that_is_not_a_string(name):
    with pytest.raises(ValueError, match=r"integrator name = .* is invalid \(allowed: a string, one of: .*lgvi"):
        get_integrator(name)


def test_get_integrator_takes_no_constructor_options():
    with pytest.raises(TypeError, match="bogus"):
        get_integrator("lgvi", bogus=1)


# ------------------------------------------------------------------------------------------
# Budgets end in statuses
# ------------------------------------------------------------------------------------------
def test_time_limit_ends_a_compiled_fixed_step_run_and_keeps_its_prefix(small):
    lgvi = get_integrator("lgvi")
    full = lgvi.solve(small, t_end=200.0, dt=1e-3, save_every=0.1)  # one call, no chunks (~1 s)
    assert full.ok, full.reason
    cut = lgvi.solve(small, t_end=200.0, dt=1e-3, save_every=0.1, time_limit=0.05)
    assert cut.status == Status.TIME_LIMIT.value, cut.reason
    assert "stopped by time_limit = 0.05 s" in cut.reason and "kept up to" in cut.reason
    assert 1 <= len(cut) < len(full) and cut.stats["steps"] < full.stats["steps"]
    # the chunked run is the same computation: its saved states are the full run's, bit for bit
    np.testing.assert_array_equal(cut.x, full.x[: len(cut)])
    np.testing.assert_array_equal(cut.momentum, full.momentum[: len(cut)])
    # and a generous limit changes nothing
    roomy = lgvi.solve(small, t_end=200.0, dt=1e-3, save_every=0.1, time_limit=1e4)
    assert roomy.ok and roomy.stats["steps"] == full.stats["steps"]
    np.testing.assert_array_equal(roomy.x, full.x)


@pytest.mark.parametrize("name, kw", [("rk45", dict(rtol=1e-10, atol=1e-12)), ("tsit5", dict(dt=1e-4))])
def test_time_limit_ends_an_adapter_run(small, name, kw):
    integ = get_integrator(name)
    integ.solve(small, t_end=0.01, save_every=0.005, **kw)  # compile (diffrax: the untimed solve)
    tr = integ.solve(small, t_end=50.0, save_every=0.5, time_limit=0.05, **kw)
    assert tr.status == Status.TIME_LIMIT.value, tr.reason
    assert "time_limit = 0.05 s" in tr.reason
    assert tr.t[-1] < 50.0 and np.all(np.isfinite(tr.x))


def test_scipy_has_a_default_step_budget_and_max_steps_ends_in_its_status(small):
    from reelbench.integrators.scipy_ivp import DEFAULT_MAX_STEPS

    tr = get_integrator("dop853").solve(small, t_end=0.05, rtol=1e-6, atol=1e-8)
    assert tr.ok and tr.settings["max_steps"] == DEFAULT_MAX_STEPS
    cut = get_integrator("dop853").solve(small, t_end=1.0, rtol=1e-10, atol=1e-12, max_steps=7)
    assert cut.status == Status.MAX_STEPS.value and cut.stats["steps"] == 7 and "max_steps = 7" in cut.reason


# ------------------------------------------------------------------------------------------
# Compile caches
# ------------------------------------------------------------------------------------------
class Relaxed(FixedStepMethod):
    """Forward Euler with a constructor option (test only): y + weight h f(t, y)."""

    name = "test_relaxed"
    order = 1

    def __init__(self, weight: float):
        self.weight = weight

    def step(self, ode, y, t, h):
        return y + self.weight * h * ode.f(t, y)


def test_two_configurations_of_one_class_do_not_share_a_compiled_loop(small):
    a, b = Relaxed(1.0), Relaxed(0.5)
    assert a.loop_key() != b.loop_key() and Relaxed(1.0).loop_key() == a.loop_key()
    ta = a.solve(small, t_end=0.01, dt=1e-3, save_every=0.005)
    tb = b.solve(small, t_end=0.01, dt=1e-3, save_every=0.005)
    assert ta.ok and tb.ok and tb.stats["compile_time"] > 0  # compiled its own loop
    assert not np.allclose(ta.velocity, tb.velocity)  # and ran its own weight
    # a half-weight Euler step moves the velocities half as far from the start
    dv_a, dv_b = ta.velocity[1] - ta.velocity[0], tb.velocity[1] - tb.velocity[0]
    assert np.abs(dv_b).max() < 0.9 * np.abs(dv_a).max()
    again = Relaxed(0.5).solve(small, t_end=0.01, dt=1e-3, save_every=0.005)
    assert again.stats["compile_time"] < tb.stats["compile_time"] / 2  # same configuration: cached
    np.testing.assert_array_equal(again.x, tb.x)


def test_compile_caches_are_bounded_least_recently_used_first_out():
    cache = lifecycle.CompileCache(maxsize=2)
    built = []
    for key in ("a", "b", "a", "c"):  # "a" is used again before "c" comes: "b" goes
        value, seconds = cache.get(key, lambda k=key: built.append(k) or k.upper())
        assert value == key.upper() and seconds >= 0
    assert built == ["a", "b", "c"] and len(cache) == 2 and "a" in cache and "b" not in cache
    from reelbench.integrators import diffrax_ode, lgvi

    for c in (fixed_step._LOOPS, lgvi._VELOCITY, diffrax_ode._SOLVES):
        assert isinstance(c, lifecycle.CompileCache) and c.maxsize <= 64


def test_the_loop_cache_holds_the_model_structure_not_its_id(small):
    """A loop is keyed by what it depends on, the model's structure (its numbers are run-time
    arguments), never by an object id that a later model may reuse."""
    from reelbench.models import build_model

    get_integrator("lgvi").solve(small, t_end=0.01, dt=1e-3)
    model = build_model(small)
    keys = list(fixed_step._LOOPS._entries)
    assert any(k[1] == model.structure_key() for k in keys)
    assert not any(isinstance(part, int) and part == id(model) for k in keys for part in k)


# ------------------------------------------------------------------------------------------
# Metadata without JAX
# ------------------------------------------------------------------------------------------
def test_every_method_declares_how_it_runs():
    for name in available():
        integ = get_integrator(name)
        if name.startswith("test_"):
            continue
        assert integ.implementation in IMPLEMENTATIONS, (name, integ.implementation)
        expected = "scipy-python" if type(integ).__module__ == "reelbench.integrators.scipy_ivp" else "jax-compiled"
        assert integ.implementation == expected, name


def test_names_and_declarations_need_no_jax():
    code = ("import sys, integrators\n"
            "names = integrators.available()\n"
            "rows = [(n, i.description, i.order, sorted(c.value for c in i.capabilities), i.implementation)\n"
            "        for n in names for i in [integrators.get_integrator(n)]]\n"
            "assert {'lgvi', 'rk45', 'dopri5', 'dopri8', 'kvaerno5'} <= set(names), names\n"
            "assert not integrators.plugin_errors(), integrators.plugin_errors()\n"
            "print(sorted(m for m in ('jax', 'diffrax', 'scipy.integrate') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_no_function_in_integrators_is_longer_than_60_lines():
    long = []
    for path in sorted((ROOT / "integrators").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if node.end_lineno - node.lineno + 1 > 60:
                    long.append(f"{path.name}:{node.lineno} {node.name}")
    assert not long, long


class Poisoned(FixedStepMethod):
    """A step that turns the state into NaN after a while (test only)."""

    name = "test_poisoned"
    order = 1

    def step(self, ode, y, t, h):
        from reelbench.models._jax import jnp

        return jnp.where(t >= 0.0049, jnp.nan, y + h * ode.f(t, y))


def test_a_non_finite_state_stops_the_run_at_that_step(small):
    tr = Poisoned().solve(small, t_end=0.02, dt=1e-3, save_every=0.002)
    assert tr.status == Status.DIVERGED.value and "non-finite or blown-up state" in tr.reason, tr.reason
    assert tr.stats["steps"] == 5 and "step 6 " in tr.reason
    # the saved points before it, and the last good state (step 5) after them
    np.testing.assert_allclose(tr.t, [0.0, 0.002, 0.004, 0.005], atol=1e-15)
    assert np.all(np.isfinite(tr.x)) and np.all(np.isfinite(tr.velocity))


class PoisonedCarry(FixedStepMethod):
    """`Poisoned` with a carry of (state, step count) and a saved state that is either the carry's
    own leaf or computed from it (``copy``): either way a failed step keeps the last good state."""

    name = "test_poisoned_carry"
    order = 1
    copy = False

    def init(self, ode, y0):
        from reelbench.models._jax import jnp

        return y0, jnp.zeros(())

    def step(self, ode, carry, t, h):
        from reelbench.models._jax import jnp

        y, n = carry
        return jnp.where(t >= 0.0049, jnp.nan, y + h * ode.f(t, y)), n + 1.0

    def state(self, ode, carry):
        return 1.0 * carry[0] if self.copy else carry[0]


@pytest.mark.parametrize("copy", [False, True])
def test_a_failed_step_keeps_the_last_good_state_whatever_saved_returns(small, copy):
    method = PoisonedCarry()
    method.copy = copy
    tr = method.solve(small, t_end=0.02, dt=1e-3, save_every=0.002)
    good = Poisoned().solve(small, t_end=0.02, dt=1e-3, save_every=0.002)
    assert tr.status == Status.DIVERGED.value and tr.stats["steps"] == 5
    np.testing.assert_allclose(tr.t, [0.0, 0.002, 0.004, 0.005], atol=1e-15)
    np.testing.assert_array_equal(tr.x, good.x)
    assert np.all(np.isfinite(tr.velocity))
