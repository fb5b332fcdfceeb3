"""The baselines' right-hand side (closed form by default, autodiff selectable), its
Jacobian, one definition of run time for every integrator, the work counts, the XLA options."""

import time

import numpy as np
import pytest

import reelbench.integrators.rhs as rhs_module
from reelbench.benchmark.runs.metrics import work_evals
from reelbench.integrators import Capability, available, get_integrator
from reelbench.models import build_model
from reelbench.models._jax import DEFAULT_XLA_FLAGS, append_xla_flags, jax, jnp, xla_flags

from _helpers import scene_with_effects

# Every effect the autodiff path supports, on and off: rigid body × reel (with its Carnot loss
# and control moment) × (slack + axial damping); gravity and elasticity always.
COMBOS = [["elasticity", "gravity"] + (["rigid_body"] if body else []) + (["reel", "carnot", "reel_control"] if reel else [])
          + (["slack", "axial_damping"] if string else [])
          for body in (False, True) for reel in (False, True) for string in (False, True)]
# compile time dominates at N = 2: low optimisation, same outputs (as in test_closed_form)
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}


def _scene(effects, elements=2):
    extra = {"axial_damping": 0.3} if "axial_damping" in effects else {}
    if "slack" in effects:  # start near the slack threshold: the random states mix slack and taut elements
        extra["stretch"] = 0.99
    return scene_with_effects(effects, elements=elements, **extra)


def _states(model, rng, n=2):
    lay = model.layout
    out = []
    for k in range(n):
        y = model.initial_ode_state().copy()
        y[lay.y_x] += 0.2 * rng.standard_normal(lay.nx)
        y[lay.y_w] += rng.standard_normal(lay.nw)
        if lay.has_attitude:
            q = rng.standard_normal(4)
            y[lay.y_quat] = q / np.linalg.norm(q) * (1.02 if k else 1.0)  # one drifted quaternion
        out.append((float(rng.uniform(0, 1)), jnp.asarray(y)))
    return out


#: the fluid effects with a rigid body whose centre of mass is offset: the body's drag is a body
#: load (a force and its moment on the rotation, depending on R and Ω)
OFF_CENTRE = ["elasticity", "gravity", "rigid_body", "buoyancy", "drag"]


@pytest.mark.parametrize("effects", COMBOS + [OFF_CENTRE], ids="+".join)
def test_closed_form_and_autodiff_rhs_and_jacobians_agree(effects, rng):
    model = build_model(_scene(effects) if effects is not OFF_CENTRE else
                        scene_with_effects(effects, elements=2, attachment_to_com=[0.2, -0.1, 0.3]))

    def both(rhs):
        f = rhs_module.ode_rhs(model, rhs)
        return jax.jit(lambda t, y: (f(t, y), jax.jacfwd(f, argnums=1)(t, y)), compiler_options=FAST_COMPILE)

    cf, ad = both("closed_form"), both("autodiff")
    for t, y in _states(model, rng):
        (f1, J1), (f2, J2) = cf(t, y), ad(t, y)
        assert np.all(np.isfinite(J1))
        scale_f, scale_J = np.abs(f2).max(), np.abs(J2).max()
        np.testing.assert_allclose(f1, f2, rtol=0, atol=1e-11 * scale_f)
        np.testing.assert_allclose(J1, J2, rtol=0, atol=1e-10 * scale_J)


def test_rhs_option_is_validated_and_recorded():
    scene = _scene(["elasticity", "gravity"])
    for name, kw in (("rk45", dict(rtol=1e-4, atol=1e-6)), ("tsit5", dict(dt=0.01))):
        integ = get_integrator(name)
        with pytest.raises(ValueError, match=r"rhs = 'fd' is invalid \(allowed: 'closed_form', 'autodiff'\)"):
            integ.solve(scene, t_end=0.02, rhs="fd", **kw)
    tr = get_integrator("rk45").solve(scene, t_end=0.02, rtol=1e-4, atol=1e-6, rhs="autodiff")
    assert tr.settings["rhs"] == tr.stats["rhs"] == "autodiff"
    tr = get_integrator("rk45").solve(scene, t_end=0.02, rtol=1e-4, atol=1e-6)
    assert tr.settings["rhs"] == tr.stats["rhs"] == "closed_form"


# dopri5 and dopri8 compile two more solves each (~20 s): in the slow set
@pytest.mark.parametrize("name, stages", [("tsit5", 7), pytest.param("dopri5", 7, marks=pytest.mark.slow),
                                          pytest.param("dopri8", 14, marks=pytest.mark.slow)])
def test_explicit_diffrax_rhs_evals_match_a_counting_rhs(name, stages, monkeypatch):
    """stats["rhs_evals"] of the explicit FSAL methods (derived from their steps) = evaluations
    actually made."""
    import reelbench.integrators.diffrax_ode as dx
    from reelbench.integrators.lifecycle import CompileCache

    count = [0]
    plain = rhs_module.ode_rhs

    def counting(model, rhs="closed_form"):
        f = plain(model, rhs)

        def g(t, y):
            jax.debug.callback(lambda t_, y_: count.__setitem__(0, count[0] + 1), t, y)
            return f(t, y)
        return g

    monkeypatch.setattr(rhs_module, "ode_rhs", counting)
    monkeypatch.setattr(dx, "_SOLVES", CompileCache())
    scene = _scene(["elasticity", "gravity"])
    for kw in (dict(rtol=1e-6, atol=1e-8), dict(dt=2e-3)):
        count[0] = 0
        tr = get_integrator(name).solve(scene, t_end=0.1, **kw)
        jax.effects_barrier()
        assert tr.ok and count[0] > 0, kw
        if "dt" in kw:  # exact
            assert tr.stats["rhs_evals"] == count[0], kw
        else:  # the rule counts 2 for an initial-step heuristic diffeqsolve skips (docstring of diffrax_ode)
            assert tr.stats["rhs_evals"] - 2 <= count[0] <= tr.stats["rhs_evals"], kw
    assert tr.stats["rhs_evals"] == (stages - 1) * 50 + 1  # 50 constant steps


def test_the_counting_wrapper_counts_evaluations_and_linearisations():
    """Kvaerno5's counts come from its right-hand side wrapped to count, inside the compiled code,
    its evaluations and its linearisations (a Jacobian, however many tangents it pushes)."""
    from reelbench.integrators.diffrax_ode import _counting

    counts = [0, 0]
    f = _counting(lambda t, y: jnp.sin(y) * t, counts)
    y = jnp.arange(3.0)

    @jax.jit
    def use(y):
        value = f(0.5, y)  # one evaluation
        jac = jax.jacfwd(lambda z: f(0.5, z))(y)  # one Jacobian of three tangents
        _, lin = jax.linearize(lambda z: f(0.5, z), y)  # one more linearisation, applied twice
        return value, jac, lin(y) + lin(2 * y)

    value, jac, applied = use(y)
    jax.effects_barrier()
    np.testing.assert_allclose(jac, np.diag(0.5 * np.cos(np.arange(3.0))))
    assert counts == [1, 2], counts


SLEEP = 0.15


def _settings(integ):
    return dict(dt=0.01) if integ.has(Capability.FIXED_STEP) else dict(rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("name", [n for n in available() if not n.startswith("test_")])
def test_run_time_includes_output_conversion(name, monkeypatch):
    """Turning the integrator's state into the returned Trajectory is part of the run time: a
    `Trajectory` that takes SLEEP s longer to build makes wall_time SLEEP s longer (every
    registered integrator; the constructor is patched wherever an integrator module uses it)."""
    import sys

    import reelbench.integrators.base as base

    integ = get_integrator(name)
    scene = _scene(["elasticity", "gravity"], elements=2)
    kw = dict(t_end=0.02, save_every=0.01, **_settings(integ))
    integ.solve(scene, **kw)  # compile
    plain = min(integ.solve(scene, **kw).stats["wall_time"] for _ in range(2))

    class SlowTrajectory(base.Trajectory):
        def __init__(self, *a, **k):
            time.sleep(SLEEP)
            super().__init__(*a, **k)

    patched = [m for m in list(sys.modules.values()) if getattr(m, "__name__", "").startswith("reelbench.integrators")
               and getattr(m, "Trajectory", None) is base.Trajectory and m is not base]
    for m in patched:
        monkeypatch.setattr(m, "Trajectory", SlowTrajectory)
    tr = integ.solve(scene, **kw)
    assert isinstance(tr, SlowTrajectory), f"{name} builds its Trajectory outside the patched modules"
    assert tr.stats["wall_time"] >= plain + 0.9 * SLEEP, (name, plain, tr.stats["wall_time"])
    assert tr.stats["compile_time"] < SLEEP  # the sleep was not booked as compilation


def test_work_evals_definition():
    assert work_evals({"rhs_evals": 10, "newton_iterations": 5}) == 15
    assert work_evals({"rhs_evals": 10, "jac_evals": 0}) == 10 and work_evals({"newton_iterations": 7}) == 7
    assert work_evals({"rhs_evals": 10, "jac_evals": 2, "lu_decompositions": 9}, ny=67) == 10 + 2 * 67
    assert np.isnan(work_evals({"steps": 3})) and np.isnan(work_evals({"rhs_evals": float("nan")}))
    with pytest.raises(ValueError, match="ny"):
        work_evals({"rhs_evals": 10, "jac_evals": 2})


def test_xla_flags_are_appended_not_clobbered():
    env = {"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false"}
    value = append_xla_flags(DEFAULT_XLA_FLAGS, env)
    assert value.split() == ["--xla_cpu_multi_thread_eigen=false", *DEFAULT_XLA_FLAGS]
    assert append_xla_flags(DEFAULT_XLA_FLAGS, env) == value  # idempotent
    mine = {"XLA_FLAGS": "--xla_backend_extra_options=something_else"}
    assert append_xla_flags(DEFAULT_XLA_FLAGS, mine) == "--xla_backend_extra_options=something_else"  # user wins
    empty = {}
    assert append_xla_flags(DEFAULT_XLA_FLAGS, empty) == DEFAULT_XLA_FLAGS[0] == empty["XLA_FLAGS"]
    # this process: recorded for provenance, with the option unless switched off
    import os

    if os.environ.get("REELBENCH_XLA_DEFAULTS", "1") != "0":
        assert DEFAULT_XLA_FLAGS[0].split("=", 1)[0] in xla_flags()


def test_the_persistent_compile_cache_is_in_the_users_cache_directory_unless_turned_off():
    import os

    from reelbench.models._jax import compile_cache_dir

    home = os.path.expanduser("~")
    assert compile_cache_dir({}) == os.path.join(home, ".cache", "reelbench", "jax")
    assert compile_cache_dir({"XDG_CACHE_HOME": "/x/cache"}) == "/x/cache/reelbench/jax"
    assert compile_cache_dir({"REELBENCH_COMPILE_CACHE": "0", "XDG_CACHE_HOME": "/x"}) is None
    assert compile_cache_dir({"REELBENCH_COMPILE_CACHE": "/elsewhere/jax"}) == "/elsewhere/jax"
    # this process: equinox's runtime checks return NaN unless the user chose otherwise
    assert os.environ.get("EQX_ON_ERROR") in ("nan", "raise", "off", "breakpoint")
    expected = compile_cache_dir()
    assert jax.config.values["jax_compilation_cache_dir"] == expected or expected is None


def test_speed_covers_every_registered_fixed_step_method(monkeypatch):
    """`python -m benchmark speed` takes its methods from the registry, not from a list."""
    from reelbench.benchmark.studies import lgvi_speed
    from reelbench.integrators import registry
    from reelbench.integrators.base import Integrator

    class Probe(Integrator):
        name = "speed_probe"
        capabilities = frozenset({Capability.FIXED_STEP})

        def solve(self, *a, **k):  # pragma: no cover - never run here
            raise NotImplementedError

    registry.register(Probe)
    try:
        methods = lgvi_speed.fixed_step_methods()
        lgvi_speed.check_methods(["speed_probe"])  # named, it is a fixed-step method like the others
    finally:
        registry.unregister(Probe.name)
    # a guest (not the project's own method) is timed only when named: the default is the project's methods
    assert "speed_probe" not in methods and {"lgvi", "tsit5"} <= set(methods)
    assert not {"rk45", "radau", "dop853", "kvaerno5"} & set(methods)
    with pytest.raises(ValueError, match="not a fixed-step method"):
        lgvi_speed.check_methods(["rk45"])


def test_speed_times_each_rhs_per_call():
    """us_per_call is the median of single calls: at least half the calls took that long, so
    calls x median / 2 cannot exceed the wall time of the whole measurement (a total reported
    as per-call would)."""
    from reelbench.benchmark.studies import lgvi_speed

    for rhs in rhs_module.RHS_CHOICES:
        t0 = time.perf_counter()
        r = lgvi_speed.measure_rhs("fixed_length", 2, rhs, calls=20)
        wall_us = (time.perf_counter() - t0) * 1e6
        assert r["rhs"] == rhs and r["calls"] == 20 and r["compile_s"] > 0
        assert 0 < r["us_per_call"] and r["calls"] * r["us_per_call"] / 2 <= wall_us, (r, wall_us)
